"""The run store: every render job, training and evaluation is a directory with a `run.json`.

A run is identified by a hash of the part of its config that determines its result (its *identity*:
model arguments, data spec, training schedule, seed, ...), not by paths, worker counts or labels. A run
whose hash is recorded with status "complete" is reused instead of recomputed; `force=True` recomputes.
An interrupted run keeps its directory (status "running"), so whatever it checkpointed can be resumed.
While a process computes a run it holds an exclusive lock (the file `.<hash>.lock` beside the run's
directory): a second process (another table, another shard of a sweep) that asks for the same run waits
for it and then reuses it.

A run also records the fingerprint of the code that determines its result (`code_fingerprint`: the
project modules it runs, transitively). It is checked at reuse rather than hashed into the identity, so
that a change to one model's file makes that model's runs stale, not every run, and so that the message
can name the changed file: a stale run is recomputed (`begin(..., reuse_stale=True)` reuses it anyway).

Layout: ``<runs_dir>/<kind>/<hash>/run.json`` plus the run's own artifacts beside it.
`load()` turns every record into one tidy DataFrame, from which tables are views.
"""
from __future__ import annotations

import ast
import contextlib
import errno
import fcntl
import functools
import getpass
import gzip
import hashlib
import importlib.metadata
import json
import logging
import math
import os
import pickle
import platform
import shutil
import socket
import subprocess
import tempfile
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from bench.atomic import write_atomic

log = logging.getLogger("bench")

RECORD = "run.json"
# In every training and evaluation identity: a change to what identities name (not to the code, which the
# fingerprint covers) bumps it, with a migration that re-keys the recorded runs (`rekey`, +experiment=migrate).
IDENTITY_VERSION = 2
COMMAND_STARTED_S = time.time()  # force=true recomputes what was recorded before this; a run computed since is reused
_LIBRARIES = ("torch", "mitsuba", "drjit", "numpy", "OpenEXR", "pyoidn", "scikit-image", "hydra-core")


def config_hash(identity: dict) -> str:
    """Stable short hash of a JSON-serialisable dict (key order does not matter)."""
    text = json.dumps(identity, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass
class Run:
    kind: str
    hash: str
    dir: Path
    record: dict = field(default_factory=dict)
    reused: bool = False
    stale: list = field(default_factory=list)  # code changed since it was recorded (reused on request)
    _t0: float = field(default_factory=time.perf_counter, repr=False)
    _lock: object = field(default=None, repr=False)

    @property
    def metrics(self) -> dict:
        return self.record.get("metrics", {})

    def save(self) -> None:
        text = json.dumps(_encode(self.record), indent=2, sort_keys=True, allow_nan=False, default=_json_default)
        write_atomic(self.dir / RECORD, lambda tmp: tmp.write_text(text))

    def restart_clock(self) -> None:
        """Its wall time counts from now: what ran before (another run's work, e.g. training the weights an
        evaluation needs) is not this run's, nor after a kill -9 when it resumes (`part_started_s`)."""
        self._t0 = time.perf_counter()
        self.record["part_started_s"] = time.time()
        self.save()

    def release(self) -> None:
        if self._lock is not None:
            self._lock.close()  # closing the file drops its flock
            self._lock = None


_NONFINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def _encode(value):
    """Strict JSON: non-finite floats (an infinite PSNR) are stored as the strings "inf", "-inf", "nan"."""
    if isinstance(value, dict):
        return {k: _encode(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _decode_metrics(metrics: dict) -> dict:
    return {k: _NONFINITE.get(v, v) if isinstance(v, str) else v for k, v in (metrics or {}).items()}


# ---------------------------------------------------------------- files written and read back
# Any file the suite reads back (a record, a checkpoint, a curve, a manifest) may have been cut short
# or overwritten since: one that does not parse counts as missing, so what it held is computed again.

DAMAGED = (ValueError, EOFError, RuntimeError, UnicodeDecodeError, zipfile.BadZipFile, pickle.UnpicklingError,
           gzip.BadGzipFile)


def _check_zip(path: Path) -> bool:
    """A torch checkpoint is a zip archive: every member's CRC is checked, without unpickling."""
    with zipfile.ZipFile(path) as archive:
        bad = archive.testzip()
    if bad is not None:
        raise zipfile.BadZipFile(f"member {bad} fails its CRC check")
    return True


def _read_json_object(path: Path) -> dict:
    value = json.loads(Path(path).read_text())
    if not isinstance(value, dict):
        raise ValueError(f"expected a JSON object, found {type(value).__name__}")
    return value


_READERS = {".json": _read_json_object, ".csv": pd.read_csv, ".pt": _check_zip}


_NAMED: set[str] = set()  # the damaged files this process has named: each is named once, however often read


def name_damaged(path: str | Path, why: str, then: str = "treating it as missing") -> None:
    """Log once per process that `path` is damaged, `why`, and what is done about it."""
    if str(path) not in _NAMED:
        _NAMED.add(str(path))
        log.warning("%s is damaged (%s); %s", path, why, then)


def read_or_none(path: str | Path, read=None):
    """`read(path)` (by default the reader of its suffix: a JSON object, a CSV as a DataFrame, a
    checkpoint's integrity), or None when the file is missing or damaged: a damaged file is treated as
    missing, and the log names it once. A file its run's record lists (`files`) is damaged too when its
    size or digest differs from the listed ones: a CSV cut at a line end still parses."""
    path = Path(path)
    try:
        problem = listed_file_problem(path)
        if problem is not None:
            raise ValueError(problem)
        return (read or _READERS[path.suffix])(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    except DAMAGED as err:
        name_damaged(path, f"{type(err).__name__}: {err}")
        return None


# ---------------------------------------------------------------- a run's files, listed in its record
# A run's record lists every file of its directory with its size and digest (`files`), written with the
# record when the run completes (one atomic write). Every read checks a file against its entry, so a file
# cut short or overwritten since is named and never reused. Runs recorded before the list existed carry
# none and are trusted, as runs recorded before code fingerprints are.

_DIGESTS: dict[tuple, str] = {}  # (path, size, mtime_ns) -> sha256: a file read again is not hashed again


def file_digest(path: Path) -> str:
    stat = path.stat()
    key = (str(path), stat.st_size, stat.st_mtime_ns)
    if key not in _DIGESTS:
        digest = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
        _DIGESTS[key] = digest.hexdigest()
    return _DIGESTS[key]


def list_files(run_dir: Path) -> dict:
    """Every file of a run's directory, subfolders included, but its record and half-written temporaries:
    relative path -> {"bytes", "sha256"}."""
    run_dir = Path(run_dir)
    return {p.relative_to(run_dir).as_posix(): {"bytes": p.stat().st_size, "sha256": file_digest(p)}
            for p in sorted(run_dir.rglob("*")) if p.is_file() and p.name != RECORD and not p.name.endswith(".tmp")}


def file_problem(path: Path, listed: dict) -> str | None:
    """How the file at `path` differs from its entry in a record's `files`, or None when it matches."""
    if not path.is_file():
        return "missing"
    size = path.stat().st_size
    if size != listed["bytes"]:
        return f"{size} bytes, recorded {listed['bytes']}"
    if file_digest(path) != listed["sha256"]:
        return "its digest differs from the recorded one"
    return None


def listed_file_problem(path: Path) -> str | None:
    """`file_problem` of a file inside a run directory whose record lists it; None for any other file."""
    if path.name == RECORD or not (path.parent / RECORD).exists():
        return None
    try:
        listed = (_read_json_object(path.parent / RECORD).get("files") or {}).get(path.name)
    except (OSError, *DAMAGED):  # a damaged record: whoever reads it names it
        return None
    return None if listed is None else file_problem(path, listed)


def damaged_files(run_dir: Path, record: dict) -> dict[str, str]:
    """The files `record` lists that are missing from `run_dir` or differ from their entries: name -> why."""
    problems = {name: file_problem(Path(run_dir) / name, listed) for name, listed in (record.get("files") or {}).items()}
    return {name: why for name, why in problems.items() if why is not None}


def list_files_in_record(run_dir: Path) -> None:
    """List the files of a recorded run again, after they were rewritten on purpose (an archive's run
    converted to the compact form): its record names what is there now."""
    record = _read_json_object(Path(run_dir) / RECORD)
    record["files"] = list_files(run_dir)
    text = json.dumps(record, indent=2, sort_keys=True)
    write_atomic(Path(run_dir) / RECORD, lambda tmp: tmp.write_text(text))


def read_json_or_none(path: str | Path) -> dict | None:
    """A JSON object the suite wrote, or None when missing or damaged (`read_or_none`)."""
    return read_or_none(path, _read_json_object)


def remove_temporary_files(run_dir: Path) -> None:
    """Remove the half-written files (`*.tmp`: a write that failed, or a process killed mid-write) of a
    run whose lock this process holds: no other process writes there."""
    for leftover in Path(run_dir).glob("*.tmp"):
        leftover.unlink(missing_ok=True)


def read_record(path: Path) -> dict | None:
    """A run.json, its non-finite metrics decoded; None when missing or damaged (`read_or_none`)."""
    record = read_json_or_none(path)
    if record is not None:
        record["metrics"] = _decode_metrics(record.get("metrics"))
    return record


def _json_default(value):
    if hasattr(value, "item"):
        return value.item()
    return str(value)


def lookup(runs_dir: str | Path, kind: str, identity: dict, archive: str | Path | None = None) -> Run | None:
    """The complete run with this identity, or None; with `archive`, one the store lacks is first
    restored from there (`restore`)."""
    h = config_hash(identity)
    path = Path(runs_dir) / kind / h / RECORD
    if archive is not None:
        restore(runs_dir, archive, kind, h)
    record = read_record(path)
    if record is None or record.get("status") != "complete":
        return None
    return Run(kind, h, path.parent, record, reused=True)


def find_record(kind: str, run_hash: str, runs_dir, archives=()) -> tuple[Path | None, dict | None]:
    """(path, record) of the first record of run `run_hash` that reads, the run store's first, then the
    archives' (read there, not restored); (None, None) when none does (missing or damaged)."""
    for root in (runs_dir, *archives):
        path = Path(root) / kind / run_hash / RECORD
        record = read_record(path)
        if record is not None:
            return path, record
    return None, None


def recorded_wall_s(kind: str, run_hash: str, runs_dir: str | Path, archives=()) -> float | None:
    """Recorded wall time of one run, from the run store or an archive (`find_record`); None when
    neither holds it, so a caller can tell a missing run from a fast one."""
    record = find_record(kind, run_hash, runs_dir, archives)[1]
    return None if record is None else float(record.get("wall_time_s") or 0.0)


def join_trainings(hashes: list[str]) -> str:
    """How an evaluation names the trainings it scored (its identity's `trained`, its metrics' `train_run`):
    a Cascade's stages joined by "+", in order."""
    return "+".join(hashes)


def split_trainings(trained: str | None) -> list[str]:
    """The training hashes `join_trainings` joined; [] for None (a model that trains nothing)."""
    return [h for h in (trained or "").split("+") if h]


def trainings_of(evaluation: dict) -> list[str]:
    """The training runs an evaluation record scored, in stage order; [] for a model that trains nothing."""
    return split_trainings((evaluation.get("metrics") or {}).get("train_run"))


def begin(runs_dir: str | Path, kind: str, identity: dict, config: dict | None = None,
          seed: int | None = None, device: str = "cpu", label: str = "", force: bool = False,
          code: dict | None = None, reuse_stale: bool = False, archive: str | Path | None = None,
          needs: tuple = (), every_call: bool = False, rebuild=None) -> Run:
    """Reuse a complete run, or open (or re-open, to resume) its directory for computing.

    Check `run.reused`: when True the caller must not recompute. With `force`, a run recorded before
    this command started is computed again, its directory wiped first so nothing stale (checkpoints,
    outputs) survives; one completed since (by this process, or a concurrent forced one) is reused, so
    force computes each run once per command; `every_call` computes it at every call (a render job's
    record). `code` is the run's code fingerprint (`code_fingerprint`); a recorded run computed with
    other code is recomputed from scratch, its checkpoints included, unless `reuse_stale`. `archive`: a
    run the store lacks is restored from there first (`restore`), and then reused like any recorded run.
    `needs`: files the caller reads from the run's directory (a tuple of names: any one of them, e.g. a
    full checkpoint or the archive's weights); a complete run without one of them, or with one damaged
    (`read_or_none`), is computed again from scratch, under its lock, so only one process does. So is a
    complete run any of whose files differs from the list its record keeps, unless `rebuild(run_dir,
    names)` writes the damaged ones again to their recorded bytes (a training's curves, from its
    checkpoint); that is tried under the lock only.
    """
    forced = force  # by the caller (force=true), not because the record asks for a fresh start
    if not force:
        done = _reusable(runs_dir, kind, identity, code, reuse_stale, label, quiet=True, needs=needs)
        if done is not None:
            return done
    h = config_hash(identity)
    run_dir = Path(runs_dir) / kind / h
    # the kind's folder, not the run's: a concurrent forced command may be deleting the run's folder under
    # its lock, and a probe file inside it would fail (or keep rmtree from finishing)
    ensure_writable(run_dir.parent)
    lock = acquire(run_dir.parent / f".{h}.lock", f"computing {kind}/{h}")
    if force:  # a forced run computed since this command started (here, or by a concurrent command)
        done = None if every_call else _computed_this_command(runs_dir, kind, identity, label)
    else:  # another process may have completed it while we waited for the lock
        done = _reusable_locked(runs_dir, archive, kind, identity, code, reuse_stale, label, needs, rebuild)
    if done is not None:
        lock.close()
        return done
    remove_temporary_files(run_dir)  # a killed process's half-written files
    earlier = read_record(run_dir / RECORD) or {}
    record_lost = not earlier and run_dir.is_dir() and any(p.name != RECORD for p in run_dir.iterdir())
    if earlier.get("status") == "complete":  # not reusable (code changed, or lacks what `needs` names)
        force = True
    elif force and earlier.get("forced") and not every_call and not code_changes(earlier, code):
        # an earlier force=true command started it and stopped: this command finishes what that one forced
        log.info("%s %s: resuming run %s, which an earlier force=true command started and left %s: force=true "
                 "computes each run once, and this one is not finished yet (delete %s to start it over)",
                 kind, label, h, earlier.get("status"), run_dir)
        force = False
    if earlier.get("status") == "running":  # we hold its lock, so the process that wrote this is gone
        log.info("%s %s: run %s was left running by process %s on %s, which is gone (abandoned); taking it over",
                 kind, label, h, earlier.get("pid", "?"), earlier.get("host", "?"))
    if earlier and not reuse_stale and code_changes(earlier, code):  # its checkpoints are another code's
        force = True
    if force and run_dir.exists():
        shutil.rmtree(run_dir)
        earlier = {}
    run_dir.mkdir(parents=True, exist_ok=True)
    record = {
        "kind": kind, "hash": h, "label": label, "status": "running", "identity": identity,
        "config": config if config is not None else identity, "seed": seed, "device": device, "pid": os.getpid(),
        "started": earlier.get("started", time.strftime("%Y-%m-%dT%H:%M:%S%z")), "part_started_s": time.time(),
        **provenance(),
    }
    if forced or earlier.get("forced"):  # a later force=true command resumes it rather than starting over
        record["forced"] = True
    if code is not None:
        record["code"] = code
    if earlier:  # an interrupted, failed or killed run resumes: its earlier time still counts
        record["resumed_wall_time_s"] = _earlier_wall_s(earlier, run_dir)
    elif record_lost and not force:  # files without a record that reads: what they cost is not known here
        record["earlier_wall_time"] = "lost with its record"
    run = Run(kind, h, run_dir, record, _lock=lock)
    run.save()
    return run


def reusable(runs_dir: str | Path, kind: str, identity: dict, code: dict | None = None,
             reuse_stale: bool = False, archive: str | Path | None = None) -> Run | None:
    """The complete run `begin` would reuse rather than compute, or None: decided from records alone,
    before anything it would read (frames, weights) exists. As `begin` does, an archived run is restored
    first where the store lacks it or holds it computed with other code."""
    h = config_hash(identity)
    if archive is not None and (Path(archive) / kind / h / RECORD).exists():
        (Path(runs_dir) / kind).mkdir(parents=True, exist_ok=True)
        with contextlib.closing(acquire(Path(runs_dir) / kind / f".{h}.lock", f"computing {kind}/{h}")):
            _restore_locked(runs_dir, archive, kind, h, code)
    return _reusable(runs_dir, kind, identity, code, reuse_stale, "", quiet=True)


def _reusable_locked(runs_dir, archive, kind: str, identity: dict, code, reuse_stale: bool, label: str,
                     needs: tuple, rebuild=None) -> Run | None:
    """`_reusable` under the run's lock, after restoring the run from `archive` when the store lacks it."""
    if archive is not None:
        _restore_locked(runs_dir, archive, kind, config_hash(identity), code)
    return _reusable(runs_dir, kind, identity, code, reuse_stale, label, needs=needs, rebuild=rebuild)


def _computed_this_command(runs_dir, kind: str, identity: dict, label: str) -> Run | None:
    """The complete run with this identity if it finished after this command started (force computes
    each run once: a table asking twice, or a concurrent forced command, finds it done), else None."""
    done = lookup(runs_dir, kind, identity)
    if done is None or done.record.get("finished_s", 0.0) < COMMAND_STARTED_S:
        return None
    log.info("%s %s: run %s was computed since this command started; force=true does not compute it twice",
             kind, label, done.hash)
    return done


def _earlier_wall_s(earlier: dict, run_dir: Path) -> float:
    """Wall time of a resumed run's earlier parts: as recorded when the last part ended (failed,
    interrupted); after a kill -9 (still "running"), that part counts from its start to the last file it
    wrote (its last checkpoint: what came after is computed again)."""
    if earlier.get("wall_time_s") is not None:
        return float(earlier["wall_time_s"])
    last_write = max((p.stat().st_mtime for p in run_dir.iterdir() if p.is_file()), default=0.0)
    part = max(0.0, last_write - earlier.get("part_started_s", last_write))
    return float(earlier.get("resumed_wall_time_s") or 0.0) + part


def _reusable(runs_dir, kind: str, identity: dict, code: dict | None, reuse_stale: bool,
              label: str, quiet: bool = False, needs: tuple = (), rebuild=None) -> Run | None:
    """The complete run to reuse, or None; `quiet`: a first look before the lock, which logs nothing. A
    run whose listed files are all sound is reusable; where some are damaged, `rebuild(run_dir, names)`
    may write them again from the run's other files (True: it did; given under the lock only), and the
    run is reused if they now match their recorded digests, else computed again (each named once)."""
    done = lookup(runs_dir, kind, identity)
    if done is None:
        return None
    damaged = damaged_files(done.dir, done.record)
    if damaged and rebuild is not None and rebuild(done.dir, sorted(damaged)):
        before, damaged = damaged, damaged_files(done.dir, done.record)  # rebuilt to the recorded bytes, or not
        for name in sorted(set(before) - set(damaged)):
            _NAMED.add(str(done.dir / name))
            log.info("%s %s: %s was damaged (%s) and is rebuilt to its recorded bytes from the run's other files",
                     kind, label, done.dir / name, before[name])
    if damaged:
        for name, why in damaged.items() if not quiet else ():  # (the look under the lock names them)
            name_damaged(done.dir / name, why, f"run {kind}/{done.hash} is computed again, not reused")
        return None
    alternatives = [(need,) if isinstance(need, str) else tuple(need) for need in needs]
    missing = [" or ".join(names) for names in alternatives
               if all(read_or_none(done.dir / name) is None for name in names)]
    if missing:
        if not quiet:
            log.info("%s %s: computing run %s again: it has no %s that reads (damaged, or left out by an archive, "
                     "which keeps files over %.1f MiB out)", kind, label, done.hash, ", ".join(missing),
                     ARCHIVED_FILE_MAX_BYTES / 2**20)
        return None
    done.stale = code_changes(done.record, code)
    if not done.stale:
        return done
    if quiet and not reuse_stale:
        return None
    changed = ", ".join(done.stale[:4]) + (f" and {len(done.stale) - 4} more" if len(done.stale) > 4 else "")
    if reuse_stale:
        log.warning("%s %s: reusing run %s although its code changed since (%s), as reuse_stale=true asks",
                    kind, label, done.hash, changed)
        return done
    log.info("%s %s: recomputing run %s, its code changed since it was recorded (%s); "
             "reuse_stale=true would reuse it", kind, label, done.hash, changed)
    return None


# ---------------------------------------------------------------- the archive
# The run store lives on one disk and may be lost (a fresh clone, a new machine); finished runs are
# worth keeping with the tables they make. The archive is a second store of the same layout that holds
# only complete runs, each with the small files a table reads again (its record, curves, per-frame
# scores, weights; a training in the compact form of bench.archived): it can be committed, and a store
# that lacks a run restores it from there.


PARTIAL = ".partial"  # copies being written and the archive's locks: never a run, never committed
ARCHIVED_FILE_MAX_BYTES = 5 * 2**20  # the archive is committed: a larger file (a big model's weights) stays out


def archive(run: Run, archive_dir: str | Path, files: tuple = (), write=None) -> Path | None:
    """Copy a complete run into `archive_dir/<kind>/<hash>/`: its record, the `files` of its directory
    that exist, and what `write(directory)` writes there (e.g. a slimmed checkpoint), each if it is at
    most ARCHIVED_FILE_MAX_BYTES: the run restores without a larger one (a training without its weights
    is trained again by whoever needs them, `bench.experiments.training.trained_model`). The record is
    compared first, so archiving an archived run again does nothing. The copy is written in
    `archive_dir/.partial/` and renamed into place under the archived run's lock, so a restore never
    sees half of it. Returns the archived directory, or None for a run that is not complete or is stale
    (its code changed: the archive keeps what current code computed)."""
    if run.record.get("status") != "complete" or run.stale:
        return None
    dest = Path(archive_dir) / run.kind / run.hash
    record = _read_json_object(run.dir / RECORD)
    if _without_files(read_json_or_none(dest / RECORD)) == _without_files(record):
        return dest
    partial = Path(archive_dir) / PARTIAL
    partial.mkdir(parents=True, exist_ok=True)
    tmp, old = partial / f"{run.kind}.{run.hash}.{os.getpid()}", partial / f"{run.kind}.{run.hash}.{os.getpid()}.old"
    try:
        tmp.mkdir()
        for name in files:
            if (run.dir / name).exists():
                shutil.copy2(run.dir / name, tmp / name)
        if write is not None:
            write(tmp)
        for path in tmp.iterdir():
            if path.stat().st_size > ARCHIVED_FILE_MAX_BYTES:
                log.info("runs: archiving %s/%s without %s (%.1f MiB, over the archive's %.1f MiB)", run.kind,
                         run.hash, path.name, path.stat().st_size / 2**20, ARCHIVED_FILE_MAX_BYTES / 2**20)
                path.unlink()
        text = json.dumps({**record, "files": list_files(tmp)}, indent=2, sort_keys=True)  # the archive's own files
        (tmp / RECORD).write_text(text)
        dest.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.closing(acquire(partial / f"{run.kind}.{run.hash}.lock", f"archiving {run.kind}/{run.hash}")):
            if dest.exists():
                dest.rename(old)
            tmp.rename(dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
    return dest


def _without_files(record: dict | None) -> dict | None:
    """A record but for its list of files: the store's and the archive's copies of a run list different
    files (the archive's compact forms) and are the same run."""
    return None if record is None else {k: v for k, v in record.items() if k != "files"}


def restore(runs_dir: str | Path, archive_dir: str | Path, kind: str, run_hash: str) -> bool:
    """Copy an archived complete run into the store when the store has no record of it (a run there,
    even an interrupted one, is left alone: it resumes). Holds the run's lock, as computing it would:
    no process can be writing the directory it fills."""
    if (Path(runs_dir) / kind / run_hash / RECORD).exists() or not (Path(archive_dir) / kind / run_hash / RECORD).exists():
        return False
    (Path(runs_dir) / kind).mkdir(parents=True, exist_ok=True)
    with contextlib.closing(acquire(Path(runs_dir) / kind / f".{run_hash}.lock", f"computing {kind}/{run_hash}")):
        return _restore_locked(runs_dir, archive_dir, kind, run_hash)


def _restore_locked(runs_dir, archive_dir, kind: str, run_hash: str, code: dict | None = None) -> bool:
    """`restore` for a caller that holds the run's lock (`begin`). With `code`, a store run computed with
    other code (it would be recomputed from scratch) also gives way to an archived run that this code
    computed, e.g. one another machine archived after the change."""
    src, dst = Path(archive_dir) / kind / run_hash, Path(runs_dir) / kind / run_hash
    if not (src / RECORD).exists():
        return False
    if (dst / RECORD).exists():
        stored, archived = read_record(dst / RECORD) or {}, read_record(src / RECORD) or {}
        if not (code_changes(stored, code) and not code_changes(archived, code)):
            return False
        shutil.rmtree(dst)  # we hold its lock; begin would wipe it anyway
        log.info("runs: %s/%s in the store was computed with other code; the archive's run is current", kind, run_hash)
    partial = Path(archive_dir) / PARTIAL
    partial.mkdir(parents=True, exist_ok=True)
    tmp = Path(runs_dir) / PARTIAL / f"{kind}.{run_hash}.{os.getpid()}"
    try:
        with contextlib.closing(acquire(partial / f"{kind}.{run_hash}.lock", f"archiving {kind}/{run_hash}")):
            if (read_record(src / RECORD) or {}).get("status") != "complete":
                return False
            shutil.copytree(src, tmp)
        if dst.exists():
            if any(dst.iterdir()):  # files without a record: not ours to replace
                return False
            dst.rmdir()  # the empty directory begin makes before taking the lock
        tmp.rename(dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("runs: restored %s/%s from %s", kind, run_hash, archive_dir)
    return True


# ---------------------------------------------------------------- code identity

ROOT = Path(__file__).resolve().parent.parent    # the project: the packages whose source runs fingerprint
COMMITTED_RESULTS = ROOT / "results"  # the tables (and their run archives) committed with the code
PACKAGES = ("bench", "baselines")


def committed_archive(preset: str) -> Path:
    """The preset's committed run archive (conf/config.yaml's runs_archive when results_dir is left as it is)."""
    return COMMITTED_RESULTS / preset / "runs"


def committed_archives() -> list[Path]:
    """Every preset's committed archive, and (an installed package, another checkout) the working
    directory's `results/*/runs`, each once."""
    found = {p.resolve(): p for p in [*sorted(COMMITTED_RESULTS.glob("*/runs")), *sorted(Path("results").glob("*/runs"))]}
    return list(found.values())


def code_fingerprint(modules) -> dict:
    """{path: hash} of the project source files that `modules` (dotted names, or `_target_` strings of
    a class) run: each module, its packages' `__init__`, and every project module they import,
    transitively, plus the C++ sources a module names. A Python file is hashed by its syntax tree
    without docstrings, so comments, formatting and documentation do not make runs stale. Computed
    once per process and set of modules (the file hashes are, too)."""
    return dict(_code_fingerprint(tuple(m for m in modules if m)))


@functools.lru_cache(maxsize=None)
def _code_fingerprint(modules: tuple) -> dict:
    files: set[Path] = set()
    todo = list(modules)
    while todo:
        name = todo.pop()
        path = module_file(name)
        if path is None:
            parent = name.rpartition(".")[0]  # "pkg.module.Class": the module that defines it
            if parent.split(".")[0] in PACKAGES:
                todo.append(parent)
            continue
        if path in files:
            continue
        files.add(path)
        todo.extend(project_imports(path, name))
        parts = name.split(".")
        todo.extend(".".join(parts[:i]) for i in range(1, len(parts)))  # packages run their __init__
    return {str(p.relative_to(ROOT)): source_hash(p) for p in sorted(files)}


def code_changes(record: dict, code: dict | None) -> list:
    """Paths whose code differs between a recorded run and `code` (added, removed or changed); empty
    when either has no fingerprint (runs recorded before fingerprints are trusted)."""
    recorded = record.get("code")
    if not code or not recorded:
        return []
    return sorted(p for p in set(recorded) | set(code) if recorded.get(p) != code.get(p))


def module_file(name: str) -> Path | None:
    if name.split(".")[0] not in PACKAGES:
        return None
    base = ROOT.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def project_imports(path: Path, name: str) -> list:
    """Dotted names of the project modules (or their attributes: `from pkg.mod import Name` gives
    pkg.mod and pkg.mod.Name) that the source file `path` of module `name` imports."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            found.append(base)
            found.extend(f"{base}.{alias.name}" for alias in node.names)  # `from pkg import module`
    return [m for m in found if m.split(".")[0] in PACKAGES]


def native_sources(tree: ast.AST) -> set[str]:
    """The C++ sources a module names (string constants ending .cpp or .cu, relative to its folder):
    its compiled kernels, part of its source hash."""
    return {node.value for node in ast.walk(tree) if isinstance(node, ast.Constant)
            and isinstance(node.value, str) and node.value.endswith((".cpp", ".cu"))}


@functools.lru_cache(maxsize=None)
def source_hash(path: Path) -> str:
    if path.suffix != ".py":
        return hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    tree = ast.parse(path.read_text())
    native = sorted({path.parent / name for name in native_sources(tree) if (path.parent / name).is_file()})
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) \
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]
    digest = hashlib.sha256(ast.dump(tree).encode())
    for source in native:  # a module's compiled kernels are part of it
        digest.update(source.read_bytes())
    return digest.hexdigest()[:16]


_HELD: dict[str, object] = {}  # this process's locks: a run begun again after an error reuses its own lock


def acquire(path: Path, what: str):
    """An exclusive lock on `path`, held until the returned file is closed (`with closing(acquire(...))`);
    while another process holds it, says it waits for `what`. The OS drops a dead process's lock, so an
    interrupted process never blocks anyone. This process taking the same lock again replaces its own."""
    key = str(path.resolve())
    if key in _HELD and not _HELD[key].closed:
        _HELD[key].close()
    handle = try_acquire(path)
    if handle is None:
        print(f"[runs] waiting for another process {what}", flush=True)
        handle = open(path, "a")
        fcntl.flock(handle, fcntl.LOCK_EX)
    _HELD[key] = handle
    return handle


def try_acquire(path: Path):
    """An exclusive lock on `path` if no other holder has it: the open file (close it to release), else
    None. Unlike `acquire`, never waits."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = open(path, "a")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        return None
    return handle


def complete(run: Run, metrics: dict, **extra) -> Run:
    """Record metrics and wall time; the run becomes reusable."""
    run.record.update(extra)
    run.record["metrics"] = metrics
    run.record["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    run.record["finished_s"] = time.time()
    return _close(run, "complete")


def fail(run: Run, message: str, status: str = "failed") -> Run:
    """Record that the run stopped without a result ("failed", or "interrupted" on request); its
    directory stays, so a checkpoint in it can be resumed."""
    run.record["error"] = message
    return _close(run, status)


def _close(run: Run, status: str) -> Run:
    """Save the run's last record (its status and wall time, the earlier parts' included) and drop its
    lock. A record that cannot be saved (a full disk) is removed rather than left saying "running": the
    run is then missing, and its checkpoints resume."""
    run.record["status"] = status
    run.record["wall_time_s"] = run.record.get("resumed_wall_time_s", 0.0) + time.perf_counter() - run._t0
    remove_temporary_files(run.dir)
    if status == "complete":  # what a reader checks it against (`damaged_files`)
        run.record["files"] = list_files(run.dir)
    try:
        run.save()
    except OSError:
        (run.dir / RECORD).unlink(missing_ok=True)
        raise
    finally:
        run.release()
    return run


def load(runs_dir: str | Path, kind: str | None = None) -> pd.DataFrame:
    """All recorded runs as one tidy DataFrame: a row per run, metrics as `metric.<name>` columns and
    the identity flattened as `cfg.<dotted.key>` columns. A record left "running" by a process that no
    longer exists shows as "abandoned" (its checkpoints resume on the next request)."""
    rows = []
    pattern = f"{kind}/*/{RECORD}" if kind else f"*/*/{RECORD}"
    for path in sorted(Path(runs_dir).glob(pattern)):
        if path.parts[-3].startswith(".") or path.parts[-2].startswith("."):  # a copy being restored (PARTIAL)
            continue
        record = read_record(path)
        if record is None:  # damaged: named in the log, and computed again when a table asks for it
            continue
        row = {k: record.get(k) for k in ("kind", "hash", "label", "status", "seed", "device",
                                          "wall_time_s", "git_commit", "git_dirty", "host", "started")}
        if row["status"] == "running" and not computing(path.parent):
            row["status"] = "abandoned"  # its process is gone (killed, or the machine went away)
        row["dir"] = str(path.parent)
        row.update({f"metric.{k}": v for k, v in (record.get("metrics") or {}).items()
                    if not isinstance(v, (dict, list))})
        row.update({f"cfg.{k}": v for k, v in flatten(record.get("identity", {})).items()})
        rows.append(row)
    return pd.DataFrame(rows)


def computing(run_dir: Path) -> bool:
    """Whether some process holds the run's lock now (a record says "running" also after a kill -9)."""
    lock = run_dir.parent / f".{run_dir.name}.lock"
    if not lock.exists():
        return False
    handle = try_acquire(lock)  # flock conflicts with any other open file, this process's too
    if handle is None:
        return True
    handle.close()
    return False


def flatten(d: dict, prefix: str = "") -> dict:
    """A nested dict as one level, keys joined by '.' (lists as JSON text)."""
    out = {}
    for key, value in d.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        else:
            out[name] = json.dumps(value) if isinstance(value, list) else value
    return out


# What a command line can cause besides a UserError: a path that is missing or not writable, a file where a
# folder belongs or the reverse. The entry points print these as one line too (exit 2).
PATH_ERRORS = (PermissionError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError)


def error_line(err: BaseException) -> str:
    """The one line an entry point prints for a UserError or one of PATH_ERRORS."""
    if isinstance(err, (FileExistsError, NotADirectoryError)) and err.filename and not Path(err.filename).is_dir():
        return f"{err.filename}: a file stands where a folder is needed on this path ({err.strerror})"
    if isinstance(err, IsADirectoryError) and err.filename:
        return f"{err.filename}: a folder stands where a file is needed ({err.strerror})"
    return str(err)


def probe_write(folder: Path) -> None:
    """Make and remove a folder in `folder` (an OSError if it cannot): permissions alone do not tell (root,
    /proc). A probe of its own name: processes started together on one store must not remove each other's."""
    os.rmdir(tempfile.mkdtemp(dir=folder, prefix=".write_probe."))


def ensure_writable(path: Path, setting: str = "runs_dir") -> None:
    """Create `path` and prove it writable, or raise PermissionError naming the setting to change."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe_write(path)
    except OSError as err:
        raise PermissionError(f"{setting.removesuffix('_dir')} directory {path} is not writable "
                              f"({err.strerror}); set {setting}=... to a writable place") from err


def out_of_space(err: BaseException, path: Path) -> bool:
    """Whether `err` is a full disk (or quota): ENOSPC/EDQUOT, or any write error at a time when a write
    of a few pages under `path` fails with one (torch's file writer loses the errno)."""
    if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    probe = Path(path) / f".space_probe.{os.getpid()}"
    try:
        with open(probe, "wb") as file:
            file.write(b"\0" * 65536)
            file.flush()
            os.fsync(file.fileno())
    except OSError as probe_err:
        return probe_err.errno in (errno.ENOSPC, errno.EDQUOT)
    finally:
        probe.unlink(missing_ok=True)
    return False


_PROVENANCE: dict | None = None


def provenance() -> dict:
    """Where and with what a run was computed: git commit/dirty flag, host, library versions."""
    global _PROVENANCE
    if _PROVENANCE is None:
        versions = {}
        for lib in _LIBRARIES:
            try:
                versions[lib] = importlib.metadata.version(lib)
            except importlib.metadata.PackageNotFoundError:
                versions[lib] = None
        _PROVENANCE = {"host": socket.gethostname(), "user": getpass.getuser(),
                       "python": platform.python_version(), "platform": platform.platform(),
                       "versions": versions, **_git_state()}
    return dict(_PROVENANCE)


def _git_state() -> dict:
    repo = ROOT
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True,
                                text=True, timeout=10).stdout.strip() or None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                               capture_output=True, text=True, timeout=10).stdout.strip() != ""
    except (OSError, subprocess.SubprocessError):
        commit, dirty = None, None
    return {"git_commit": commit, "git_dirty": dirty}

"""The compact form of an archived training or evaluation, and the one place that writes and reads it.

The run store keeps a training's full checkpoint (weights, EMA, optimizer, per-step curve) and its
per-step `curve.csv`: what resuming needs. The archive (`runs_archive`, committed with the tables)
keeps what the tables, claims, `adopt`, predict and export read again, small:

- `weights.fp16.pt`: the weights evaluation loads (the EMA, else the raw ones) rounded to float16,
  concatenated into one buffer, its two byte planes apart (the high bytes, sign and exponent, compress
  well) and lzma-compressed; names, shapes and dtypes beside it. Tensors float16 cannot hold (integer
  buffers, values beyond its range) are kept as they are. 2.5x smaller than float32 on the cpu archive;
  what the rounding moves in the scores is measured by `scripts/fp16_weights_accuracy.py`
  (docs/runs.md) and allowed for by adopt (`rtol_rounded_weights`).
- `curve.csv.gz`: the per-step curve's steps 1-100 whole (adopt replays the first steps), then every
  `CURVE_EVERY`th step and the last; a learning-rate range test's (schedule `range`, analysed step by
  step) whole. Rows are kept as the trainer wrote them.
- `val_curve.csv` and `run.json` as they are.

An archived evaluation keeps its record and its per-frame scores gzip-compressed (`per_image.csv.gz`,
the same bytes as the store's `per_image.csv`; claims and the reference check read them); its output
frames (`eval.save_exr`) stay out.

A restored run (the store filled from the archive) holds the compact form too; the readers here take
either form, the full one first. `python -m bench.archived DIR` converts an archive written before in
place (idempotent); `--drop-unlisted results/<preset>` deletes the evaluations no table lists any more;
`--first-seed-weights` deletes the weights of every training but the lowest seed of its row.
"""
from __future__ import annotations

import argparse
import gzip
import io
import logging
import lzma
import shutil
import sys
import time
import zlib
from pathlib import Path

import pandas as pd
import torch

from bench import runs
from bench.atomic import write_atomic
from bench.table_writer import listed_evaluations, read_table
from bench.train import CHECKPOINT

log = logging.getLogger("bench")

WEIGHTS = "weights.fp16.pt"
CURVE = "curve.csv"          # the trainer's per-step curve, in the run store
COMPACT_CURVE = "curve.csv.gz"
VAL_CURVE = "val_curve.csv"
FILES = (runs.RECORD, WEIGHTS, COMPACT_CURVE, VAL_CURVE)  # what an archived training may hold
PER_IMAGE = "per_image.csv"          # an evaluation's per-frame scores, in the run store
COMPACT_PER_IMAGE = "per_image.csv.gz"
EVALUATION_FILES = (runs.RECORD, COMPACT_PER_IMAGE)   # what an archived evaluation holds
FORMAT = "srd-bench-archived-weights/1"
CURVE_WHOLE_STEPS = 100
CURVE_EVERY = 10
FLOAT16_MAX = float(torch.finfo(torch.float16).max)


# ---------------------------------------------------------------- weights

def encode(state_dict: dict) -> dict:
    """The compact form of a state dict (see the module docstring), for torch.save."""
    names, shapes, dtypes, halves, exact = [], [], [], [], {}
    for name, tensor in state_dict.items():
        tensor = tensor.detach().cpu()
        names.append(name)
        shapes.append(list(tensor.shape))
        dtypes.append(str(tensor.dtype).removeprefix("torch."))
        fits = tensor.is_floating_point() and (tensor.numel() == 0 or tensor.abs().max().item() <= FLOAT16_MAX)
        if fits:
            halves.append(tensor.flatten().to(torch.float16))
        else:
            exact[name] = tensor.clone()
    flat = torch.cat(halves) if halves else torch.zeros(0, dtype=torch.float16)
    planes = flat.view(torch.uint8).view(-1, 2).t().contiguous()  # low bytes, then high bytes
    packed = lzma.compress(planes.numpy().tobytes())
    return {"format": FORMAT, "names": names, "shapes": shapes, "dtypes": dtypes, "exact": exact,
            "float16_planes_lzma": torch.frombuffer(bytearray(packed), dtype=torch.uint8)}


def decode(saved: dict, device: str = "cpu") -> dict:
    """The state dict `encode` stored, in its original dtypes (float16-rounded values)."""
    if not isinstance(saved, dict) or saved.get("format") != FORMAT:
        raise ValueError(f"not archived weights ({FORMAT})")
    planes = torch.frombuffer(bytearray(lzma.decompress(saved["float16_planes_lzma"].numpy().tobytes())),
                              dtype=torch.uint8)
    flat = planes.view(2, -1).t().reshape(-1).view(torch.float16)
    out, offset = {}, 0
    for name, shape, dtype in zip(saved["names"], saved["shapes"], saved["dtypes"]):
        if name in saved["exact"]:
            out[name] = saved["exact"][name].to(device)
            continue
        n = int(torch.Size(shape).numel())
        out[name] = flat[offset:offset + n].view(shape).to(device=device, dtype=getattr(torch, dtype))
        offset += n
    return out


def write_weights(state_dict: dict, path: Path) -> None:
    buffer = io.BytesIO()  # torch.save names the zip's folder after a file: through a buffer, same bytes always
    torch.save(encode(state_dict), buffer)
    write_atomic(path, lambda tmp: tmp.write_bytes(buffer.getvalue()))


def _checkpoint_weights(path: Path, device: str = "cpu") -> dict:
    """The weights evaluation uses from a trainer's checkpoint: the EMA when the run kept one."""
    state = torch.load(path, map_location=device, weights_only=False)
    return state.get("ema") or state["model"]


def weights_file(run_dir: Path) -> Path | None:
    """The file holding a training's weights: its full checkpoint, else the archived form; None for none."""
    for name in (CHECKPOINT, WEIGHTS):
        if (Path(run_dir) / name).exists():
            return Path(run_dir) / name
    return None


def has_weights(run_dir: Path) -> bool:
    return weights_file(run_dir) is not None


def rounded(run_dir: Path) -> bool:
    """Whether the run's weights are the archive's float16-rounded ones (no full checkpoint beside them)."""
    path = weights_file(run_dir)
    return path is not None and path.name == WEIGHTS


def state_dict(run_dir: Path, device: str = "cpu") -> dict:
    """The weights evaluation uses of a training run (full or archived form); FileNotFoundError without."""
    path = weights_file(run_dir)
    if path is None:
        raise FileNotFoundError(f"no {CHECKPOINT} or {WEIGHTS} in {run_dir}")
    if path.name == CHECKPOINT:
        return _checkpoint_weights(path, device)
    return decode(torch.load(path, map_location="cpu", weights_only=True), device)


def load_weights(model, run_dir: Path, device: str = "cpu"):
    """`model` (in place) with the run's weights loaded (`state_dict`)."""
    model.load_state_dict(state_dict(run_dir, device))
    return model


# ---------------------------------------------------------------- the per-step curve

def whole_curve(record: dict) -> bool:
    """A learning-rate range test's curve is its result, analysed step by step: kept whole."""
    return (record.get("identity") or {}).get("train", {}).get("schedule") == "range"


def compact_curve(text: str, whole: bool = False) -> str:
    """The rows of a per-step curve the archive keeps, as written: steps up to CURVE_WHOLE_STEPS, every
    CURVE_EVERYth step and the last (all with `whole`)."""
    header, *rows = text.splitlines(keepends=True)
    if whole:
        return text
    kept = [row for i, row in enumerate(rows) if i == len(rows) - 1 or _kept_step(int(row.split(",", 1)[0]))]
    return header + "".join(kept)


def _kept_step(step: int) -> bool:
    return step <= CURVE_WHOLE_STEPS or step % CURVE_EVERY == 0


def write_curve(text: str, path: Path, whole: bool = False) -> None:
    _write_gzip(compact_curve(text, whole).encode(), path)


def _write_gzip(data: bytes, path: Path) -> None:
    packed = gzip.compress(data, compresslevel=9, mtime=0)  # mtime 0: the same bytes every time
    write_atomic(path, lambda tmp: tmp.write_bytes(packed))


def _read_gzip_csv(path: Path, **read_csv) -> pd.DataFrame:
    try:
        return pd.read_csv(io.BytesIO(gzip.decompress(Path(path).read_bytes())), **read_csv)
    except (gzip.BadGzipFile, zlib.error) as err:  # damaged: runs.read_or_none treats it as missing
        raise ValueError(str(err)) from err


def read_per_image(run_dir: Path) -> pd.DataFrame | None:
    """An evaluation's per-frame scores (the store's file, else, or where it is damaged, the archive's
    compressed one), sequence names as strings; None when it has neither that reads (the log names a
    damaged one)."""
    run_dir = Path(run_dir)
    plain = runs.read_or_none(run_dir / PER_IMAGE, lambda p: pd.read_csv(p, dtype={"sequence": str}))
    if plain is not None:
        return plain
    return runs.read_or_none(run_dir / COMPACT_PER_IMAGE, lambda p: _read_gzip_csv(p, dtype={"sequence": str}))


def read_curve(run_dir: Path) -> pd.DataFrame | None:
    """A training's per-step curve (the store's full one, else the archive's compact one); None when it
    has none or it is damaged (the log names it)."""
    run_dir = Path(run_dir)
    if (run_dir / CURVE).exists():
        return runs.read_or_none(run_dir / CURVE)
    return runs.read_or_none(run_dir / COMPACT_CURVE, _read_gzip_csv)


def read_val_curve(run_dir: Path) -> pd.DataFrame | None:
    """A training's validation curve (step, train_s, the metrics), kept as it is in the store and the
    archive; None when it has none or it is damaged (the log names it)."""
    return runs.read_or_none(Path(run_dir) / VAL_CURVE)


# ---------------------------------------------------------------- writing and converting

def write(run_dir: Path, dest: Path, record: dict) -> None:
    """Write the compact form of the training in `run_dir` (full or already compact) into `dest`: its
    weights, its per-step curve and its validation curve (the record is the archive's to write)."""
    run_dir, dest = Path(run_dir), Path(dest)
    if (run_dir / CHECKPOINT).exists():
        write_weights(_checkpoint_weights(run_dir / CHECKPOINT), dest / WEIGHTS)
    else:
        _copy(WEIGHTS, run_dir, dest)
    if (run_dir / CURVE).exists():
        write_curve((run_dir / CURVE).read_text(), dest / COMPACT_CURVE, whole_curve(record))
    else:
        _copy(COMPACT_CURVE, run_dir, dest)
    _copy(VAL_CURVE, run_dir, dest)


def _copy(name: str, run_dir: Path, dest: Path) -> None:
    """A file kept as it is, copied from `run_dir` to `dest` where it is there and they differ."""
    if (run_dir / name).exists() and run_dir != dest:
        write_atomic(dest / name, lambda tmp: tmp.write_bytes((run_dir / name).read_bytes()))


def write_evaluation(run_dir: Path, dest: Path) -> None:
    """Write the compact form of the evaluation in `run_dir` (store or archive) into `dest`: its per-frame
    scores (the record is the archive's to write)."""
    run_dir, dest = Path(run_dir), Path(dest)
    if (run_dir / PER_IMAGE).exists():
        _write_gzip((run_dir / PER_IMAGE).read_bytes(), dest / COMPACT_PER_IMAGE)
    else:
        _copy(COMPACT_PER_IMAGE, run_dir, dest)


def convert_evaluation(run_dir: Path) -> bool:
    """Convert one archived evaluation in place to the compact form; False when it already is one."""
    run_dir = Path(run_dir)
    if not (run_dir / PER_IMAGE).exists():
        return False
    write_evaluation(run_dir, run_dir)
    (run_dir / PER_IMAGE).unlink()
    runs.list_files_in_record(run_dir)
    return True


def convert(run_dir: Path) -> bool:
    """Convert one archived training in place to the compact form; False when it already is one, or is not
    complete (an interrupted run's checkpoint is what it resumes from). The compact files are written
    before the full ones go, so an interrupted conversion loses nothing."""
    run_dir = Path(run_dir)
    if not ((run_dir / CHECKPOINT).exists() or (run_dir / CURVE).exists()):
        return False
    record = runs.read_record(run_dir / runs.RECORD)
    if record is None:
        raise ValueError(f"{run_dir / runs.RECORD} is missing or damaged: not converted")
    if record.get("status") != "complete":
        return False
    write(run_dir, run_dir, record)
    (run_dir / CHECKPOINT).unlink(missing_ok=True)
    (run_dir / CURVE).unlink(missing_ok=True)
    runs.list_files_in_record(run_dir)
    return True


def convert_archive(archive_dir: Path) -> int:
    """Convert every training and evaluation of an archive (`<archive_dir>/{train,eval}/<hash>/`) in place;
    the number converted."""
    def runs_of(kind):
        return sorted(p.parent for p in Path(archive_dir).glob(f"{kind}/*/{runs.RECORD}")
                      if not p.parent.name.startswith("."))
    converted = 0
    jobs = [(d, convert) for d in runs_of("train")] + [(d, convert_evaluation) for d in runs_of("eval")]
    for run_dir, conversion in jobs:
        try:
            converted += conversion(run_dir)
        except Exception as err:  # a damaged file: name the run; those before it are converted, it is unchanged
            raise ValueError(f"{run_dir}: not converted ({type(err).__name__}: {err}); "
                             f"{converted} runs before it were") from err
    return converted


def listed_runs(results_dir: Path) -> set[str]:
    """The evaluations the tables under `results_dir` list (every `table.csv`'s `runs` column)."""
    listed = set()
    for table in Path(results_dir).rglob("table.csv"):
        try:
            frame = read_table(table)
        except (ValueError, pd.errors.ParserError, UnicodeDecodeError) as err:
            raise ValueError(f"{table} does not read ({err}): nothing is deleted") from err
        if "runs" in frame:
            listed.update(h for cell in frame["runs"] for h in listed_evaluations(cell))
    return listed


def unlisted_evaluations(archive_dir: Path, results_dir: Path) -> list[Path]:
    """The archived evaluations no table under `results_dir` lists: superseded ones (e.g. scored before
    their split's references got more samples, then scored again). Nothing reads them: tables, claims
    and the reference check read the evaluations a table lists."""
    listed = listed_runs(results_dir)
    if not listed:
        raise ValueError(f"{results_dir} holds no table that lists runs: every evaluation would go")
    return sorted(p.parent for p in Path(archive_dir).glob(f"eval/*/{runs.RECORD}")
                  if not p.parent.name.startswith(".") and p.parent.name not in listed)


def weights_beyond_the_first_seed(archive_dir: Path) -> list[Path]:
    """The archived trainings holding weights that are not the lowest seed of their row (same label and
    identity but the seed). What runs weights again takes that seed: adopt's witness, time, stability, the
    figures' crops, the learning-rate range test; a table's scores come from its archived evaluations."""
    groups: dict[str, list[tuple[int, Path]]] = {}
    for record_path in sorted(Path(archive_dir).glob(f"train/*/{runs.RECORD}")):
        record = runs.read_json_or_none(record_path)
        if record is None or record_path.parent.name.startswith("."):
            continue
        identity = {k: v for k, v in record["identity"].items() if k != "seed"}
        key = runs.config_hash({"label": record.get("label"), "identity": identity})
        groups.setdefault(key, []).append((int(record["identity"].get("seed", 0)), record_path.parent))
    return sorted(run_dir for members in groups.values() for _, run_dir in sorted(members)[1:]
                  if (run_dir / WEIGHTS).exists())


def drop_weights(run_dirs: list[Path]) -> None:
    """Delete archived trainings' weights on purpose; each record then lists what is left (its curves),
    so that a verify does not call the run damaged. Such a training is trained again, into the run store
    only, when something runs its weights (docs/runs.md); archiving it again keeps them out."""
    for run_dir in run_dirs:
        (Path(run_dir) / WEIGHTS).unlink()
        runs.list_files_in_record(run_dir)


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def archive_problem(archive: Path, results_dir: Path | None) -> str | None:
    """Why `archive` is not one this tool may change, or None: it must be a run archive, not a run store
    (whose checkpoints resume trainings), and the tables that --drop-unlisted reads must be those of the
    results dir it serves (its parent, as runs_archive follows results_dir): any other folder lists only
    some of its evaluations, and the rest would go."""
    if not ((archive / "train").is_dir() or (archive / "eval").is_dir()):
        return f"{archive} holds no train/ or eval/ directory: not a run archive"
    if any((archive / name).exists() for name in ("data", "hydra", "mlflow.db")):
        return (f"{archive} is a run store (it holds data/, hydra/ or mlflow.db), not an archive "
                "(results/<preset>/runs): its full checkpoints are what trainings resume from")
    if results_dir is not None and results_dir.resolve() != archive.resolve().parent:
        return (f"--drop-unlisted {results_dir}: the tables that list {archive}'s evaluations are under "
                f"{archive.resolve().parent} (the results dir it is the archive of); another folder lists only "
                "some of them")
    return None


def _reads(path: Path) -> bool:
    """Whether a run's file reads whole: gzip's CRC, a checkpoint's zip CRCs, a CSV or JSON that parses."""
    if path.suffix == ".gz":
        return runs.read_or_none(path, lambda p: gzip.decompress(p.read_bytes())) is not None
    return path.suffix not in (".pt", ".csv", ".json") or runs.read_or_none(path) is not None


def verify(store: Path, list_unlisted: bool = False) -> tuple[list[str], dict[str, int]]:
    """Every run of a run store or archive checked against its record: (one line per problem, counts).
    A record that does not read, and a listed file that is missing or differs from its size and digest,
    are problems; a complete run recorded before records listed their files is counted as unlisted
    (trusted, as reads trust it). `list_unlisted`: such a run whose every file reads whole (`_reads`)
    gets its list now, so later reads check it."""
    problems, counts = [], {"runs": 0, "checked": 0, "unlisted": 0, "damaged": 0, "listed": 0}
    for record_path in sorted(Path(store).glob(f"*/*/{runs.RECORD}")):
        run_dir = record_path.parent
        if run_dir.name.startswith(".") or run_dir.parent.name in ("hydra", runs.PARTIAL):
            continue
        counts["runs"] += 1
        record = runs.read_json_or_none(record_path)
        if record is None:
            problems.append(f"{record_path}: does not read (the run is computed again when a table needs it)")
            counts["damaged"] += 1
            continue
        if "files" not in record:
            if record.get("status") != "complete":
                continue
            unreadable = [p for p in sorted(run_dir.rglob("*")) if p.is_file() and p.name != runs.RECORD and not _reads(p)]
            problems += [f"{p}: does not read (recorded before file lists: not listed)" for p in unreadable]
            counts["damaged"] += bool(unreadable)
            if list_unlisted and not unreadable:
                runs.list_files_in_record(run_dir)
                counts["listed"] += 1
            else:
                counts["unlisted"] += 1
            continue
        counts["checked"] += 1
        damaged = runs.damaged_files(run_dir, record)
        counts["damaged"] += bool(damaged)
        problems += [f"{run_dir / name}: {why}" for name, why in damaged.items()]
    return problems, counts


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.archived",
                                     description="Convert a run archive's trainings and evaluations in place to the compact form.")
    parser.add_argument("archive", type=Path, help="an archive directory, e.g. results/cpu/runs (with --verify: "
                                                   "a run store too, e.g. runs)")
    instead = parser.add_mutually_exclusive_group()   # one action a call; without any, the conversion
    instead.add_argument("--drop-unlisted", type=Path, metavar="RESULTS_DIR",
                         help="instead: delete the evaluations no table under RESULTS_DIR (e.g. results/cpu) lists")
    instead.add_argument("--first-seed-weights", action="store_true",
                         help="instead: delete the weights of every training that is not the lowest seed of its "
                              "row (keeps the committed tree small; docs/runs.md)")
    instead.add_argument("--verify", action="store_true",
                         help="instead: check every run's files against the sizes and digests its record lists; "
                              "exit 1 if any is damaged (nothing is changed: a damaged run is computed again, or "
                              "rebuilt, by the next command that needs it)")
    parser.add_argument("--dry-run", action="store_true",
                        help="with --drop-unlisted or --first-seed-weights: name them, delete nothing")
    parser.add_argument("--list-unlisted", action="store_true",
                        help="with --verify: give each complete run recorded before file lists, whose every file "
                             "reads whole, its list now (its record is rewritten)")
    args = parser.parse_args(argv)
    # a flag that qualifies an action never runs the conversion, which rewrites the archive, in its place
    if args.dry_run and args.drop_unlisted is None and not args.first_seed_weights:
        parser.error("--dry-run goes with --drop-unlisted or --first-seed-weights (the conversion has none)")
    if args.list_unlisted and not args.verify:
        parser.error("--list-unlisted goes with --verify")
    if args.verify:
        if not args.archive.is_dir():
            print(f"error: {args.archive} is not a directory", file=sys.stderr)
            return 2
        problems, counts = verify(args.archive, args.list_unlisted)
        for line in problems:
            print(line)
        print(f"{args.archive}: {counts['runs']} runs, {counts['checked']} with listed files checked, "
              f"{counts['damaged']} damaged, {counts['listed']} listed now, {counts['unlisted']} complete runs "
              "recorded before file lists (trusted)")
        return 1 if counts["damaged"] else 0
    problem = archive_problem(args.archive, args.drop_unlisted)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    if args.first_seed_weights:
        beyond = weights_beyond_the_first_seed(args.archive)
        size = sum((run_dir / WEIGHTS).stat().st_size for run_dir in beyond)
        for run_dir in beyond:
            print(f"{'would drop' if args.dry_run else 'dropped'} the weights of {run_dir} "
                  f"({(runs.read_record(run_dir / runs.RECORD) or {}).get('label', '?')})")
        if not args.dry_run:
            drop_weights(beyond)
        print(f"{args.archive}: {len(beyond)} trainings beyond their row's first seed, {size / 2**20:.1f} MiB of weights"
              + (" (dry run: none dropped)" if args.dry_run else " dropped"))
        return 0
    if args.drop_unlisted is not None:
        try:
            unlisted = unlisted_evaluations(args.archive, args.drop_unlisted)
        except ValueError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        for run_dir in unlisted:
            print(f"{'would delete' if args.dry_run else 'deleted'} {run_dir} "
                  f"({(runs.read_record(run_dir / runs.RECORD) or {}).get('label', '?')})")
            if not args.dry_run:
                shutil.rmtree(run_dir)
        print(f"{args.archive}: {len(unlisted)} evaluations no table under {args.drop_unlisted} lists"
              + (" (dry run: none deleted)" if args.dry_run else " deleted"))
        return 0
    before, t0 = _size(args.archive), time.perf_counter()
    try:
        converted = convert_archive(args.archive)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    after = _size(args.archive)
    print(f"{args.archive}: {converted} runs converted in {time.perf_counter() - t0:.1f} s; "
          f"{before} -> {after} bytes ({before / 2**20:.1f} -> {after / 2**20:.1f} MiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

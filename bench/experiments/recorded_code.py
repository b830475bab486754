"""The code a run recorded, rebuilt from git, and adopt's replay run in it: the differential check.

adopt holds a stale training to its recorded numbers by replaying it. That needs the frames it trained
on; a training recorded on another render of its split (session 28 changed how multi-light scenes are
built, so the cpu archive's trainings cannot be rendered again anywhere) has none to replay on. What
adopt has to show is narrower: that the code change moves no number. So the code the run's fingerprint
names is rebuilt in a copy of the project (each changed file's most recent version in git history whose
source hash is the recorded one) and the same replay runs there, in a subprocess, and here, on today's
frames: equal numbers mean the change moves none, whatever the frames.

The subprocess runs `python -m bench.experiments.replay JOB OUT` with the copy on its path: JOB is a
pickle of `replay.replay`'s arguments, OUT receives what it returns. The harness (today's experiments)
imports every model module; another model's, which the run's fingerprint does not name, is taken at the
run's recorded git commit, so that it imports what the rebuilt files define (`rebuild`). Every other
file stays today's (bench/measure.py, the experiments): such a file may import from a fingerprinted one
only names its recorded versions define too. Moving a function into a fingerprinted module that one of
them imports fails every replay on the import, and adopt checks nothing (error_summary into bench/errors.py
did: it stays in bench/measure.py).
"""
from __future__ import annotations

import ast
import logging
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench import runs
from bench.errors import UserError

log = logging.getLogger("bench")


MODEL_FOLDERS = ("bench/models/", "baselines/")  # a model's definition: another run's model, never the harness's
HARNESS = ("__init__.py", "factory.py")  # what today's harness imports by name from those folders


def rebuild(recorded: dict, current: dict, dest: Path, commit: str | None = None, repo: Path = runs.ROOT) -> Path:
    """A copy of the project's packages at `dest` in which every file whose recorded source hash differs
    from `current`'s is the version git history has with the recorded hash, with the C++ sources it names
    from the same commit (a file added since stays: the recorded code imports nothing it did not name).
    A file the recorded fingerprint does not name but the replay's harness imports is taken at the run's
    recorded git `commit`, where it exists, so that it imports what the rebuilt files define: one today's
    fingerprint names (the evaluator beside a training's fingerprint, which names only the trainer), and
    another model's definition that neither names (in bench/models or baselines, not their __init__ or the
    factory, which today's harness imports by name; e.g. models/srd.py beside an EDSR run). UserError
    naming a file no version matches."""
    for package in runs.PACKAGES:
        shutil.copytree(repo / package, dest / package, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    changed = runs.code_changes({"code": recorded}, current)
    for path in changed:
        if path in recorded and not _checkout_version(repo, path, recorded[path], dest):
            raise UserError(f"{path}: no version in the git history of {repo} has the recorded source hash "
                            f"{recorded[path]} (the recorded code cannot be rebuilt)")
    if commit and changed:
        models = {p.relative_to(repo).as_posix() for folder in MODEL_FOLDERS for p in (repo / folder).glob("*.py")}
        for path in sorted(p for p in (models | set(current)) - set(recorded) if not p.endswith(HARNESS)):
            shown = _git(repo, "show", f"{commit}:{path}")
            if shown.returncode == 0:
                (dest / path).write_bytes(shown.stdout)
            else:
                log.debug("recorded code: %s is not in commit %s: today's version stays", path, commit)
    return dest


def _git(repo: Path, *args) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, timeout=60)


def _natives(text: str) -> list[str]:
    """The C++ sources a module's text names (`runs.native_sources`); none when it does not parse."""
    try:
        return sorted(runs.native_sources(ast.parse(text)))
    except SyntaxError:
        return []


def _checkout_version(repo: Path, path: str, source_hash: str, dest: Path) -> bool:
    """Write into `dest` the newest version of `path` in git history whose source hash is `source_hash`,
    each candidate with the C++ sources it names from its own commit (a .py's hash covers them)."""
    folder = Path(path).parent
    natives = [str(folder / n) for n in _natives((repo / path).read_text())] if (repo / path).exists() else []
    commits = _git(repo, "log", "--full-history", "--format=%H", "--", path, *natives).stdout.decode().split()
    target = dest / path
    target.parent.mkdir(parents=True, exist_ok=True)
    for commit in commits:
        shown = _git(repo, "show", f"{commit}:{path}")
        if shown.returncode != 0:  # not there in this commit
            continue
        target.write_bytes(shown.stdout)
        for native in _natives(shown.stdout.decode(errors="replace")):
            source = _git(repo, "show", f"{commit}:{(folder / native).as_posix()}")
            if source.returncode == 0:
                (dest / folder / native).write_bytes(source.stdout)
        try:
            if runs.source_hash.__wrapped__(target) == source_hash:  # uncached: one path, many versions
                return True
        except SyntaxError:
            continue
    return False


def replay_there(tree: Path, job: dict, timeout_s: float = 1800) -> dict:
    """adopt's replay of `job` by the code in `tree`, in a subprocess (`replay.main`); its result, with the
    code fingerprint the subprocess computed of what it ran."""
    with tempfile.TemporaryDirectory() as tmp:
        job_file, out_file = Path(tmp) / "job.pkl", Path(tmp) / "out.pkl"
        job_file.write_bytes(pickle.dumps(job))
        env = {**os.environ, "PYTHONPATH": str(tree)}
        # -P: the working directory (where relative paths resolve) does not shadow the rebuilt packages
        try:
            done = subprocess.run([sys.executable, "-P", "-m", "bench.experiments.replay", str(job_file),
                                   str(out_file)], env=env, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"the recorded code's replay took over {timeout_s:.0f} s") from None
        if done.returncode != 0 or not out_file.exists():
            lines = done.stderr.strip().splitlines() or ["no output"]
            log.debug("the recorded code's replay:\n%s", "\n".join(lines[-20:]))
            raise RuntimeError(f"the recorded code's replay failed (exit {done.returncode}): {lines[-1]}")
        return pickle.loads(out_file.read_bytes())

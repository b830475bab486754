"""The code a run recorded, rebuilt from git, and adopt's replay run in it: the differential check.

adopt holds a stale training to its recorded numbers by replaying it. That needs the frames it trained
on; a training recorded on another render of its split (session 28 changed how multi-light scenes are
built, so the cpu archive's trainings cannot be rendered again anywhere) has none to replay on. What
adopt has to show is narrower: that the code change moves no number. So the code the run's fingerprint
names is rebuilt in a copy of the project (each changed file's most recent version in git history whose
source hash is the recorded one) and the same replay runs there, in a subprocess, and here, on today's
frames: equal numbers mean the change moves none, whatever the frames.

The subprocess runs `python -m bench.experiments.adopt JOB OUT` with the copy on its path: JOB is a
pickle of `adopt.replay`'s arguments, OUT receives what it returns.
"""
from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench import runs
from bench.errors import UserError


def rebuild(recorded: dict, current: dict, dest: Path, repo: Path = runs.ROOT) -> Path:
    """A copy of the project's packages at `dest` in which every file whose recorded source hash differs
    from `current`'s is the version git history has with the recorded hash (a file added since stays:
    the recorded code imports nothing it did not name). UserError naming a file no version matches."""
    for package in runs.PACKAGES:
        shutil.copytree(repo / package, dest / package, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    changed = [p for p in runs.code_changes({"code": recorded}, current) if p in recorded]
    for path in sorted(changed, key=lambda p: p.endswith(".py")):  # C++ sources first: a .py hash reads them
        if not _checkout_version(repo, path, recorded[path], dest):
            raise UserError(f"{path}: no version in the git history of {repo} has the recorded source hash "
                            f"{recorded[path]} (the recorded code cannot be rebuilt)")
    return dest


def _checkout_version(repo: Path, path: str, source_hash: str, dest: Path) -> bool:
    """Write into `dest/path` the newest version of `path` in git history whose source hash is `source_hash`."""
    log = subprocess.run(["git", "-C", str(repo), "log", "--format=", "--raw", "--no-abbrev", "--", path],
                         capture_output=True, text=True, timeout=60)
    blobs = dict.fromkeys(line.split()[3] for line in log.stdout.splitlines()
                          if line.startswith(":") and line.split()[3].strip("0"))
    target = dest / path
    target.parent.mkdir(parents=True, exist_ok=True)
    for blob in blobs:
        content = subprocess.run(["git", "-C", str(repo), "cat-file", "blob", blob], capture_output=True,
                                 timeout=60).stdout
        target.write_bytes(content)
        try:
            if runs.source_hash.__wrapped__(target) == source_hash:  # uncached: one path, many versions
                return True
        except SyntaxError:
            continue
    return False


def replay_there(tree: Path, job: dict) -> dict:
    """adopt's replay (`adopt.replay`) of `job` by the code in `tree`, in a subprocess; its result."""
    with tempfile.TemporaryDirectory() as tmp:
        job_file, out_file = Path(tmp) / "job.pkl", Path(tmp) / "out.pkl"
        job_file.write_bytes(pickle.dumps(job))
        env = {**os.environ, "PYTHONPATH": str(tree)}
        done = subprocess.run([sys.executable, "-m", "bench.experiments.adopt", str(job_file),
                               str(out_file)], cwd=tree, env=env, capture_output=True, text=True)
        if done.returncode != 0 or not out_file.exists():
            last = (done.stderr.strip().splitlines() or ["no output"])[-1]
            raise RuntimeError(f"the recorded code's replay failed (exit {done.returncode}): {last}")
        return pickle.loads(out_file.read_bytes())

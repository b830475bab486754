"""The run scheduler: one command's table computed by several processes at once on one machine.

`jobs=N` starts N copies of the command, each a shard (`shard=i/N`: its own (row, seed) runs first, then
those no other shard has reached; bench.experiments.table.compute_shard), on the same run store, so the
run identities, locks and resumption are the ones every command has. On a CPU each copy gets its share
of the cores as its OpenMP threads: on 2 cores two one-thread processes keep both busy where one
two-thread training waits on its own synchronisation (docs/speed.md has the measured figures). On a GPU
the copies share the device. The command that started them then writes the table from the recorded runs.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from bench.errors import UserError


def threads_per_job(jobs: int) -> int:
    """This process's cores, shared out among `jobs` processes (at least one thread each)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // jobs)


def shard_commands(overrides: list[str], jobs: int) -> list[list[str]]:
    """The command line of each of `jobs` shards: `python -m bench` with the command's overrides, its
    shard, one job, and no MLflow mirror (the starting command mirrors once, at its end)."""
    kept = [o for o in overrides if not o.split("=", 1)[0].lstrip("+~") in ("jobs", "shard", "tracking")]
    return [[sys.executable, "-m", "bench", *kept, f"shard={i}/{jobs}", "jobs=1", "tracking=none"]
            for i in range(jobs)]


def _relay(stream, prefix: str) -> None:
    for line in stream:
        sys.stdout.write(f"{prefix}{line}")
        sys.stdout.flush()


def run_shards(overrides: list[str], jobs: int, cwd: Path) -> None:
    """Run the command's shards at once and wait for all of them; each output line is prefixed with its
    shard. Ctrl-C or SIGTERM here is passed on as SIGTERM (each training checkpoints and stops) before
    it is raised; a shard that fails makes this a UserError naming it once the others have finished
    (their runs are recorded, and the same command again resumes the rest)."""
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", str(threads_per_job(jobs)))
    procs = []
    try:
        for i, command in enumerate(shard_commands(overrides, jobs)):
            proc = subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    text=True, start_new_session=True)  # a terminal's Ctrl-C reaches us alone
            relay = threading.Thread(target=_relay, args=(proc.stdout, f"[shard {i}/{jobs}] "), daemon=True)
            relay.start()
            procs.append((proc, relay))
        codes = [proc.wait() for proc, _ in procs]
    except BaseException:  # Ctrl-C, SIGTERM (bench.cli.Terminated): every shard checkpoints and stops
        for proc, _ in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc, relay in procs:
            proc.wait()
            relay.join(timeout=5)
        raise
    for _, relay in procs:
        relay.join(timeout=5)
    failed = [f"shard {i}/{jobs} (exit {code})" for i, code in enumerate(codes) if code != 0]
    if failed:
        raise UserError(f"jobs={jobs}: {', '.join(failed)} failed (its lines above say why); the runs the shards "
                        "recorded are kept, and the same command again resumes the rest")

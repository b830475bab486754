"""The run scheduler (`jobs=N`, bench/scheduler.py): a table's runs computed by shards at once, with real
processes on one run store, then the table written from them."""
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from bench import scheduler
from bench.cli import CONF_DIR, make_context
from bench.errors import UserError
from conftest import bench_here
from test_faults import TINY_CLI

REPO = Path(__file__).resolve().parent.parent


def test_each_shard_runs_the_command_with_its_shard_one_job_and_no_mirror():
    commands = scheduler.shard_commands(["+experiment=sota", "jobs=3", "seeds=[0,1]", "tracking=mlflow"], 3)
    assert [c[3:] for c in commands] == [["+experiment=sota", "seeds=[0,1]", f"shard={i}/3", "jobs=1", "tracking=none"]
                                         for i in range(3)]
    assert all(c[:3] == [sys.executable, "-m", "bench"] for c in commands)
    assert scheduler.threads_per_job(64) == 1 and scheduler.threads_per_job(1) >= 1


def test_jobs_and_shard_together_are_one_line_before_anything_runs(tmp_path):
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=["+experiment=smoke", "preset=smoke", "jobs=2", "shard=0/2",
                                           f"runs_dir={tmp_path}/runs"])
    with pytest.raises(UserError, match="jobs=2 with shard=0/2: jobs starts the shards itself"):
        make_context(cfg)


def test_jobs_trains_each_seed_once_across_the_shards_then_writes_the_table(tmp_path):
    """Two seeds, jobs=2: two shard processes share the run store (each seed trained once, by either),
    every line says which shard printed it, and the starting command writes the table reusing both."""
    out = bench_here(*TINY_CLI, "seeds=[0,1]", "jobs=2", f"runs_dir={tmp_path / 'runs'}",  # the shards: processes
                     f"results_dir={tmp_path / 'results'}", f"data_dir={tmp_path / 'data'}")
    log = out.stdout + out.stderr
    assert out.returncode == 0, log[-3000:]
    assert log.count("trained in") == 2 and all(f"[shard {i}/2]" in log for i in (0, 1)), log[-3000:]
    assert all("trained in" not in line or line.startswith("[shard ") for line in log.splitlines())
    assert "smoke: 1 of 1 rows reused from the run store" in log
    table = pd.read_csv(tmp_path / "results" / "smoke" / "table.csv")
    assert list(table["method"]) == ["E"] and table["PSNR std"].notna().all()


def test_a_sigterm_to_the_command_stops_every_shard_at_a_checkpoint_each_run_recorded_interrupted(tmp_path):
    import signal
    import time
    command = [sys.executable, "-m", "bench", *TINY_CLI, "seeds=[0,1]", "jobs=2", "train.steps=100000",
               f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}", f"data_dir={tmp_path / 'data'}"]
    proc = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 120
    while len(list((tmp_path / "runs").glob("train/*/checkpoint.pt"))) < 2 and time.time() < deadline:
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 143, out[-3000:]
    assert all(f"[shard {i}/2] error: training E stopped by SIGTERM" in out for i in (0, 1)), out[-3000:]
    records = [p.read_text() for p in (tmp_path / "runs").glob("train/*/run.json")]
    assert len(records) == 2 and all('"status": "interrupted"' in r for r in records)

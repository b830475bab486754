"""Scale-out and tracking end to end: a table's trainings sharded over two joblib jobs, a final run that
reuses them and mirrors the run store into MLflow, read back with MLflow's own client."""
import json
import os
import re
from pathlib import Path

import pandas as pd
import pytest

from bench import runs, tracking
from conftest import SMOKE_DATA, bench_here, python_process



def bench(*args):
    env = dict(os.environ, HYDRA_FULL_ERROR="0", PYTHONUNBUFFERED="1", SRD_TRACKING="none")
    return python_process("-m", "bench", *args, env=env)


@pytest.fixture(scope="module")
def store(tmp_path_factory, smoke_data):
    """Two joblib jobs train the smoke table's two (row, seed) runs; a final run assembles the table from
    them and mirrors every run into MLflow (the data run too: the shared render's record)."""
    root = tmp_path_factory.mktemp("tracked")
    smoke_data(root / "data", root / "runs")
    args = ["+experiment=smoke", f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}",
            f"data_dir={root / 'data'}", "progress=false", "train.steps=6", *SMOKE_DATA]
    sweep = bench("-m", "hydra/launcher=joblib", "shard=0/2,1/2", *args)
    assert sweep.returncode == 0, sweep.stderr[-3000:]
    assert not (root / "runs" / "mlflow.db").exists()  # tracking=none: no MLflow store
    final = bench_here(*args, "tracking=mlflow")
    assert final.returncode == 0, final.stderr[-3000:]
    return root, sweep.stdout + sweep.stderr, final.stdout + final.stderr


def client_of(root):
    # imported here, not at the top: both xdist workers collect every file, one runs this one (MLflow: 1-2 s)
    from mlflow.tracking import MlflowClient
    return MlflowClient(tracking_uri=tracking.default_uri(root / "runs"))


def mirrored(client, kind):
    experiment = client.get_experiment_by_name(tracking.EXPERIMENT_PREFIX + kind)
    return client.search_runs([experiment.experiment_id]) if experiment else []


def test_joblib_shards_train_disjoint_runs_and_the_final_run_reuses_them(store):
    root, sweep_log, final_log = store
    for index in (0, 1):  # its own unit, and the other's too when that one was free (then reused)
        assert re.search(rf"shard {index}/2 computed or found [12] of 2 \(row, seed\) runs", sweep_log)
    assert sweep_log.count("train Ours: trained") == 1          # one shard trained it, once
    assert "2 of 2 rows reused" in final_log
    assert not list((root / "results" / "sweeps").glob("*/smoke/table.csv"))  # shards write no table
    assert (root / "results" / "smoke" / "table.csv").exists()


def test_every_recorded_run_is_listed_by_mlflow_with_params_metrics_tags_and_artifacts(store):
    root, _, final_log = store
    assert "runs logged to MLflow" in final_log
    client = client_of(root)
    for kind in ("train", "eval", "data"):
        recorded = runs.load(root / "runs", kind)
        listed = {r.data.tags["srd.hash"]: r for r in mirrored(client, kind)}
        assert set(listed) == set(recorded["hash"]), kind
    train = runs.load(root / "runs", "train").iloc[0]
    run = {r.data.tags["srd.hash"]: r for r in mirrored(client, "train")}[train["hash"]]
    assert run.info.status == "FINISHED" and run.info.run_name == "Ours seed 0"
    assert run.data.params["model._target_"] == "bench.models.srd.SRDNet"
    assert run.data.params["train.steps"] == "6"
    assert run.data.tags["mlflow.source.git.commit"] == train["git_commit"]
    assert run.data.tags["srd.tables"] == "smoke"  # through the evaluation that fed the table
    record = json.loads((Path(train["dir"]) / "run.json").read_text())
    assert run.data.tags["srd.code"] == runs.config_hash(record["code"])
    assert run.data.metrics["val.PSNR"] == pytest.approx(record["metrics"]["val"]["PSNR"])
    history = client.get_metric_history(run.info.run_id, "train.loss")
    assert sorted(m.step for m in history) == list(range(1, 7))  # the whole curve, by step
    curve = pd.read_csv(Path(train["dir"]) / "val_curve.csv")
    assert {m.step for m in client.get_metric_history(run.info.run_id, "val.PSNR")} == set(curve["step"])
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"run.json", "curve.csv", "weights.pt", "weights.pt.json", "tables"} <= artifacts
    evaluation = {r.data.tags["srd.hash"]: r for r in mirrored(client, "eval")}
    table = pd.read_csv(root / "results" / "smoke" / "table.csv")
    ours = evaluation[table.set_index("method").loc["Ours", "runs"]]
    assert ours.data.metrics["PSNR"] == pytest.approx(table.set_index("method").loc["Ours", "PSNR"])
    assert ours.data.tags["srd.train_run"] == train["hash"]
    assert "per_image.csv" in {a.path for a in client.list_artifacts(ours.info.run_id)}


def test_a_second_sync_logs_nothing_and_a_changed_record_replaces_its_mirror(store):
    root, _, _ = store
    assert tracking.sync(root / "runs", None, root / "results") == \
        {"logged": 0, "replaced": 0, "tables": 0, "unchanged": len(runs.load(root / "runs"))}
    record_path = next((root / "runs" / "eval").glob("*/run.json"))
    record = json.loads(record_path.read_text())
    record["metrics"]["PSNR"] += 1.0  # as a re-evaluation would change it
    record_path.write_text(json.dumps(record))
    counts = tracking.sync(root / "runs", None, root / "results")
    assert counts["replaced"] == 1 and counts["logged"] == 0
    listed = [r for r in mirrored(client_of(root), "eval") if r.data.tags["srd.hash"] == record["hash"]]
    assert len(listed) == 1 and listed[0].data.metrics["PSNR"] == pytest.approx(record["metrics"]["PSNR"])


def test_a_tracking_failure_is_a_warning_not_an_error(store, monkeypatch, caplog):
    from bench.cli import mirror_runs
    root, _, _ = store
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")   # should port 9 ever listen: no minutes of retries
    mirror_runs("mlflow", root / "runs", "http://127.0.0.1:9", root / "results")  # nothing listens there
    assert "tracking: mirroring runs to MLflow failed" in caplog.text


def test_a_server_that_refuses_is_said_at_once_and_a_proxied_one_is_left_to_mlflow(monkeypatch):
    """MLflow's own retries on a refused connection took 110-253 s; the probe says it in one connect."""
    import socket
    import time
    with socket.socket() as listening:                 # a port that was free and is closed again: refused
        listening.bind(("127.0.0.1", 0))
        port = listening.getsockname()[1]
    t0 = time.perf_counter()
    with pytest.raises(ConnectionError, match=f"the MLflow server http://127.0.0.1:{port} does not answer"):
        tracking.check_server(f"http://127.0.0.1:{port}")
    assert time.perf_counter() - t0 < 6
    tracking.check_server("sqlite:///x.db")                                      # not a server: nothing to probe
    monkeypatch.setenv("http_proxy", "http://proxy.invalid:3128")
    monkeypatch.setenv("no_proxy", "")
    tracking.check_server(f"http://mlflow.example:{port}")                       # through the proxy: MLflow's


@pytest.mark.slow  # submitit's local executor starts two jobs; make test-slow
def test_submitit_local_launcher_runs_a_sweep(tmp_path):
    """submitit's local executor (the Slurm launcher's stand-in without a cluster): two jobs, two tables."""
    out = bench("-m", "hydra/launcher=submitit_local", "+experiment=macs", "preset=smoke", "seeds=[0],[1]",
                f"runs_dir={tmp_path}/runs", f"results_dir={tmp_path}/results", "progress=false")
    assert out.returncode == 0, out.stderr[-2000:]
    tables = sorted(p.parent.parent.name for p in (tmp_path / "results" / "sweeps").glob("*/macs/table.csv"))
    assert tables == ["seeds=_0_", "seeds=_1_"]


def test_a_training_whose_archive_left_its_weights_out_is_mirrored_without_them(tmp_path):
    """The archive keeps some trainings without weights (docs/runs.md); mirroring one logs its record and
    curve, not a failure that stops the whole mirror."""
    run_dir = tmp_path / "runs" / "train" / ("0" * 16)
    run_dir.mkdir(parents=True)
    record = {"kind": "train", "hash": "0" * 16, "status": "complete", "identity": {"model": {}}}
    (run_dir / runs.RECORD).write_text(json.dumps(record))
    (run_dir / "curve.csv").write_text("step,loss\n1,0.5\n")
    logged = []

    class Client:
        def log_artifact(self, run_id, path):
            logged.append(Path(path).name)
    tracking._log_artifacts(Client(), "id", record, run_dir)
    assert logged == ["run.json", "curve.csv"]

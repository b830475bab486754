"""MLflow as the run store's view: every recorded run, mirrored into an MLflow tracking store.

The run store (bench/runs.py) stays the source of truth for reuse; MLflow is where runs are browsed and
compared (`mlflow ui --backend-store-uri sqlite:///runs/mlflow.db`). After each command the CLI calls
`sync`, which mirrors every complete or failed run the store holds and MLflow does not (or holds in an
older version), so runs computed by other processes (shards, sweep jobs) appear too. Per run:

- the MLflow experiment `srd-bench/<kind>` (train, eval, data, time), run name = label + seed;
- params: the run's identity, flattened (`model.channels`, `train.lr`, ...);
- metrics: the final metrics (`val.PSNR` for a training), and for a training its curves by step
  (`train.loss`, `train.lr`, ... from curve.csv, or an archived run's curve.csv.gz; `val.PSNR`, ... from
  val_curve.csv);
- tags: `srd.hash`, `srd.kind`, `srd.status`, the git commit (`mlflow.source.git.commit`) and dirty flag,
  host, device, and the code fingerprint (its digest; the per-file hashes are in the run.json artifact);
- artifacts: run.json, a training's weights (`weights.pt`, as `srd-bench export` writes them) and curves,
  an evaluation's per-image metrics, and every table under `results_dir` that lists the run.

A run is matched by its `srd.hash` tag; when its record changed since (recomputed after a code change,
re-evaluated), the MLflow run is replaced. One process syncs at a time (a lock beside the store).
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import socket
import subprocess
import sys
import tempfile
from contextlib import closing
from datetime import datetime
from pathlib import Path
from urllib.parse import urlparse
from urllib.request import getproxies, proxy_bypass

import pandas as pd

from bench import archived, runs
from bench.table_writer import listed_evaluations, read_table

log = logging.getLogger("bench")

EXPERIMENT_PREFIX = "srd-bench/"
LAYOUT = 2                                 # bump when what a mirrored run shows changes: every run is re-logged
MIRRORED = ("complete", "failed")          # statuses worth a view; running/abandoned runs are not final
_BATCH = 1000                              # MLflow's limit of entities per log_batch call


def default_uri(runs_dir: str | Path) -> str:
    """The embedded store: an SQLite file inside the run store."""
    return f"sqlite:///{(Path(runs_dir) / 'mlflow.db').resolve()}"


def check_server(uri: str, timeout_s: float = 5.0) -> None:
    """A server URI that does not take a connection raises ConnectionError at once: MLflow's client would
    retry each request for minutes before giving up."""
    parsed = urlparse(uri)
    if parsed.scheme not in ("http", "https") or (parsed.scheme in getproxies() and not proxy_bypass(parsed.hostname)):
        return  # through a proxy, only MLflow's own requests tell
    try:
        socket.create_connection((parsed.hostname, parsed.port or (443 if parsed.scheme == "https" else 80)),
                                 timeout=timeout_s).close()
    except OSError as err:
        raise ConnectionError(f"the MLflow server {uri} does not answer ({err.strerror or err})") from err


def sync(runs_dir: str | Path, uri: str | None = None, results_dir: str | Path | None = None) -> dict:
    """Mirror the run store into MLflow at `uri` (None: `default_uri(runs_dir)`); returns counts
    {"logged": new runs, "replaced": runs whose record changed, "tables": runs whose tables changed,
    "unchanged": the rest}."""
    from mlflow.tracking import MlflowClient
    runs_dir = Path(runs_dir)
    local = uri is None
    uri = uri or default_uri(runs_dir)
    check_server(uri)
    tables = _tables_by_run(Path(results_dir)) if results_dir else {}
    counts = {"logged": 0, "replaced": 0, "tables": 0, "unchanged": 0}
    with closing(runs.acquire(runs_dir / ".mlflow.lock", "mirroring the run store to MLflow")):
        client = MlflowClient(tracking_uri=uri)
        by_kind = {d.name: [r for r in _records(d) if r.get("status") in MIRRORED]
                   for d in sorted(p for p in runs_dir.iterdir() if p.is_dir())}
        for record in by_kind.get("eval", []):  # a training feeds the tables its evaluations feed
            for h in runs.trainings_of(record):
                tables.setdefault(h, []).extend(tables.get(record["hash"], []))
        replaced = []
        for kind, records in by_kind.items():
            if not records:
                continue
            experiment = _experiment(client, kind, runs_dir if local else None)
            mirrored = {r.data.tags.get("srd.hash"): r for r in _all_runs(client, experiment)}
            for record in records:
                counts[_mirror(client, experiment, record, mirrored.get(record["hash"]),
                               dict(tables.get(record["hash"], [])), runs_dir / kind / record["hash"],
                               replaced)] += 1
        if replaced:
            _purge(client, replaced, uri)
    return counts


def _mirror(client, experiment: str, record: dict, old, tables: dict[str, Path], run_dir: Path,
            replaced: list) -> str:
    """Bring one run's mirror up to date; returns what was done (a key of sync's counts). A changed
    record gets a new MLflow run (the old one's id goes to `replaced`); changed tables are re-attached."""
    version = _digest(f"{LAYOUT}:{json.dumps(record, sort_keys=True, default=str)}")
    tables_version = _digest("".join(f"{name}:{_digest(path.read_bytes())}" for name, path in sorted(tables.items())))
    done = "unchanged"
    if old is not None and old.data.tags.get("srd.version") == version:
        run_id, tags = old.info.run_id, old.data.tags
    else:
        if old is not None:
            replaced.append(old.info.run_id)
        run_id, tags = _log_run(client, experiment, record, run_dir, version), {}
        done = "logged" if old is None else "replaced"
    if tags.get("srd.tables_version") != tables_version:
        for name, path in tables.items():
            client.log_artifact(run_id, str(path), artifact_path=f"tables/{name}")
        client.set_tag(run_id, "srd.tables", ",".join(sorted(tables)))
        client.set_tag(run_id, "srd.tables_version", tables_version)
        done = "tables" if done == "unchanged" else done
    return done


# ---------------------------------------------------------------- reading the store

def _records(kind_dir: Path) -> list[dict]:
    out = []
    for path in sorted(kind_dir.glob(f"*/{runs.RECORD}")):
        record = runs.read_record(path)  # None: damaged (the log names it)
        if record is not None:
            out.append(record)
    return out


def _tables_by_run(results_dir: Path) -> dict[str, list[tuple[str, Path]]]:
    """run hash -> [(table name, table.csv)] for every table under `results_dir` that lists it in its `runs`
    column (an evaluation; `sync` gives its trainings its tables)."""
    out: dict[str, list] = {}
    for path in sorted(results_dir.rglob("table.csv")):
        try:
            table = read_table(path)
        except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError):
            continue
        name = str(path.parent.relative_to(results_dir))
        for cell in table.get("runs", []):
            for h in listed_evaluations(cell):
                out.setdefault(h, []).append((name, path))
    return out


def _digest(data: str | bytes) -> str:
    return hashlib.sha256(data.encode() if isinstance(data, str) else data).hexdigest()[:16]


# ---------------------------------------------------------------- writing MLflow

KIND_TAG = {"mlflow.experimentKind": "custom_model_development"}  # the UI opens on runs, not GenAI traces


def _experiment(client, kind: str, local_runs_dir: Path | None) -> str:
    name = EXPERIMENT_PREFIX + kind
    found = client.get_experiment_by_name(name)
    if found is not None:
        if not KIND_TAG.items() <= found.tags.items():
            client.set_experiment_tag(found.experiment_id, *next(iter(KIND_TAG.items())))
        return found.experiment_id
    location = (local_runs_dir / "mlflow-artifacts" / kind).resolve().as_uri() if local_runs_dir else None
    return client.create_experiment(name, artifact_location=location, tags=KIND_TAG)


def _all_runs(client, experiment_id: str) -> list:
    out, token = [], None
    while True:
        page = client.search_runs([experiment_id], max_results=5000, page_token=token)
        out += list(page)
        token = page.token
        if not token:
            return out


def _log_run(client, experiment_id: str, record: dict, run_dir: Path, version: str) -> str:
    """A new MLflow run mirroring `record`; returns its id."""
    from mlflow.entities import Metric, Param
    seed = record.get("seed")
    name = " ".join(str(p) for p in (record.get("label") or record["hash"],
                                      f"seed {seed}" if seed is not None else None) if p)
    tags = {"srd.hash": record["hash"], "srd.kind": record["kind"], "srd.status": record["status"],
            "srd.version": version, "srd.host": record.get("host"), "srd.device": record.get("device"),
            "srd.git_dirty": record.get("git_dirty"), "mlflow.source.git.commit": record.get("git_commit"),
            "srd.code": runs.config_hash(record["code"]) if record.get("code") else None,
            "srd.error": record.get("error"),
            "srd.train_run": (record.get("metrics") or {}).get("train_run")}
    start = _ms(record.get("started"))
    run = client.create_run(experiment_id, start_time=start, run_name=name,
                            tags={k: str(v)[:5000] for k, v in tags.items() if v is not None})
    run_id = run.info.run_id
    params = [Param(k, str(v)[:6000]) for k, v in runs.flatten(record.get("identity", {})).items()]
    # the final metrics at the last step, so that a training's `val.PSNR` history ends with them
    last_step, end = int((record.get("metrics") or {}).get("steps") or 0), _ms(record.get("finished")) or start or 0
    metrics = _curve_metrics(run_dir, start or 0)
    metrics += [Metric(k, v, end, last_step) for k, v in _numbers(record.get("metrics", {})).items()]
    for i in range(0, max(len(params), 1), 100):  # MLflow takes at most 100 params per call
        client.log_batch(run_id, params=params[i:i + 100])
    for i in range(0, len(metrics), _BATCH):
        client.log_batch(run_id, metrics=metrics[i:i + _BATCH])
    _log_artifacts(client, run_id, record, run_dir)
    client.set_terminated(run_id, "FINISHED" if record["status"] == "complete" else "FAILED",
                          end_time=_ms(record.get("finished")))
    return run_id


def _purge(client, run_ids: list[str], uri: str) -> None:
    """Delete replaced runs for good, metrics and artifacts included: `delete_run` only marks a run
    deleted, and MLflow's own `mlflow gc` is what removes it."""
    for run_id in run_ids:
        client.delete_run(run_id)
    subprocess.run([sys.executable, "-m", "mlflow", "gc", "--backend-store-uri", uri, "--run-ids", ",".join(run_ids)],
                   env={**os.environ, "MLFLOW_TRACKING_URI": uri}, check=True, capture_output=True)


def _curve_metrics(run_dir: Path, start_ms: int) -> list:
    """A training's curves by step: its per-step curve (bench.archived) as `train.<column>`,
    val_curve.csv as `val.<column>`."""
    from mlflow.entities import Metric
    out = []
    for curve, prefix in ((archived.read_curve(run_dir), "train."), (archived.read_val_curve(run_dir), "val.")):
        if curve is None:
            continue
        for row in curve.to_dict("records"):
            step = int(row.pop("step"))
            at = start_ms + int(1000 * (row.get("train_s") or 0))
            out += [Metric(prefix + k, float(v), at, step) for k, v in row.items()
                    if isinstance(v, (int, float)) and math.isfinite(v)]
    return out


def _log_artifacts(client, run_id: str, record: dict, run_dir: Path) -> None:
    client.log_artifact(run_id, str(run_dir / runs.RECORD))
    for file in (archived.CURVE, archived.COMPACT_CURVE, archived.VAL_CURVE, archived.PER_IMAGE,
                 archived.COMPACT_PER_IMAGE):
        if (run_dir / file).exists():
            client.log_artifact(run_id, str(run_dir / file))
    # weights where the run has them: an archive leaves some out (docs/runs.md), and the run is mirrored without
    if record["kind"] == "train" and record["status"] == "complete" and not record["identity"].get("stage") \
            and archived.has_weights(run_dir):
        from bench.weights import export  # the published weights format, identity and sha256 beside them
        with tempfile.TemporaryDirectory() as tmp:
            out = export(record["hash"], Path(tmp) / "weights.pt", run_dir.parent.parent)
            client.log_artifact(run_id, str(out))
            client.log_artifact(run_id, str(out.with_suffix(".pt.json")))


def _numbers(metrics: dict) -> dict:
    """The finite numeric entries of a metrics dict, nested keys joined by '.'."""
    return {k: float(v) for k, v in runs.flatten(metrics).items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}


def _ms(timestamp: str | None) -> int | None:
    if not timestamp:
        return None
    try:
        return int(datetime.strptime(timestamp, "%Y-%m-%dT%H:%M:%S%z").timestamp() * 1000)
    except ValueError:
        return None

"""The exported weights file (`srd-bench export`): a recorded training run's weights outside the run
store, with what is needed to use them.

An exported file holds the model's config (its `_target_` and arguments), the upsampling factor, the
network domain (`hdr`) it was trained in, its evaluation weights (the EMA when the recipe kept one), the
training run's identity, metrics and code fingerprint; weights the archive rounded to float16 in its
compact form (`bench.archived.encode`): the values evaluation scored, bit for bit. A JSON beside it
repeats all but the weights and adds the file's sha256, which `load_exported` checks. `bench.predict` applies such a file (or a recorded
run, `from_run`) to EXR frames; `bench.tracking` attaches one to each training it mirrors.
"""
from __future__ import annotations

import hashlib
import json
import lzma
from pathlib import Path

import torch

from bench import archived, exposure, runs
from bench.atomic import write_atomic
from bench.errors import UserError
from bench.models.factory import build_model
from bench.tasks import get_task

# /2: the weights may be in the archive's compact float16 form (COMPACT); a /1 reader would fail on it, so
# it refuses a /2 file by its format instead. This reader reads both.
FORMAT = "srd-bench-weights/2"
READABLE_FORMATS = ("srd-bench-weights/1", FORMAT)
COMPACT = "weights_float16_compact"  # instead of "state_dict" when the run's weights are float16-rounded

def training_record(run_hash: str, runs_dir: str | Path) -> Path:
    """The run.json of training run `run_hash`: in the run store, else in a committed archive (a fresh
    clone has no run store)."""
    path, _ = runs.find_record("train", run_hash, runs_dir, runs.committed_archives())
    if path is None:
        raise UserError(f"no training run {run_hash} in {runs_dir} (runs are directories of "
                        f"{Path(runs_dir) / 'train'}) or in {runs.committed_archive('*')}/train or results/*/runs/train")
    return path


def finished_training(run_hash: str, runs_dir: str | Path) -> tuple[Path, dict]:
    """(run.json path, record) of training run `run_hash`, which must be complete and a whole model (not an
    interrupted run's last checkpoint, nor one stage of a Cascade)."""
    path = training_record(run_hash, runs_dir)
    record = runs.read_record(path)
    if record is None:
        raise UserError(f"{path} does not read (damaged); train the run again")
    if record.get("status") != "complete":
        raise UserError(f"training run {run_hash} is {record.get('status')!r}, not complete: its weights are "
                        "not the trained model's; run its table again to finish it")
    if record["identity"].get("stage"):
        raise UserError(f"run {run_hash} trained one stage of a Cascade; use a whole model's run")
    return path, record


def export(run_hash: str, out: str | Path, runs_dir: str | Path, force: bool = False) -> Path:
    """Write the weights of the complete training run `run_hash` to `out` (+ `out`.json); an existing
    file there (a committed weights file, an earlier export, a run's own checkpoint) only with `force`."""
    out = Path(out)
    if out.is_dir():
        raise UserError(f"--out {out} is a folder: give the weights file's path, e.g. {out / 'weights.pt'}")
    taken = [p for p in (out, out.with_suffix(out.suffix + ".json")) if p.is_file()]
    if taken and not force:
        raise UserError(f"--out {out}: {taken[0]} exists; --force replaces it")
    path, record = finished_training(run_hash, runs_dir)
    identity = record["identity"]
    cfg, task = identity["model"], get_task(identity["task"])
    if not archived.has_weights(path.parent):
        raise UserError(_no_weights(run_hash, path.parent, record, runs_dir, then="export"))
    model = archived.load_weights(build_model(cfg, task.scale), path.parent)
    meta = {"format": FORMAT, "model": cfg, "task": task.name, "scale": task.scale,
            "hdr": identity["train"]["hdr"], "run": run_hash, "identity": identity,
            "weights_rounded_to_float16": archived.rounded(path.parent),
            "metrics": record.get("metrics", {}), "code": record.get("code"),
            "git_commit": record.get("git_commit"), "git_dirty": record.get("git_dirty")}
    out.parent.mkdir(parents=True, exist_ok=True)
    # float16-rounded weights in the archive's compact form: the same values, a quarter of the bytes
    weights = ({COMPACT: archived.encode(model.state_dict())} if meta["weights_rounded_to_float16"]
               else {"state_dict": model.state_dict()})
    # never half a file, also where --force replaces a committed one
    write_atomic(out, lambda tmp: torch.save({**meta, **weights}, tmp))
    meta["sha256"] = hashlib.sha256(out.read_bytes()).hexdigest()
    sidecar = json.dumps(meta, indent=2, sort_keys=True, default=str)
    write_atomic(out.with_suffix(out.suffix + ".json"), lambda tmp: tmp.write_text(sidecar))
    return out


def _one_line(err: BaseException) -> str:
    """An exception's message on one line (torch's load_state_dict errors span many)."""
    text = " ".join(str(err).split())
    return text if len(text) <= 300 else text[:297] + "..."


def _model_with(cfg: dict, scale: int, state_dict, source) -> torch.nn.Module:
    """The model `cfg` builds with `state_dict` loaded: a config that does not build or weights of
    another model are one UserError naming `source`."""
    try:
        model = build_model(cfg, scale)
    except Exception as err:  # hydra wraps whatever the constructor raised
        target = cfg.get("_target_") if isinstance(cfg, dict) else repr(cfg)
        raise UserError(f"{source}: its model config ({target}) does not build: {_one_line(err)}") from err
    try:
        model.load_state_dict(state_dict)
    except (RuntimeError, TypeError, KeyError, AttributeError) as err:
        raise UserError(f"{source}: its weights are not those of its model {cfg.get('_target_')} "
                        f"({_one_line(err)})") from err
    return model


def _torch_load(path: Path, what: str):
    """torch.load of a file the user gave or a run holds; a damaged one (truncated, not a torch file) is
    one UserError."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:
        raise UserError(f"{path}: {what} does not load (truncated or damaged: {_one_line(err)}); "
                        "export it again") from err


def load_exported(path: str | Path):
    """(model in eval mode, metadata) from an exported weights file; its sha256 is checked against the
    JSON beside it when there is one. A leading `~` is the home folder (a path in a Hydra override or a
    config reaches here without a shell)."""
    path = Path(path).expanduser()
    if path.is_dir():
        found = sorted(p.name for p in path.glob("*.pt"))
        raise UserError(f"--weights {path} is a folder: give a weights file"
                        + (f" in it ({', '.join(found)})" if found else " (.pt, written by `srd-bench export`)"))
    if not path.is_file():
        raise UserError(f"weights file {path} does not exist")
    sidecar = path.with_suffix(path.suffix + ".json")
    if sidecar.exists():
        recorded = runs.read_json_or_none(sidecar)
        if recorded is None:
            raise UserError(f"{sidecar} is damaged (not a JSON object): export the weights again, or remove it "
                            "to load the weights without their sha256 check")
        expected = recorded.get("sha256")
        actual = hashlib.sha256(path.read_bytes()).hexdigest()
        if expected and expected != actual:
            raise UserError(f"{path}: sha256 {actual[:16]}... does not match {sidecar.name} ({expected[:16]}...): "
                            "the file is damaged or not the one exported")
    saved = _torch_load(path, "the weights file")
    if not isinstance(saved, dict) or saved.get("format") not in READABLE_FORMATS:
        newer = isinstance(saved, dict) and str(saved.get("format", "")).startswith("srd-bench-weights/")
        raise UserError(f"{path} is " + (f"an SRD-Bench weights file of a newer format ({saved['format']}): update "
                                         "SRD-Bench to read it" if newer else
                                         "not an SRD-Bench weights file (write one with `srd-bench export RUN`)"))
    lacking = [key for key in ("model", "scale", "hdr") if key not in saved]
    if lacking or not ({COMPACT, "state_dict"} & set(saved)):
        raise UserError(f"{path}: an SRD-Bench weights file without its {', '.join(lacking) or 'weights'}: "
                        "damaged or not written by `srd-bench export`; export it again")
    if saved["hdr"] not in exposure.DOMAINS:
        raise UserError(f"{path}: its network domain hdr={saved['hdr']!r} is none of {', '.join(exposure.DOMAINS)} "
                        "(bench.exposure): damaged or not written by `srd-bench export`; export it again")
    try:
        state = archived.decode(saved[COMPACT]) if COMPACT in saved else saved["state_dict"]
    except (KeyError, ValueError, RuntimeError, EOFError, lzma.LZMAError) as err:
        raise UserError(f"{path}: its weights do not read ({_one_line(err)}); export them again") from err
    model = _model_with(saved["model"], saved["scale"], state, path)
    return model.eval(), {k: v for k, v in saved.items() if k not in ("state_dict", COMPACT)}


def _no_weights(run_hash: str, run_dir: Path, record: dict, runs_dir, then: str) -> str:
    """Why a recorded training has no weights here, and how to get them (export and predict --run say it)."""
    seed = record["identity"].get("seed", record.get("seed"))
    return (f"training run {run_hash} has no weights in {run_dir}: the archive leaves some out of git (every seed's but "
            f"a row's first, files over {runs.ARCHIVED_FILE_MAX_BYTES / 2**20:.1f} MiB, retired studies'; docs/runs.md). The run "
            f"store of the machine that trained it has them. Elsewhere, run the table whose row it is with "
            f"seeds=[{seed}] results_dir=<a scratch folder>: its crops.png loads that seed's weights, which trains "
            f"the run again into {runs_dir}; then {then}")


def from_run(run_hash: str, runs_dir: str | Path):
    """(model, metadata) of a recorded training run, without exporting it."""
    path, record = finished_training(run_hash, runs_dir)
    identity = record["identity"]
    task = get_task(identity["task"])
    checkpoint = archived.weights_file(path.parent)
    if checkpoint is None:
        raise UserError(_no_weights(run_hash, path.parent, record, runs_dir, then="predict"))
    try:
        state = archived.state_dict(path.parent)
    except Exception as err:
        raise UserError(f"{checkpoint}: the run's weights do not load (truncated or damaged: {_one_line(err)}); "
                        "train the run again") from err
    model = _model_with(identity["model"], task.scale, state, checkpoint)
    return model.eval(), {"model": identity["model"], "task": task.name, "scale": task.scale,
                          "hdr": identity["train"]["hdr"], "run": run_hash}

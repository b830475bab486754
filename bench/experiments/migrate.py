"""`+experiment=migrate`: re-key every recorded training and evaluation to the identity of
`runs.IDENTITY_VERSION`, so that the current code finds them instead of recomputing them.

Version 2 (from 1, which had no `version` key): the training identity names every recipe option (the
options added later, `colour_permute`, `precision`, `channels_last`, were left out at their defaults, which
are filled in) and leaves out loss terms of weight 0; the evaluation identity names `fast_path` (before:
`path`, present only when not fp32) and `tile`. Each run's new identity is computed from its recorded one
through the current `Recipe.identity()`, its hash recomputed, its directory moved (`migrated_from` keeps
the old hash) and every link to it rewritten: an evaluation's `trained` and `train_run` (a Cascade's
stages joined by "+"), and the hashes the committed result files under `results_dir` quote (tables, the
exported weights' sidecars). A run recorded with an option that no longer exists (`train_sequences` set, an
`ssim_linear` loss term) is not representable: it is listed as dropped, with its evaluations, and deleted
only with `delete_dropped`. Running it again changes nothing.

Writes `<results_dir>/<name>/table.{csv,md,tex}` (per store and kind: re-keyed, left as recorded,
dropped) and `runs.csv` (every run: store, kind, old and new hash, outcome).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import re
import shutil
from pathlib import Path

import pandas as pd

from bench import runs
from bench.atomic import write_atomic
from bench.experiments.context import Context
from bench.infer import REFERENCE
from bench.losses import absolute_weights
from bench.table_writer import write_table
from bench.train import Recipe

log = logging.getLogger("bench")

# the values the version-1 identity implied for the options it left out at their defaults
IMPLIED_V1 = {"colour_permute": False, "precision": "fp32", "channels_last": False}
# options added since, at the value a recipe recorded before them had (bench.train.Recipe.OMITTED_AT: the
# identity leaves them out there); here too, not read from it, because a replay of recorded code has that
# code's Recipe (tests/test_migrate.py checks the two agree)
IMPLIED = {**IMPLIED_V1, "compile": None, "emitters": 0.0, "fireflies": 0.0, "emitters_exposure": "with",
           "loss_knee": None}
# options that are gone: a run recorded with one set otherwise than this cannot be represented
RETIRED_OPTIONS = {"train_sequences": None}
RETIRED_LOSS_TERMS = ("ssim_linear",)
HASH = re.compile(r'(?<!"migrated_from": ")\b[0-9a-f]{16}\b')  # a run hash; an old one kept as such stays
RESULT_SUFFIXES = (".csv", ".md", ".tex", ".json")
REKEYED, CURRENT, UNLINKED, DROPPED = ("re-keyed", "left as recorded (version 2)",
                                       "left as recorded (its training is in no store)", "dropped")


class NotRepresentable(ValueError):
    """A recorded identity that the current code cannot compute (an option that no longer exists)."""


def train_identity(old: dict) -> dict:
    """The current identity of a recorded training identity (version 1 or current)."""
    if old.get("version") == runs.IDENTITY_VERSION:
        return old
    train = dict(old["train"])
    for option, value in RETIRED_OPTIONS.items():
        if option in train and train[option] != value:
            raise NotRepresentable(f"train.{option}={train[option]!r}: the option no longer exists")
    for head, terms in train["loss"].items():
        for term in RETIRED_LOSS_TERMS:
            if terms.get(term, 0):
                raise NotRepresentable(f"train.loss.{head}.{term}={terms[term]}: the loss term no longer exists")
        try:
            absolute_weights(terms)
        except ValueError as err:
            raise NotRepresentable(f"train.loss.{head}: {err}") from None
    recipe_options = {f.name for f in dataclasses.fields(Recipe)} - set(Recipe.NOT_IDENTITY)
    values = {**IMPLIED, **train}
    for option in set(values) - recipe_options:
        if option not in RETIRED_OPTIONS:
            raise NotRepresentable(f"train.{option}: not an option of the current recipe")
        del values[option]
    missing = recipe_options - set(values)
    if missing:
        raise NotRepresentable(f"train: no recorded value for {sorted(missing)}")
    not_identity = dict.fromkeys(Recipe.NOT_IDENTITY, 1)  # any value: they are not in the identity
    try:  # through the current code: its validation, its rule for the loss terms of weight 0
        recipe = Recipe(**{**values, **not_identity, "betas": tuple(values["betas"])})
    except (TypeError, ValueError) as err:
        raise NotRepresentable(f"train: {err}") from None
    return {**old, "version": runs.IDENTITY_VERSION, "train": recipe.identity()}


def eval_identity(old: dict, train_hashes: dict[str, str]) -> dict:
    """The current identity of a recorded evaluation identity, its trainings' hashes mapped by
    `train_hashes` (old -> new, and new -> new); KeyError for a training in no store."""
    trained = old["trained"]
    if isinstance(trained, str):
        trained = runs.join_trainings([train_hashes[h] for h in runs.split_trainings(trained)])
    if old.get("version") == runs.IDENTITY_VERSION:
        return {**old, "trained": trained}
    new = {k: v for k, v in old.items() if k not in ("path", "tile")}
    return {**new, "version": runs.IDENTITY_VERSION, "trained": trained,
            "fast_path": old.get("path", REFERENCE), "tile": old.get("tile")}


def _records(store: Path, kind: str) -> list[tuple[Path, dict]]:
    out = []
    for path in sorted((Path(store) / kind).glob(f"*/{runs.RECORD}")):
        if not path.parts[-2].startswith("."):
            record = runs.read_json_or_none(path)  # raw: non-finite metrics stay as written
            if record is not None and "identity" in record:
                out.append((path.parent, record))
    return out


def _move(run_dir: Path, record: dict, identity: dict, new_hash: str) -> Path:
    """Rewrite `record` for its new identity and move its directory to `new_hash` (a crash between the
    two leaves a record whose hash is not its directory's: the next call finishes the move)."""
    old_hash = run_dir.name
    if record.get("config") == record["identity"]:
        record["config"] = identity
    if record["hash"] != new_hash:
        record["migrated_from"] = record["hash"]
    record.update(identity=identity, hash=new_hash)
    text = json.dumps(record, indent=2, sort_keys=True, allow_nan=False)
    write_atomic(run_dir / runs.RECORD, lambda tmp: tmp.write_text(text))
    if old_hash == new_hash:
        return run_dir
    target = run_dir.parent / new_hash
    if target.exists():
        raise FileExistsError(f"{run_dir} re-keys to {target}, which holds another run")
    run_dir.rename(target)
    (run_dir.parent / f".{old_hash}.lock").unlink(missing_ok=True)
    return target


def rekey(stores: list[Path], results_dir: Path | None = None, delete_dropped: bool = False,
          skip_results: tuple = ()) -> pd.DataFrame:
    """Re-key every training and evaluation of `stores` (run stores and archives) to its current
    identity, and the run hashes quoted by the result files under `results_dir` (but `skip_results`
    folders and the stores themselves). Returns one row per run: store, kind, hash (now), old hash,
    outcome, reason."""
    rows, train_hashes, train_identities, dropped = [], {}, {}, set()
    for kind in ("train", "eval"):
        for store in stores:
            for run_dir, record in _records(store, kind):
                old_hash = record.get("migrated_from", run_dir.name)
                row = {"store": str(store), "kind": kind, "hash": run_dir.name, "old hash": old_hash,
                       "label": record.get("label"), "outcome": CURRENT, "reason": ""}
                try:
                    if kind == "train":
                        identity = train_identity(record["identity"])
                    else:
                        identity = eval_identity(record["identity"], train_hashes)
                        trained = identity["trained"]
                        if isinstance(trained, str):
                            record.setdefault("metrics", {})["train_run"] = trained
                except NotRepresentable as err:
                    row.update(outcome=DROPPED, reason=str(err))
                except KeyError as err:
                    dropped_training = err.args[0] in dropped
                    row.update(outcome=DROPPED if dropped_training else UNLINKED,
                               reason=f"training {err.args[0]} " + ("was dropped" if dropped_training else
                                                                     "is in no store"))
                else:
                    new_hash = runs.config_hash(identity)
                    if identity != record["identity"] or new_hash != run_dir.name:
                        run_dir = _move(run_dir, record, identity, new_hash)
                    if "migrated_from" in record:
                        row["outcome"] = REKEYED
                    row["hash"] = new_hash
                    if kind == "train":
                        train_hashes.update({old_hash: new_hash, new_hash: new_hash})
                        train_identities[new_hash] = identity
                if row["outcome"] == DROPPED:
                    dropped.add(old_hash)
                    if delete_dropped:
                        shutil.rmtree(run_dir)
                        row["reason"] += " (deleted)"
                rows.append(row)
    table = pd.DataFrame(rows, columns=["store", "kind", "hash", "old hash", "label", "outcome", "reason"])
    table = table.sort_values(["kind", "store", "old hash"], ascending=[False, True, True], ignore_index=True)
    if results_dir is not None:
        renamed = {r["old hash"]: r["hash"] for r in rows if r["outcome"] == REKEYED}
        skipped = [Path(p).resolve() for p in (*stores, *skip_results)]
        rewrite_results(Path(results_dir), renamed, train_identities, skipped)
    return table


def rewrite_results(results_dir: Path, renamed: dict[str, str], train_identities: dict[str, dict],
                    skipped: list[Path]) -> list[Path]:
    """Replace every re-keyed run hash that a result file quotes by its new one; an exported weights
    sidecar (a JSON object naming its `run` and `identity`) gets the run's new identity and keeps the old
    hash as `migrated_from` (the weights file itself, binary, keeps its metadata as exported)."""
    changed, old_of = [], {now: old for old, now in renamed.items()}
    for path in sorted(results_dir.rglob("*")):
        if path.suffix not in RESULT_SUFFIXES or not path.is_file() \
                or any(path.resolve().is_relative_to(s) for s in skipped):
            continue
        text = path.read_text()
        new = HASH.sub(lambda m: renamed.get(m.group(0), m.group(0)), text)
        value = _json_object(new) if path.suffix == ".json" else None
        if value is not None and value.get("run") in train_identities and "identity" in value \
                and value["identity"] != train_identities[value["run"]]:  # an exported weights file's sidecar
            value.update(identity=train_identities[value["run"]], migrated_from=old_of.get(value["run"]))
            new = json.dumps(value, indent=2, sort_keys=True, default=str)
        if new != text:
            write_atomic(path, lambda tmp, new=new: tmp.write_text(new))
            changed.append(path)
    return changed


def _json_object(text: str) -> dict | None:
    try:
        value = json.loads(text)
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


OUTCOMES = (REKEYED, CURRENT, UNLINKED, DROPPED)


def summary(table: pd.DataFrame, names: dict[str, str]) -> pd.DataFrame:
    """Counts per store (named by `names`) and kind of each outcome."""
    rows = []
    for (store, kind), group in table.groupby(["store", "kind"], sort=False):
        counts = group["outcome"].value_counts()
        rows.append({"store": names.get(store, store), "kind": "trainings" if kind == "train" else "evaluations",
                     **{outcome: int(counts.get(outcome, 0)) for outcome in OUTCOMES}})
    return pd.DataFrame(rows)


def run(ctx: Context, name: str, delete_dropped: bool) -> pd.DataFrame:
    """conf/experiment/migrate.yaml says what each argument is."""
    stores = [ctx.runs_dir, *ctx.archives]
    names = {str(ctx.runs_dir): f"run store ({ctx.runs_dir})"}
    if ctx.runs_archive is not None:
        names[str(ctx.runs_archive)] = f"archive ({ctx.runs_archive})"
    out_dir = ctx.results_dir / name
    table = rekey(stores, ctx.results_dir, delete_dropped, skip_results=(out_dir,))
    counts = summary(table, names)
    dropped = table[table["outcome"] == DROPPED]
    write_table(counts, out_dir, caption=(
        f"Recorded runs re-keyed to identity version {runs.IDENTITY_VERSION} (bench/experiments/migrate.py): "
        f"per store and kind, the runs moved to their new hash (now or by an earlier call), left as recorded, "
        f"and dropped (an option that no longer exists; {'deleted' if delete_dropped else 'kept on disk'}). "
        f"Every run, its old and new hash: runs.csv."))
    listed = table.assign(store=table["store"].map(lambda s: names.get(s, s)))
    write_atomic(out_dir / "runs.csv", lambda tmp: listed.to_csv(tmp, index=False))
    for _, row in dropped.iterrows():
        log.warning("migrate: dropped %s/%s (%s): %s", row["kind"], row["hash"], row["label"], row["reason"])
    log.info("migrate: %s", "; ".join(f"{r['store']} {r['kind']}: " + ", ".join(f"{r[o]} {o}" for o in OUTCOMES)
                                      for _, r in counts.iterrows()))
    return counts

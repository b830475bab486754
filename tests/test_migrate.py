"""+experiment=migrate (bench/experiments/migrate.py): recorded runs re-keyed to the current identity version,
their links and the hashes result files quote rewritten, idempotent, unrepresentable runs listed as dropped.

tests/data/runs_v1 holds records copied as they were recorded (identity version 1) from the cpu archive:
the sota table's Ours row (seed 0) and its training, a Cascade's evaluation and its two stage trainings,
the Input bilinear row (a model that trains nothing), and a training with an `ssim_linear` term, a loss term
that no longer exists, with its evaluation. The committed archive is only read."""
import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from bench import runs
from bench.cli import CONF_DIR, make_context
from bench.experiments import migrate, training
from bench.experiments.context import model_config, with_training
from bench.experiments.evaluation import evaluation_identity
from bench.tasks import get_task

ROOT = Path(__file__).resolve().parent.parent
V1 = ROOT / "tests/data/runs_v1"
ARCHIVE = ROOT / "results/cpu/runs"
OURS_EVAL, OURS_TRAIN = "870fc8db22469f8d", "df766c8e9b043e4d"
CASCADE_EVAL, CASCADE_STAGES = "9d9a215cd427405b", ("d1526e9a3c2fb548", "d49acac8b3295a4d")
BILINEAR_EVAL = "814dc7561fff30eb"
SSIM_LINEAR_TRAIN, SSIM_LINEAR_EVAL = "3f3a377b46920f5b", "48ed7ee137c118ad"


def _tree(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def stores(tmp_path):
    """The v1 records split over a run store (the evaluations) and an archive (the trainings, and the
    Ours row's evaluation too), beside a results folder whose table and weights sidecar quote them."""
    store, archive, results = tmp_path / "runs", tmp_path / "results/cpu/runs", tmp_path / "results/cpu"
    shutil.copytree(V1 / "train", archive / "train")
    shutil.copytree(V1 / "eval", store / "eval")
    shutil.copytree(V1 / "eval" / OURS_EVAL, archive / "eval" / OURS_EVAL)
    (results / "sota").mkdir(parents=True)
    (results / "sota" / "table.csv").write_text(
        f"method,PSNR,runs\nOurs,33.1,{OURS_EVAL}\nCascade,32.0,{CASCADE_EVAL}\nlinear SSIM,32.5,{SSIM_LINEAR_EVAL}\n")
    (results / "weights").mkdir()
    shutil.copy(V1 / "ours.pt.json", results / "weights" / "ours.pt.json")  # the sidecar results/cpu/weights had then
    return store, archive, results


def _record(store: Path, kind: str, run_hash: str) -> dict:
    return json.loads((store / kind / run_hash / runs.RECORD).read_text())


def _new_hash(table: pd.DataFrame, kind: str, old: str) -> str:
    (new,) = set(table[(table["kind"] == kind) & (table["old hash"] == old)]["hash"])
    return new


def test_rekey_moves_every_run_to_its_new_hash_and_rewrites_every_link(stores):
    store, archive, results = stores
    table = migrate.rekey([store, archive], results)
    rekeyed = table[table["outcome"] == migrate.REKEYED]
    assert len(rekeyed) == 3 + 4  # trainings in the archive; evaluations: 3 in the store, Ours also archived
    for _, row in rekeyed.iterrows():
        record = _record(Path(row["store"]), row["kind"], row["hash"])
        assert record["hash"] == row["hash"] == runs.config_hash(record["identity"]) != row["old hash"]
        assert record["migrated_from"] == row["old hash"] and record["identity"]["version"] == runs.IDENTITY_VERSION
        assert not (Path(row["store"]) / row["kind"] / row["old hash"]).exists()
    ours_train = _new_hash(table, "train", OURS_TRAIN)
    train = _record(archive, "train", ours_train)["identity"]["train"]
    assert (train["colour_permute"], train["precision"], train["channels_last"]) == (False, "fp32", False)
    assert "perceptual" not in train["loss"]["final"]  # weight 0: out of the identity
    for where in (store, archive):  # the Ours evaluation, in both stores, links the new training
        ours = _record(where, "eval", _new_hash(table, "eval", OURS_EVAL))
        assert ours["identity"]["trained"] == ours["metrics"]["train_run"] == ours_train
        assert (ours["identity"]["fast_path"], ours["identity"]["tile"]) == ("fp32", None)
    cascade = _record(store, "eval", _new_hash(table, "eval", CASCADE_EVAL))
    assert cascade["identity"]["trained"] == runs.join_trainings([_new_hash(table, "train", h) for h in CASCADE_STAGES])
    assert all((archive / "train" / h).is_dir() for h in runs.split_trainings(cascade["identity"]["trained"]))
    bilinear = _record(store, "eval", _new_hash(table, "eval", BILINEAR_EVAL))
    assert bilinear["identity"]["trained"] == {"model": {"_target_": "baselines.classical.Bilinear"}, "task": "srd"}
    quoted = (results / "sota" / "table.csv").read_text()
    assert _new_hash(table, "eval", OURS_EVAL) in quoted and _new_hash(table, "eval", CASCADE_EVAL) in quoted
    assert OURS_EVAL not in quoted and SSIM_LINEAR_EVAL in quoted  # a dropped run keeps its hash
    sidecar = json.loads((results / "weights" / "ours.pt.json").read_text())
    assert (sidecar["run"], sidecar["migrated_from"]) == (ours_train, OURS_TRAIN)
    assert runs.config_hash(sidecar["identity"]) == ours_train


def test_runs_with_an_option_that_no_longer_exists_are_listed_as_dropped_and_deleted_on_request(stores):
    store, archive, results = stores
    table = migrate.rekey([store, archive], results)
    dropped = table[table["outcome"] == migrate.DROPPED].set_index("old hash")
    assert set(dropped.index) == {SSIM_LINEAR_TRAIN, SSIM_LINEAR_EVAL}
    assert "ssim_linear" in dropped.loc[SSIM_LINEAR_TRAIN, "reason"]
    assert SSIM_LINEAR_TRAIN in dropped.loc[SSIM_LINEAR_EVAL, "reason"]  # its training was dropped
    assert (archive / "train" / SSIM_LINEAR_TRAIN).is_dir()  # kept unless asked
    migrate.rekey([store, archive], results, delete_dropped=True)
    assert not (archive / "train" / SSIM_LINEAR_TRAIN).exists() and not (store / "eval" / SSIM_LINEAR_EVAL).exists()


def test_a_training_with_train_sequences_set_is_not_representable():
    identity = json.loads((V1 / "train" / OURS_TRAIN / runs.RECORD).read_text())["identity"]
    with pytest.raises(migrate.NotRepresentable, match="train_sequences"):
        migrate.train_identity({**identity, "train": {**identity["train"], "train_sequences": 8}})


def test_an_evaluation_run_another_way_keeps_its_way_under_the_new_name():
    identity = json.loads((V1 / "eval" / OURS_EVAL / runs.RECORD).read_text())["identity"]
    new = migrate.eval_identity({**identity, "path": "bf16", "tile": 64}, {OURS_TRAIN: "0" * 16})
    assert (new["fast_path"], new["tile"], new["trained"]) == ("bf16", 64, "0" * 16) and "path" not in new


def test_rekey_twice_changes_nothing(stores, tmp_path):
    store, archive, results = stores
    first = migrate.rekey([store, archive], results)
    after_first = _tree(tmp_path)
    second = migrate.rekey([store, archive], results)
    assert _tree(tmp_path) == after_first
    assert second.sort_values(["kind", "old hash", "store"]).reset_index(drop=True).equals(
        first.sort_values(["kind", "old hash", "store"]).reset_index(drop=True))


def test_the_experiment_writes_its_table_and_leaves_other_kinds_alone(stores, tmp_path):
    store, archive, results = stores
    (store / "data" / "abc").mkdir(parents=True)
    (store / "data" / "abc" / runs.RECORD).write_text(json.dumps({"identity": {"spec": {}}, "hash": "abc"}))
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        ctx = make_context(compose("config", overrides=["+experiment=migrate", f"runs_dir={store}",
                                                        f"results_dir={results}"]))
    counts = migrate.run(ctx, "migrate", delete_dropped=False).set_index(["store", "kind"])
    assert counts.loc[(f"archive ({archive})", "trainings"), [migrate.REKEYED, migrate.DROPPED]].tolist() == [3, 1]
    assert counts.loc[(f"run store ({store})", "evaluations"), [migrate.REKEYED, migrate.DROPPED]].tolist() == [3, 1]
    assert (results / "migrate" / "table.md").exists() and len(pd.read_csv(results / "migrate" / "runs.csv")) == 9
    assert (store / "data" / "abc" / runs.RECORD).exists()


def _sota_ours_identities(ctx, recorded_train: dict, recorded_eval: dict) -> tuple[dict, dict]:
    """The training and evaluation identities the current code computes for the sota table's Ours row
    (seed 0) from the current config, with the data fingerprints as recorded (the frames are not here)."""
    task = get_task("srd")
    cfg = model_config(ctx, "srd")
    row_ctx = with_training(ctx, None, "srd")
    fingerprint = training.split_fingerprint
    training.split_fingerprint = lambda *_: recorded_train["identity"]["data"]
    try:
        train = training._train_identity(row_ctx, cfg, task, 0, None)
    finally:
        training.split_fingerprint = fingerprint
    evaluation = evaluation_identity(runs.config_hash(train), ctx.eval.split, recorded_eval["identity"]["data"],
                                     row_ctx.train.hdr, ctx.eval.fast_path, ctx.eval.tile, ctx.eval.save_exr)
    return train, evaluation


def test_the_sota_ours_row_migrated_is_what_the_current_config_computes(tmp_path):
    """The committed table's Ours row (seed 0), read from the committed archive (a copy of its records is
    migrated when the archive is still at an older identity version): the current config (sota trains in
    exposure_pass, as the table was), through the code that keys trainings and evaluations, gives its recorded
    identities, so nothing retrains."""
    sota = pd.read_csv(ROOT / "results/cpu/val/sota/table.csv").set_index("method")
    eval_hash = sota.loc["Ours", "runs"].split()[0]
    recorded_eval = _record(ARCHIVE, "eval", eval_hash)
    recorded_train = _record(ARCHIVE, "train", recorded_eval["identity"]["trained"])
    if recorded_eval["identity"].get("version") != runs.IDENTITY_VERSION:
        store = tmp_path / "runs"
        for kind, record in (("train", recorded_train), ("eval", recorded_eval)):
            (store / kind / record["hash"]).mkdir(parents=True)
            shutil.copy(ARCHIVE / kind / record["hash"] / runs.RECORD, store / kind / record["hash"])
        table = migrate.rekey([store])
        recorded_train = _record(store, "train", _new_hash(table, "train", recorded_train["hash"]))
        recorded_eval = _record(store, "eval", _new_hash(table, "eval", eval_hash))
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        ctx = make_context(compose("config", overrides=["preset=cpu", "+experiment=sota", "eval.split=val"]))
    assert recorded_train["identity"]["train"]["hdr"] == ctx.train.hdr == "exposure_pass"
    train, evaluation = _sota_ours_identities(ctx, recorded_train, recorded_eval)
    assert json.loads(json.dumps(train)) == recorded_train["identity"]
    assert runs.config_hash(train) == recorded_train["hash"]
    assert evaluation == recorded_eval["identity"] and runs.config_hash(evaluation) == recorded_eval["hash"]


def test_every_option_the_identity_leaves_out_is_implied_at_that_value():
    """migrate.IMPLIED restates Recipe.OMITTED_AT (a replay of recorded code has that code's Recipe, so it
    cannot read today's): an option added to the one and not the other would leave adopt's replays of
    older code unchecked ("the code replayed has no such option")."""
    from bench.experiments.migrate import IMPLIED
    from bench.train import Recipe
    assert {k: IMPLIED.get(k, "missing") for k in Recipe.OMITTED_AT} == Recipe.OMITTED_AT

"""Every paper table at `smoke` scale with a few training steps: rows, formats, paper values, figures,
run reuse within and across tables, seeds as mean +- std, and `all`."""
import re
import shutil
import time

import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from bench import archived, runs
from bench.cli import CONF_DIR, run_experiment
from bench.errors import UserError
from bench.experiments import evaluation
from bench.experiments.table import (compute_shard, domain_note, expand_rows, paper_agreement, reference_check,
                                    shard_units, unit_lock)
from bench.models.srd import SRDNet, SRDStage, load_stage
from bench.paper import paper_values
from conftest import bench_here, smoke_context, smoke_overrides

# a table's folder under results_dir; studies/NAME is `+study=NAME`
TABLES = ["sr_denoise", "dilation", "dilation_crop", "stage_order", "deform", "sota", "ipt", "deform_num",
          "perceptual", "generalization", "studies/dark_bias"]
PAPER_TABLES = {"sr_denoise", "dilation", "stage_order", "deform", "sota", "ipt", "deform_num"}


@pytest.fixture(scope="module")
def dirs(tmp_path_factory, smoke_data):
    root = tmp_path_factory.mktemp("tables")
    smoke_data(root / "data")
    overrides = smoke_overrides(root) + ["vgg.weights=null", "vgg.allow_random=true"]
    return overrides, root


@pytest.fixture(scope="module")
def tables(dirs):
    """Every table at the smoke preset, run once for the module, so that the tests reading them pass in any order."""
    overrides, root = dirs
    for name in TABLES:  # one seed: a study may ask for more (test_seeds_give_mean_and_std checks seeds)
        run_experiment(compose_experiment(name, overrides + ["seeds=[0]"]))
    return overrides, root


def compose_experiment(name, overrides):
    """`name`'s config: an experiment, or `studies/NAME` for a study."""
    choice = f"+study={name.removeprefix('studies/')}" if name.startswith("studies/") else f"+experiment={name}"
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        return compose("config", overrides=[choice, *overrides])


def expected_labels(name, overrides):
    exp = OmegaConf.to_container(compose_experiment(name, overrides).experiment, resolve=True)
    return [r["label"] for r in expand_rows(exp["rows"])], exp


@pytest.mark.parametrize("name", TABLES)
def test_table_runs_at_smoke_and_writes_every_format(tables, name):
    overrides, root = tables
    labels, exp = expected_labels(name, overrides)
    out = root / "results" / name
    for ext in ("csv", "md", "tex"):
        assert (out / f"table.{ext}").stat().st_size > 0
    assert (out / "crops.png").stat().st_size > 0
    assert (out / "curves.png").stat().st_size > 0    # every table has a learned row with a curve
    table = pd.read_csv(out / "table.csv")
    assert list(table["method"]) == labels
    assert table[["relMSE", "PSNR", "SSIM"]].notna().all().all()
    if name in PAPER_TABLES:  # every row that names a paper row shows the published numbers
        named = [r.get("paper") is not None for r in expand_rows(exp["rows"])]
        assert table.loc[named, "paper relMSE"].notna().all()
        assert len(paper_values(name)) >= sum(named) / (2 if name in ("sr_denoise", "dilation") else 1) - 1e-9
    if name == "sota":
        learned = table[table["params"] > 0]
        assert learned["GMac"].between(0.95 * 72, 1.05 * 72).all()  # smoke budget, +-5%
    if name == "perceptual":
        assert "random(seed=0)" in (out / "table.md").read_text()  # says which VGG it used


def test_identical_rows_are_trained_once_across_tables(tables):
    """The paper's own reuse: "ours" is Table 4's one-stage row, Table 5's Ours and Table 7's u1+u2+u3;
    Table 6's last row is Table 7's 0 and Table 3's +IPT."""
    _, root = tables
    runs = lambda name: pd.read_csv(root / "results" / name / "table.csv").set_index("method")["runs"]
    assert runs("sota")["Ours"] == runs("deform_num")["u1+u2+u3"] == runs("deform")["End2End + one-stage deform (ours)"]
    assert runs("ipt")["+ channel aug + skip + CFM"] == runs("deform_num")["0"] \
        == runs("stage_order")["Simple End2End (SR->dn) + IPT"]
    assert runs("ipt")["Simple End2End (SR->dn)"] == runs("stage_order")["Simple End2End (SR->dn)"]


def test_rerun_trains_nothing(tables, caplog):
    overrides, _ = tables
    with caplog.at_level("INFO", logger="bench"):
        run_experiment(compose_experiment("stage_order", overrides))
    assert "5 of 5 rows reused" in caplog.text
    assert "train Cascade (dn->SR) [dn stage]: reusing" in caplog.text


def test_a_lost_run_store_is_rebuilt_from_the_archive_without_training(dirs, tmp_path, caplog):
    """The run store may not survive (a fresh clone, a new machine): finished runs archived beside the
    tables bring the table back, weights included (crops.png runs them), with nothing trained again."""
    overrides, _ = dirs
    mine = [o for o in overrides if not o.startswith(("runs_dir=", "results_dir="))]
    mine += [f"results_dir={tmp_path / 'results'}", f"runs_archive={tmp_path / 'archive'}"]
    run_experiment(compose_experiment("ipt", mine + [f"runs_dir={tmp_path / 'lost'}"]))
    first = pd.read_csv(tmp_path / "results" / "ipt" / "table.csv")
    n = len(first)  # every row learned
    weights = sorted((tmp_path / "archive" / "train").glob(f"*/{archived.WEIGHTS}"))
    evaluations = sorted((tmp_path / "archive" / "eval").glob(f"*/{archived.COMPACT_PER_IMAGE}"))
    assert len(weights) == n and len(evaluations) == n
    assert {p.name for p in weights[0].parent.iterdir()} == set(archived.FILES)  # compact: float16 EMA, thinned curve
    assert {p.name for p in evaluations[0].parent.iterdir()} == set(archived.EVALUATION_FILES)  # scores gzipped
    (tmp_path / "results" / "ipt" / "crops.png").unlink()
    caplog.clear()  # the first command's lines are captured too where an earlier test left the logger at INFO
    with caplog.at_level("INFO", logger="bench"):
        run_experiment(compose_experiment("ipt", mine + [f"runs_dir={tmp_path / 'fresh'}"]))
    assert f"{n} of {n} rows reused" in caplog.text and "trained in" not in caplog.text
    again = pd.read_csv(tmp_path / "results" / "ipt" / "table.csv")
    pd.testing.assert_frame_equal(first[["method", "runs", "PSNR", "SSIM"]], again[["method", "runs", "PSNR", "SSIM"]])
    assert (tmp_path / "results" / "ipt" / "crops.png").stat().st_size > 0
    run_experiment(compose_experiment("claims", mine + [f"runs_dir={tmp_path / 'third'}"]))  # pairs per_image.csv
    claims = pd.read_csv(tmp_path / "results" / "claims" / "table.csv")
    assert claims.loc[claims["claim"].str.startswith("IPT"), "PSNR 2SE"].notna().all()


def test_weights_the_archive_left_out_are_trained_again_only_where_they_are_run(dirs, tmp_path, caplog,
                                                                                monkeypatch):
    """Weights over the archive's file limit stay out of git (a big model's). A fresh store restores the
    table from the archived evaluations; crops.png trains again the first seed's runs only, an evaluation
    the archive lacks its run's, and the archive keeps the records its evaluations scored."""
    overrides, _ = dirs
    mine = [o for o in overrides if not o.startswith(("runs_dir=", "results_dir="))]
    mine += [f"results_dir={tmp_path / 'results'}", f"runs_archive={tmp_path / 'archive'}", "seeds=[0,1]",
             "experiment.rows.0.sweep.dilation=[1]"]                          # one row, two seeds
    name, archive = "dilation_crop", tmp_path / "archive"
    monkeypatch.setattr(runs, "ARCHIVED_FILE_MAX_BYTES", 20_000)  # smoke weights in float16: about 0.08 MB and more
    run_experiment(compose_experiment(name, mine + [f"runs_dir={tmp_path / 'lost'}"]))
    first = pd.read_csv(tmp_path / "results" / name / "table.csv")
    n = len(first)  # every row learned
    assert not [p for p in archive.glob("train/*/*.pt")]                     # left out: over the limit
    assert len(list(archive.glob("train/*/val_curve.csv"))) == 2 * n          # the small files are kept
    records = {p: p.read_bytes() for p in archive.glob("train/*/run.json")}

    def rerun(*more):
        caplog.clear()
        with caplog.at_level("INFO", logger="bench"):
            run_experiment(compose_experiment(name, mine + [f"runs_dir={tmp_path / 'fresh'}", *more]))
        return caplog.text

    log = rerun("++experiment.figure=false")
    assert f"{n} of {n} rows reused" in log and "trained in" not in log      # scores only: nothing to train
    log = rerun()                                                              # crops.png runs seed 0
    assert log.count(f"has no checkpoint.pt or {archived.WEIGHTS}") == n and log.count("trained in") == n
    # each says which render of val its archived curve and its own scored: here the same
    assert len(re.findall(r"archived final val PSNR [\d.]+ dB on val render (\w+), now [\d.]+ dB on val "
                          r"render \1\)", log)) == n, log
    fresh = {runs.read_record(p)["seed"]: p.parent for p in (tmp_path / "fresh" / "train").glob("*/run.json")}
    assert (fresh[0] / "checkpoint.pt").exists() and not (fresh[1] / "checkpoint.pt").exists()
    assert {p: p.read_bytes() for p in archive.glob("train/*/run.json")} == records  # what was scored
    again = pd.read_csv(tmp_path / "results" / name / "table.csv")
    pd.testing.assert_frame_equal(first[["method", "runs", "PSNR", "SSIM"]], again[["method", "runs", "PSNR", "SSIM"]])
    seed1 = next(p.parent for p in (tmp_path / "fresh" / "eval").glob("*/run.json") if runs.read_record(p)["seed"] == 1)
    shutil.rmtree(seed1), shutil.rmtree(archive / "eval" / seed1.name)        # an evaluation neither has
    trained_until = []

    def slow_training(*args, **kwargs):  # a training long enough to show in the evaluation's time if counted
        out = real_trained_model(*args, **kwargs)
        if kwargs.get("load", True):          # the call that trains for the weights (not the lookup before)
            time.sleep(2.0)
            trained_until.append(time.perf_counter())
        return out

    real_trained_model = evaluation.trained_model
    monkeypatch.setattr(evaluation, "trained_model", slow_training)
    log = rerun("++experiment.figure=false")
    (trained,) = trained_until                                                 # seed 1's, the one retrained
    since_training = time.perf_counter() - trained
    assert log.count(f"has no checkpoint.pt or {archived.WEIGHTS}") == 1 and log.count("trained in") == 1
    assert (tmp_path / "fresh" / "eval" / seed1.name / "per_image.csv").exists()
    # the evaluation's wall time is its own, not the training's it waited for
    assert runs.read_record(tmp_path / "fresh" / "eval" / seed1.name / runs.RECORD)["wall_time_s"] < since_training
    # the archive keeps the records its other evaluations scored, also of the training retrained here
    assert {p: p.read_bytes() for p in archive.glob("train/*/run.json")} == records


def test_a_cascade_evaluation_is_reused_from_its_stages_records_without_their_weights(dirs, tmp_path, caplog,
                                                                                     monkeypatch):
    """The archive keeps the weights of each row's first seed only (docs/runs.md): a Cascade row's recorded
    evaluation is reused from its stages' records, as any row's is, not trained again for weights it does
    not load (the committed stage_order table's seeds 1 and 2 were: 8 trainings and a render). A store's
    reused stage trainings go to the archive with their evaluation, as a single training does."""
    overrides, _ = dirs
    mine = [o for o in overrides if not o.startswith(("runs_dir=", "results_dir="))]
    mine += [f"results_dir={tmp_path / 'results'}", "seeds=[0]",
             "experiment.rows=[{label:c,model:srd,cascade:true,overrides:{channel_aug:false,skip:false}}]",
             "++experiment.figure=false"]
    archive = [f"runs_archive={tmp_path / 'archive'}"]
    monkeypatch.setattr(runs, "ARCHIVED_FILE_MAX_BYTES", 20_000)  # smoke weights in float16: left out
    run_experiment(compose_experiment("stage_order", mine + [f"runs_dir={tmp_path / 'lost'}", "runs_archive=null"]))
    run_experiment(compose_experiment("stage_order", mine + archive + [f"runs_dir={tmp_path / 'lost'}"]))  # reuses
    assert len(list((tmp_path / "archive" / "train").glob("*/run.json"))) == 2      # the two stages
    assert len(list((tmp_path / "archive" / "eval").glob("*/run.json"))) == 1
    assert not list((tmp_path / "archive").glob("train/*/*.pt"))
    mine += archive
    with caplog.at_level("INFO", logger="bench"):
        run_experiment(compose_experiment("stage_order", mine + [f"runs_dir={tmp_path / 'fresh'}"]))
    assert "1 of 1 rows reused" in caplog.text and "trained in" not in caplog.text, caplog.text[-3000:]


def test_seeds_give_mean_and_std(dirs):
    overrides, root = dirs
    run_experiment(compose_experiment("perceptual", overrides + ["seeds=[0,1]", "++experiment.figure=false"]))
    table = pd.read_csv(root / "results" / "perceptual" / "table.csv")
    assert table.loc[1:, "relMSE std"].notna().all() and (table.loc[1:, "relMSE std"] > 0).all()
    assert " \u00b1 " in (root / "results" / "perceptual" / "table.md").read_text()
    assert r"$\pm$" in (root / "results" / "perceptual" / "table.tex").read_text()


def test_the_one_model_command_is_the_sota_tables_ours_row():
    """`+experiment=train experiment.model=srd` hands the table the row sota's Ours is (at the cpu preset
    too): the same model, overrides, task, training overrides and cascade, so the same runs."""
    from bench.experiments.one_model import one_row
    keys = ("model", "overrides", "task", "train", "cascade")
    for preset in ("smoke", "cpu"):
        sota = expand_rows(OmegaConf.to_container(compose_experiment("sota", [f"preset={preset}"]).experiment,
                                                  resolve=True)["rows"])
        ours = next(r for r in sota if r["label"] == "Ours")
        exp = OmegaConf.to_container(compose_experiment("train", [f"preset={preset}", "experiment.model=srd"])
                                     .experiment, resolve=True)
        mine = expand_rows([one_row(**{k: exp[k] for k in keys})])[0]
        assert {k: mine[k] or None for k in keys} == {k: ours.get(k) or None for k in keys}


def test_the_one_model_command_and_a_table_reuse_each_others_runs(dirs, caplog):
    """A table trains, then the one-model command reuses its runs and says so; the one-model command
    trains, then the table reuses its runs. Seeds no other test trains, so the first of each pair computes."""
    overrides, root = dirs
    one_model = lambda seed: compose_experiment("train", overrides + ["experiment.model=srd", f"seeds=[{seed}]",
                                                                      "++experiment.figure=false"])
    table = lambda seed: compose_experiment("smoke", overrides + [f"seeds=[{seed}]", "++experiment.figure=false"])
    ours = lambda name: pd.read_csv(root / "results" / name / "table.csv").set_index("method")["runs"]
    run_experiment(table(7))
    caplog.clear()
    with caplog.at_level("INFO", logger="bench"):
        run_experiment(one_model(7))
    assert ours("train/srd")["srd"] == ours("smoke")["Ours"]
    said = next(line for line in caplog.text.splitlines() if "srd seed 7:" in line)
    assert "reused training run" in said and "recorded by the row 'Ours'" in said and "computed" not in said

    run_experiment(one_model(8))
    caplog.clear()
    with caplog.at_level("INFO", logger="bench"):
        run_experiment(table(8))
    assert ours("smoke")["Ours"] == ours("train/srd")["srd"]
    assert "train Ours: reusing run" in caplog.text and "smoke: 2 of 2 rows reused" in caplog.text


def test_all_runs_the_listed_tables_and_reuses_them(tables):
    overrides, root = tables  # every run of both tables is recorded
    out = bench_here("+experiment=all", "experiment.tables=[ipt,deform_num]", *overrides)
    assert out.returncode == 0, out.stderr[-3000:]
    log = out.stdout + out.stderr
    rows = {name: len(expected_labels(name, overrides)[0]) for name in ("ipt", "deform_num")}
    assert all(f"{name}: {n} of {n} rows reused" in log for name, n in rows.items())
    summary = pd.read_csv(root / "results" / "all" / "table.csv")
    assert list(summary["experiment"]) == ["ipt", "deform_num", "all (each run once)"]
    assert (summary["compute (min)"] > 0).all()  # recorded when the runs were computed, not this reuse
    tables, total = summary.iloc[:2], summary.iloc[2]
    # the tables share runs (ipt's full row is deform_num's default count): counted once in the last row
    assert tables["compute (min)"].max() < total["compute (min)"] < tables["compute (min)"].sum()
    assert total["trainings"] < tables["trainings"].sum()
    assert tables["relMSE order as paper"].str.fullmatch(r"\d+/\d+").all()
    ipt = pd.read_csv(root / "results" / "ipt" / "table.csv")
    assert (ipt["train (min)"] > 0).all() and (ipt["eval (min)"] > 0).all()


def test_sweep_expands_in_order():
    rows = expand_rows([{"label": "rate {dilation} ({task})", "model": "edsr", "paper": "{dilation}",
                         "overrides": {"blocks": 4}, "sweep": {"task": ["sr", "denoise"], "dilation": [1, 5]}}])
    assert [r["label"] for r in rows] == ["rate 1 (sr)", "rate 5 (sr)", "rate 1 (denoise)", "rate 5 (denoise)"]
    assert rows[3]["overrides"] == {"blocks": 4, "dilation": 5} and rows[3]["paper"] == "5"
    with pytest.raises(ValueError, match="unknown keys"):
        expand_rows([{"label": "x", "model": "edsr", "overide": {}}])


@pytest.mark.parametrize("count", [1, 2, 3, 5])
def test_shards_cover_every_row_and_seed_once_and_stay_balanced(count):
    rows = [{"label": "a"}, {"label": "b"}, {"label": "c"}]
    shards = [[(r["label"], s) for r, s in shard_units(rows, [0, 1, 2], i, count)] for i in range(count)]
    every = [pair for shard in shards for pair in shard]
    assert sorted(every) == sorted((r["label"], s) for r in rows for s in (0, 1, 2))
    assert max(map(len, shards)) - min(map(len, shards)) <= 1


def test_a_shard_that_runs_out_of_units_takes_those_no_other_process_holds(tmp_path):
    """While shard 1 is busy on its first unit, shard 0 does its own units, then shard 1's that have
    not started; the unit shard 1 holds it leaves alone. Shard 1 then finds the rest free (in a real
    table its row() reuses them)."""
    rows = [{"label": "cheap"}, {"label": "dear"}]
    calls, inner = [], []

    def shard(index):
        return [(r["label"], seed) for r, seed in
                compute_shard(rows, [0, 1, 2], index, 2, tmp_path, "t", lambda r, seed: compute(index, r, seed))]

    def compute(index, r, seed):
        calls.append((index, r["label"], seed))
        if (index, r["label"], seed) == (1, "cheap", 1):  # shard 1's first unit: shard 0 runs meanwhile
            inner.extend(shard(0))

    outer = shard(1)
    assert inner == [("cheap", 0), ("cheap", 2), ("dear", 1), ("dear", 0), ("dear", 2)]
    assert (0, "cheap", 1) not in calls
    assert outer == [("cheap", 1), ("dear", 0), ("dear", 2), ("cheap", 0), ("cheap", 2), ("dear", 1)]
    # a unit held when the shard reaches it and freed before the end (its holder died) is tried again
    held, order = runs.try_acquire(unit_lock(tmp_path, "u", rows[0], 2)), []

    def release_at_dear_0(r, seed):
        order.append((r["label"], seed))
        if (r["label"], seed) == ("dear", 0):
            held.close()
    assert len(compute_shard(rows, [0, 1, 2], 0, 2, tmp_path, "u", release_at_dear_0)) == 6
    assert order == [("cheap", 0), ("dear", 1), ("cheap", 1), ("dear", 0), ("dear", 2), ("cheap", 2)]
    # force: each shard its own units only
    own = compute_shard(rows, [0, 1, 2], 1, 2, tmp_path, "v", lambda r, seed: None, take_others=False)
    assert [(r["label"], seed) for r, seed in own] == [("cheap", 1), ("dear", 0), ("dear", 2)]
    # a unit of another table (another key) held meanwhile does not hold this table's same unit
    meanwhile = []
    compute_shard(rows, [0], 0, 1, tmp_path, "another table", lambda r, seed: meanwhile.append(shard(0)))
    assert all(len(units) == 6 for units in meanwhile) and len(meanwhile) == 2


@pytest.mark.parametrize("stage_order", ["sr_dn", "dn_sr"])
def test_cascade_stages_assemble_into_one_net(stage_order):
    """Stage weights trained separately (SRDStage) load into the parts of one SRDNet they came from."""
    kw = dict(channels=8, stage_order=stage_order, channel_aug=False, skip=False, gbuffer_mode="concat")
    torch.manual_seed(0)
    first, second = SRDStage(SRDNet(**kw), "sr"), SRDStage(SRDNet(**kw), "dn")
    for p in list(first.parameters()) + list(second.parameters()):
        torch.nn.init.normal_(p, std=0.05)
    net = load_stage(load_stage(SRDNet(**kw), "sr", first.state_dict()), "dn", second.state_dict())
    for name, p in net.named_parameters():
        source = first.net if name.startswith(("sr.", "cond_sr.")) else second.net
        torch.testing.assert_close(p, dict(source.named_parameters())[name])
    with pytest.raises(ValueError, match="no parameters of stage 'sr'"):
        load_stage(SRDNet(**kw), "sr", {"net.dn.out.weight": torch.zeros(1)})


def test_paper_agreement_counts_pairs_ordered_as_in_the_paper_within_a_task():
    table = pd.DataFrame({
        "task": ["sr", "sr", "sr", "denoise", "denoise"],
        "PSNR": [30.0, 31.0, 29.0, 25.0, 26.0],
        "paper PSNR": [30.5, 31.5, 31.6, 28.0, 27.0],   # sr: (0,1) agree, (0,2) and (1,2) disagree
        "SSIM": [0.9, 0.8, 0.7, 0.6, 0.5],
        "paper SSIM": [0.95, 0.95, None, 0.9, 0.8],    # tie and missing value are left out
    })
    assert paper_agreement(table) == {"PSNR": (1, 4), "SSIM": (1, 1)}


def test_claims_give_each_paper_claim_a_verdict_from_the_recorded_tables(dirs):
    overrides, root = dirs
    for name in ("stage_order", "ipt", "deform", "deform_num", "dilation", "dilation_crop", "sota", "perceptual"):
        run_experiment(compose_experiment(name, overrides + ["++experiment.figure=false"]))  # reused
    run_experiment(compose_experiment("claims", overrides))
    table = pd.read_csv(root / "results" / "claims" / "table.csv")
    exp = OmegaConf.to_container(compose_experiment("claims", overrides).experiment, resolve=True)
    assert list(table["claim"].unique()) == [c["claim"] for c in exp["claims"]]
    assert set(table["verdict"]) <= {"holds", "reversed", "within noise"}
    assert table["basis"].str.contains("sequences|seeds").all()
    assert table["recipe"].str.match(r"\d+ steps").all()   # every claim compares trained rows


def _claims_fixture(tmp_path):
    """Synthetic evaluation runs: 3 seeds x 6 sequences of families x, y, z (two frames each), and a
    table of rows built from them: B a base, A = B + 1 dB, C deterministic (one run listed per seed),
    X = B - 1 dB on family x and + 0.5 dB elsewhere (within noise, holds without x)."""
    import numpy as np
    ctx = smoke_context(preset="t", runs_dir=tmp_path / "runs", results_dir=tmp_path / "results", data_dir=tmp_path)
    sequences = ["x-1-v0", "x-2-v0", "y-3-v0", "y-4-v0", "z-5-v0", "z-6-v0"]
    base, rng = np.array([30.0, 35.0, 28.0, 40.0, 33.0, 31.0]), np.random.default_rng(0)
    shift = {"a": 1.0, "b": 0.0, "x": np.array([-1.0, -0.9, 0.5, 0.52, 0.48, 0.51])}
    per_run = {f"{row}{s}": base + offset + rng.normal(0, 0.01, 6) for row, offset in shift.items() for s in range(3)}
    per_run["c"] = base - 0.01
    for run, values in per_run.items():
        (ctx.runs_dir / "eval" / run).mkdir(parents=True)
        pd.DataFrame({"sequence": sequences * 2, "frame": [0] * 6 + [1] * 6, "PSNR": np.tile(values, 2),
                      "SSIM": np.tile(values, 2) / 100, "relMSE": 1 / np.tile(values, 2)}).to_csv(
            ctx.runs_dir / "eval" / run / "per_image.csv", index=False)
    rows = {"A": "a0 a1 a2", "B": "b0 b1 b2", "C": "c c c", "X": "x0 x1 x2"}
    table = pd.DataFrame({"method": list(rows), "runs": list(rows.values())})
    for metric in ("PSNR", "SSIM", "relMSE"):
        means = [np.mean([pd.read_csv(ctx.runs_dir / "eval" / r / "per_image.csv")[metric].mean()
                          for r in runs_.split()]) for runs_ in rows.values()]
        table[metric], table[f"{metric} std"] = means, 0.1
    (ctx.results_dir / "t").mkdir(parents=True)
    table.to_csv(ctx.results_dir / "t" / "table.csv", index=False)
    return ctx


def test_claim_verdicts_pair_seeds_and_sequences_with_holm_and_scene_robustness(tmp_path):
    from bench.experiments import claims
    ctx = _claims_fixture(tmp_path)
    claim_list = [
        {"claim": "A beats B", "better": "t:A", "worse": "t:B"},       # +1 dB on every sequence: holds
        {"claim": "B beats A", "better": "t:B", "worse": "t:A"},       # the same comparison: reversed
        {"claim": "A beats C", "better": "t:A", "worse": "t:C"},       # against a deterministic row
        {"claim": "X beats B", "better": "t:X", "worse": "t:B"},       # +0.02 dB, rests on family x
        {"claim": "both", "better": "t:X", "worse": ["t:B", "t:A"]}]   # within noise + reversed
    elsewhere = {"claim": "in a table not rerun", "better": "t:A", "worse": "other:X"}
    table = claims.run(ctx, "claims", claim_list + [elsewhere], "PSNR", tables=["t"])  # `other` is not read
    by_claim = table.drop_duplicates("claim").set_index("claim")
    assert by_claim["verdict"].to_dict() == {"A beats B": "holds", "B beats A": "reversed", "A beats C": "holds",
                                             "X beats B": "within noise", "both": "reversed"}
    # the earlier test (2SE over seeds from the std columns, 0.16 here) calls X's +0.02 dB within noise too
    assert by_claim.loc["X beats B", "verdict (2SE)"] == "within noise"
    page = (ctx.results_dir / "README.md").read_text()     # the results page, rewritten from the tables
    assert "| A beats B | **holds** |" in page and "[`" in page and "t/table.csv" in page
    assert by_claim.loc["X beats B", "rests on"] == "x -> holds" and by_claim.loc["A beats B", "rests on"] == "-"
    ab = by_claim.loc["A beats B"]
    assert ab["PSNR diff"] == pytest.approx(1.0, abs=0.02) and ab["PSNR low"] < 1.0 < ab["PSNR high"]
    assert ab["PSNR diff"] == pytest.approx(by_claim.loc["B beats A", "PSNR diff"] * -1)
    assert ab["relMSE diff"] > 0 and ab["SSIM diff"] > 0   # relMSE oriented: worse minus better
    assert by_claim.loc["A beats C", "basis"] == "seeds 3 vs 1 (deterministic row broadcast), 6 sequences"
    assert ab["basis"] == "seeds 3 vs 3 (paired by index), 6 sequences"
    assert (ctx.results_dir / "claims" / "table.md").read_text().startswith("The paper's claims at ")
    claims.run(ctx, "studies/s", claim_list[:1], "PSNR", tables=None, subject="A study's comparisons")  # +study=domain_verdicts
    assert (ctx.results_dir / "studies" / "s" / "table.md").read_text().startswith("A study's comparisons at ")
    # Holm over the 4 distinct comparisons (A-B twice counts once): p Holm = 4 x p for the smallest
    distinct = table.drop_duplicates("PSNR p")["PSNR p"].sort_values()
    assert len(distinct) == 4 and table["PSNR p Holm"].min() == pytest.approx(4 * distinct.iloc[0])
    written = pd.read_csv(ctx.results_dir / "claims" / "table.csv")   # the CSV keeps the per-family columns
    assert written.set_index("claim").loc["X beats B", "PSNR diff x"] == pytest.approx(-0.95, abs=0.02)
    assert "PSNR diff x" not in (ctx.results_dir / "claims" / "table.md").read_text()
    assert "Holm" in (ctx.results_dir / "claims" / "table.md").read_text().splitlines()[0]
    assert claims.family_of("dining-1877746876-v0") == "dining" and claims.family_of("my_scene") == "my_scene"
    assert set(table["recipe"]) == {"runs not recorded"}   # these evaluations have no run records
    assert claims.pair_recipe("2000 steps", "untrained") == claims.pair_recipe("untrained", "2000 steps") == "2000 steps"
    assert claims.pair_recipe("2000 steps", "1000 steps") == "2000 steps vs 1000 steps"

    # a row no recorded table has, or a table not run: that claim is "not run" (and says what to run),
    # every other claim is still judged; with nothing recorded at all, a clear error
    missing = [{"claim": "needs a row added later", "better": "t:A", "worse": ["t:B", "t:D"]},
               {"claim": "needs a table not run", "better": "t:A", "worse": "other:X"},
               {"claim": "misspelt", "better": "t:A", "worse": "t:BB"}]
    table = claims.run(ctx, "claims", claim_list + missing, "PSNR", tables=None)
    verdicts = table.drop_duplicates("claim").set_index("claim")["verdict"].to_dict()
    assert table.loc[table["PSNR verdict"] == "not run", "PSNR p Holm"].isna().all()
    assert verdicts["needs a row added later"] == verdicts["needs a table not run"] == "not run"
    assert verdicts["A beats B"] == "holds" and verdicts["both"] == "reversed"
    later = table[table["claim"] == "needs a row added later"].set_index("worse (paper)")
    assert later.loc["t:B", "PSNR verdict"] == "holds" and later.loc["t:D", "PSNR verdict"] == "not run"
    assert "no row 'D'" in later.loc["t:D", "basis"] and "+experiment=t" in later.loc["t:D", "basis"]
    assert "(its rows: 'A', 'B'" in later.loc["t:D", "basis"]
    assert "no row 'BB' in" in table.set_index("claim").loc["misspelt", "basis"] and "(did you mean 'B'?)" in \
        table.set_index("claim").loc["misspelt", "basis"]
    not_run = table.set_index("claim").loc["needs a table not run"]
    assert "does not exist" in not_run["basis"] and "+experiment=other" in not_run["basis"]
    reversed_and_missing = {"claim": "a reversal decides", "better": "t:B", "worse": ["t:A", "t:D"]}
    table = claims.run(ctx, "claims", [reversed_and_missing], "PSNR", tables=None)
    assert set(table["verdict"]) == {"reversed"} and list(table.columns[-1:]) == ["basis"]
    with pytest.raises(UserError, match="none of the claims' rows are recorded") as said:
        claims.run(ctx, "claims", missing[1:] + [{**missing[1], "claim": "the same table again"}], "PSNR", tables=None)
    said = str(said.value)   # each reason once, and the command that runs the paper tables
    assert said.count("other/table.csv does not exist") == 1 and "no row 'BB'" in said
    assert said.endswith(f"(`python -m bench +experiment=all preset={ctx.preset}` runs every paper table)")
    study = {"claim": "a study's comparison", "better": "studies/s2:A", "worse": "studies/s2:B"}
    with pytest.raises(UserError, match=r"run `python -m bench \+study=s2 preset=") as said:   # not +experiment=
        claims.run(ctx, "studies/v", [study], "PSNR", tables=None)
    assert "+experiment=all" not in str(said.value)


def test_reference_check_counts_frames_whose_reference_error_is_below_a_tenth_of_the_best_rows():
    frames = [{"sequence": "s", "frame": i, "ref_spp": 1024, "ref_error": {"lr": 1e-4, "hr": err}}
              for i, err in enumerate([1e-4, 5e-4, 3e-3])]
    per_image = pd.DataFrame({"sequence": ["s"] * 3, "frame": [0, 1, 2], "relMSE": [0.02, 0.004, 0.02]})
    note = reference_check(frames, per_image, "Ours")
    assert "1024 spp as two independent halves" in note and "max 0.003" in note
    assert "relMSE on 1 of 3 scored frames" in note            # 1e-4 < 2e-3; 5e-4 !< 4e-4; 3e-3 !< 2e-3
    plain = reference_check([{"sequence": "s", "frame": 0, "ref_spp": 256}], per_image, "Ours")
    assert "one render of 256 spp per frame; their error is not estimated" in plain
    per_seed = pd.concat([per_image, per_image.assign(relMSE=per_image["relMSE"] * 3)])   # mean over seeds: x2,
    assert "on 3 of 3 scored frames" in reference_check(frames, per_seed, "Ours")      # so all three pass


def test_a_table_says_when_its_rows_scored_different_renders_of_the_split(tmp_path):
    """Hosts render the same settings with different noise: the data fingerprint cannot tell, the
    render digest (the frame files' CRCs) can, and the caption says so."""
    import json
    import types

    from bench.experiments.datasets import render_digest
    from bench.experiments.table import _renders_note
    frame = {"split": "val", "sequence": "s", "frame": 0,
             "files": {"lr": {"crc32": 1}, "hr": {"crc32": 2}}}
    (tmp_path / "manifest.json").write_text(json.dumps({"frames": [frame, {**frame, "split": "train"}]}))
    ctx = types.SimpleNamespace(data_dir=tmp_path)
    first = render_digest(ctx, "val")
    frame["files"]["hr"]["crc32"] = 3                                    # another host's render
    (tmp_path / "manifest.json").write_text(json.dumps({"frames": [frame]}))
    assert first and render_digest(ctx, "val") not in (None, first)
    del frame["files"]
    (tmp_path / "manifest.json").write_text(json.dumps({"frames": [frame]}))
    assert render_digest(ctx, "val") is None                             # unstamped frames: unknown
    assert _renders_note([[first], [first, first]]) == "" and _renders_note([[None], [None, None]]) == ""
    assert _renders_note([]) == ""
    assert "1 of 3 evaluations has no render digest" in _renders_note([[first], [first, None]])
    note = _renders_note([[first], ["other", None]])
    assert "2 different renders" in note and "1 recorded before render digests" in note


def test_a_row_scored_on_its_own_split_gets_that_splits_frame_records_rendered(monkeypatch):
    """Every evaluation recorded, no frame records anywhere for a row's own split: that split is rendered
    (the caption's reference check reads the best row's split, whichever it is), and only it."""
    import types

    from bench.experiments import table
    rendered = []
    monkeypatch.setattr(table, "unrecorded_rows", lambda *args: [])
    monkeypatch.setattr(table, "splits_on_disk", lambda *args, **kwargs: set())
    monkeypatch.setattr(table, "frame_records", lambda ctx, split: [] if split == "generalization" else [{}])
    monkeypatch.setattr(table, "ensure_data", lambda ctx, passes, needed: rendered.append(needed))
    ctx = types.SimpleNamespace(eval=types.SimpleNamespace(split="val"), force=False, seeds=[0])
    rows = [{"label": "Ours"}, {"label": "Ours, unseen", "split": "generalization"}]
    assert table.render_what_runs(ctx, "t", rows, "srd", None, False, {}) is False
    assert rendered == [{"generalization"}]
    rendered.clear()
    assert table.render_what_runs(ctx, "t", rows[:1], "srd", None, False, {}) is False and rendered == []


def test_a_rows_bad_model_argument_stops_the_table_before_anything_is_rendered(tmp_path, monkeypatch):
    from bench.experiments import table
    monkeypatch.setattr(table, "ensure_data", lambda *args: pytest.fail("rendered before the rows were checked"))
    ctx = smoke_context(runs_dir=tmp_path / "runs", results_dir=tmp_path / "results", data_dir=tmp_path / "data",
                        force=True)   # force: no recorded training is looked up (which builds the model too)
    with pytest.raises(UserError, match="SRDNet with .*chanels=8: .*unexpected keyword argument 'chanels'"):
        table.run(ctx, "t", [{"label": "X", "model": "srd", "overrides": {"chanels": 8}}])
    assert not (tmp_path / "runs").exists() and not (tmp_path / "data").exists()


def test_the_caption_names_the_domains_rows_set_beside_the_default():
    """A domain study's rows set train.hdr: the caption's default domain is then only theirs that set none."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        study = compose("config", overrides=["preset=cpu", "+study=domain"])
    rows = expand_rows(OmegaConf.to_container(study.experiment.rows, resolve=True))
    assert domain_note(study.train.hdr, rows) == ("network domain PU21 (train.hdr=pu, bench/exposure.py) where a row "
                                                  "does not set its own (rows here set exposure, exposure_pass, pu)")
    assert domain_note("exposure_pass", expand_rows([{"label": "A", "model": "srd"}])).endswith("bench/exposure.py)")

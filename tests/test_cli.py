"""The command line end to end: config composition, the smoke experiment, run reuse, clear errors."""
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from bench.errors import UserError
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from bench.cli import (CONF_DIR, apply_pin, available_experiments, available_studies, choice_problem,
                       make_context)
from bench.experiments import KINDS
from bench.experiments.results_page import CONTROLS, PAPER_TABLES
from conftest import REPO, SMOKE_DATA, bench, bench_here, perturbed, python_process

PRESETS = sorted(p.stem for p in (Path(CONF_DIR) / "preset").glob("*.yaml"))


def exit_and_text(*args) -> tuple[int, str]:
    """`python -m bench ARGS` in this process (conftest.bench_here): its exit code and what it printed. The
    one-line-error tests need no process of their own (a process costs the imports, seconds)."""
    out = bench_here(*args)
    return out.returncode, out.stdout + out.stderr


def compose_experiment(name, *overrides, group="experiment"):
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        return compose("config", overrides=[f"+{group}={name}", *overrides])


def compose_study(name, *overrides):
    return compose_experiment(name, *overrides, group="study")


def test_a_study_is_pinned_to_the_recipe_it_was_measured_at_only_on_the_preset_that_moved_on():
    """dark_bias was measured at the cpu preset's 1000-step recipe without the SSIM term; at cpu it keeps
    that recipe (pinned before anything resolves: what reads ${train.steps} sees the pin), at gpu it follows
    the gpu preset; the paper's tables and lr_range_ssim are not pinned."""
    def recipe(compose, name, preset):
        cfg = compose(name, f"preset={preset}", "++experiment.seen=${train.steps}")
        apply_pin(cfg)
        return cfg.train.steps, cfg.train.loss.final.get("ssim"), cfg.experiment.seen
    assert recipe(compose_study, "dark_bias", "cpu") == (1000, 0, 1000)   # weight 0: out of the identity
    assert recipe(compose_experiment, "sota", "cpu") == (2000, 8, 2000)
    assert recipe(compose_study, "lr_range_ssim", "cpu") == (2000, 8, 2000)
    gpu = compose_experiment("sota", "preset=gpu").train
    assert recipe(compose_study, "dark_bias", "gpu") == (gpu.steps, gpu.loss.final.get("ssim"), gpu.steps)


def test_conf_experiment_holds_the_paper_tables_their_controls_and_the_tools_only():
    """Studies are a group of their own (conf/study/, `+study=NAME`)."""
    tools = {"smoke", "train", "all", "claims", "data", "references", "macs", "time", "speed", "stability", "lr_range", "adopt",
             "migrate"}
    tables = {name for name, _ in PAPER_TABLES + CONTROLS}
    assert set(available_experiments()) == tables | tools


@pytest.mark.parametrize("name", available_studies())
@pytest.mark.parametrize("preset", PRESETS)
def test_every_study_is_documented_writes_under_studies_and_passes_the_config_check(name, preset):
    docs = (REPO / "docs" / "studies.md").read_text() + (REPO / "docs" / "experiments.md").read_text()
    assert f"`{name}`" in docs or f"### {name}" in docs, f"conf/study/{name}.yaml is in no docs page"
    cfg = compose_study(name, f"preset={preset}")
    apply_pin(cfg)
    assert cfg.experiment.name == f"studies/{name}" and cfg.experiment.kind in KINDS
    ctx = make_context(cfg)                       # the config check every command passes before it runs
    assert ctx.data_spec and ctx.train.steps > 0
    keys_are_its_kinds_arguments(cfg)


@pytest.mark.parametrize("args,problem", [
    (["+study=dark_bias", "preset=smoke"], None),
    (["+experiment=sota,ipt", "seeds=[0,1]"], None),                     # a sweep's names
    (["+study=no_such_study"], "+study=no_such_study: no conf/study/no_such_study.yaml; available: dark_bias,"),
    (["-m", "+experiment=sota,nope"], "+experiment=nope: no conf/experiment/nope.yaml; available: adopt,"),
    (["+experiment=sota", "+study=dark_bias"], "choose an experiment or a study, not both"),
    (["+experiment=data", "verify=true"], "verify=true: the config has no key `verify` at the top; write experiment.verify=true"),
    (["+experiment=sota,data", "verify=true"], "verify=true: the config has no key `verify` at the top; write experiment.verify=true"),
    (["+experiment=sota", "steps=3"], "steps=3: the config has no key `steps` at the top; write train.steps=3"),
    (["+experiment=sota", "stepz=3"], "stepz=3: the config has no key `stepz` at the top (a new key is +KEY=...)"),
    (["+experiment=sota", "preset=smoke", "force=true", "train.steps=4", "+new_key=1", "++seeds=[0]", "~tracking",
      "hydra/launcher=basic", "hydra.run.dir=/tmp/x", "model@models.srd=srd", "-m", "--cfg", "job"], None),
])
def test_choices_are_checked_before_hydra_composes_them(args, problem):
    found = choice_problem(args)
    assert (found is None) if problem is None else found.startswith(problem), found


@pytest.mark.parametrize("name", available_experiments())
@pytest.mark.parametrize("preset", PRESETS)
def test_every_experiment_composes_at_every_preset(name, preset):
    cfg = compose_experiment(name, f"preset={preset}")
    assert cfg.preset.name == preset
    assert cfg.experiment.name == name
    ctx = make_context(cfg)                       # every key the experiments read is there
    assert ctx.data_spec and ctx.train.steps > 0 and ctx.budget_gmac > 0
    keys_are_its_kinds_arguments(cfg)


def keys_are_its_kinds_arguments(cfg):
    """An experiment's keys bind to its kind's run(): the YAML is their one source (run() restates no default)."""
    import importlib
    from bench.cli import check_experiment_keys
    exp = OmegaConf.to_container(cfg.experiment, resolve=False)
    exp.pop("pin", None), exp.pop("tunes", None)
    kind = exp.pop("kind", "table")
    if kind != "all":
        check_experiment_keys(importlib.import_module(f"bench.experiments.{kind}").run, exp, kind)


@pytest.mark.parametrize("name", sorted(p.stem for p in (Path(CONF_DIR) / "model").glob("*.yaml")))
def test_every_model_config_is_configured_and_keeps_the_model_contract(name):
    """Each conf/model/*.yaml: in the root config's models, built by the one factory, (B, T, C, h, w) in,
    "final" (B, T, 3, 2h, 2w) out, finite, and the same whether the sequence comes at once or frame by
    frame for a model that is not recurrent (its weights perturbed: untrained, a learned model returns the
    bilinear upsample of each frame, which is frame by frame whatever the network does)."""
    from bench.models.factory import build_model
    cfg = compose_experiment("smoke", "preset=smoke")
    assert name in cfg.models, f"conf/model/{name}.yaml is not in conf/config.yaml's defaults"
    torch.manual_seed(0)
    model = build_model(OmegaConf.to_container(cfg.models[name], resolve=True), 2)
    x, g = torch.rand(1, 2, 3, 13, 7), torch.rand(1, 2, 7, 13, 7)
    with torch.no_grad():
        out = model(x, g)
        assert out["final"].shape == (1, 2, 3, 26, 14)
        assert torch.isfinite(out["final"]).all()
        if not getattr(model, "recurrent", False):
            if any(True for _ in model.parameters()):
                out = perturbed(model)(x, g)
                assert torch.isfinite(out["final"]).all()
            second = model(x[:, 1:], g[:, 1:])["final"]
            torch.testing.assert_close(second[:, 0], out["final"][:, 1], rtol=1e-4, atol=1e-5)


_AUDITED: dict[str, tuple[dict, dict | None]] = {}   # (label, model config, budget, width_arg) -> `_audit`'s rows


def _audit(label, cfg, budget_macs, width_arg):
    """`audit_row` of the configured model and, with `width_arg`, of its width fitted to the budget; the
    presets that share a budget and a model's config (smoke and cpu, gpu and paper) share one audit: the
    same inputs, the same counts (each fit counts about ten models at 960x540, seconds per preset)."""
    from bench.experiments.macs import audit_row
    key = json.dumps([label, cfg, budget_macs, width_arg], sort_keys=True, default=str)
    if key not in _AUDITED:
        checked, _ = audit_row(label, cfg, budget_macs, (540, 960))
        fitted = audit_row(label, {**cfg, "width_arg": width_arg}, budget_macs, (540, 960))[0] if width_arg else None
        _AUDITED[key] = checked, fitted
    return _AUDITED[key]


@pytest.mark.parametrize("preset", PRESETS)
def test_configured_widths_meet_the_preset_budget(preset):
    """The widths a preset trains with are the ones the MAC audit fits to its budget (+-5%)."""
    from bench.experiments.macs import SOTA_ROWS
    ctx = make_context(compose_experiment("smoke", f"preset={preset}"))
    for row in SOTA_ROWS:
        cfg = dict(ctx.models[row["model"]])
        checked, fitted = _audit(row["label"], cfg, ctx.budget_gmac * 1e9, row["width_arg"])
        assert abs(checked["budget deviation %"]) <= 5, (preset, checked)
        if row["width_arg"]:
            assert fitted["width"] == f"{row['width_arg']}={cfg[row['width_arg']]}", (preset, fitted)


def test_smoke_end_to_end_then_reuse(smoke_dirs):
    args, root = smoke_dirs
    table_dir = root / "results"
    for ext in ("csv", "tex", "md"):
        assert (table_dir / "smoke" / f"table.{ext}").exists()
    table = pd.read_csv(table_dir / "smoke" / "table.csv")
    assert list(table["method"]) == ["Input bilinear", "Ours"]
    for col in ("relMSE", "PSNR", "SSIM"):
        assert table[col].notna().all() and (table[col].abs() < float("inf")).all(), col

    second = bench_here("+experiment=smoke", *args)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "reusing" in second.stdout + second.stderr
    assert "2 of 2 rows reused" in second.stdout + second.stderr
    assert "trained in" not in second.stdout + second.stderr and "frames rendered" not in second.stdout + second.stderr
    again = pd.read_csv(table_dir / "smoke" / "table.csv")
    pd.testing.assert_frame_equal(table[["method", "relMSE", "PSNR", "SSIM"]],
                                  again[["method", "relMSE", "PSNR", "SSIM"]])


def test_an_evaluation_recorded_before_flip_is_reused_without_it_and_scored_again_when_asked(smoke_dirs, tmp_path,
                                                                                           caplog, monkeypatch):
    """Evaluations recorded before FLIP existed (evaluate.LATER_SCORES) are reused as they are, their FLIP
    cells blank; eval.rescore_missing=true scores them again from the recorded training, which is not retrained,
    and the other scores come out as recorded."""
    from bench import runs
    from bench.cli import run_experiment
    from bench.evaluate import LATER_SCORES
    monkeypatch.setattr(runs, "COMMAND_STARTED_S", time.time())   # a new command, after the store was made
    args, root = smoke_dirs
    shutil.copytree(root / "runs", tmp_path / "runs", ignore=shutil.ignore_patterns("mlflow*", "hydra"))
    for path in (tmp_path / "runs" / "eval").glob("*/run.json"):   # as recorded before FLIP
        record = json.loads(path.read_text())
        record["metrics"] = {k: v for k, v in record["metrics"].items() if not k.startswith(LATER_SCORES)}
        path.write_text(json.dumps(record))
    ours = [a for a in args if not a.startswith(("runs_dir=", "results_dir="))] + [
        f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}"]
    flip = list(LATER_SCORES)
    with caplog.at_level("INFO", logger="bench"):
        run_experiment(compose_experiment("smoke", *ours))
    table = pd.read_csv(tmp_path / "results" / "smoke" / "table.csv")
    assert table[flip].isna().all().all() and "re-evaluating" not in caplog.text
    caplog.clear()
    with caplog.at_level("INFO", logger="bench"):
        run_experiment(compose_experiment("smoke", *ours, "eval.rescore_missing=true"))
    rescored = pd.read_csv(tmp_path / "results" / "smoke" / "table.csv")
    assert rescored[flip].notna().all().all()
    assert caplog.text.count("recorded without LDR-FLIP, HDR-FLIP") == 2          # both rows
    assert "train Ours: reusing run" in caplog.text and "trained in" not in caplog.text
    pd.testing.assert_frame_equal(table[["method", "relMSE", "PSNR", "SSIM"]], rescored[["method", "relMSE", "PSNR", "SSIM"]])


@pytest.mark.slow  # two torchrun processes and a one-process run of the smoke table (~1-2 min on 2 cores); make test-slow
def test_torchrun_two_processes_train_as_one_and_only_rank_0_records(smoke_dirs, tmp_path):
    """`torchrun --nproc_per_node 2 -m bench` (gloo, no GPU): one run recorded, by rank 0, whose training
    curve is the one-process run's with the same global batch, and the table written once."""
    args, _ = smoke_dirs
    data = [a for a in args if a.startswith("data_dir=")]
    common = ["+experiment=smoke", *data, "progress=false", "train.steps=4", *SMOKE_DATA]
    env = dict(os.environ, HYDRA_FULL_ERROR="0", OMP_NUM_THREADS="1")
    curves = {}
    for name, launcher in (("one", []), ("two", ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"])):
        root = tmp_path / name
        cmd = [sys.executable, *launcher, "-m", "bench", *common, f"runs_dir={root / 'runs'}",
               f"results_dir={root / 'results'}"]
        out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600, env=env)
        assert out.returncode == 0, out.stderr[-3000:]
        records = list((root / "runs" / "train").glob("*/run.json"))
        assert len(records) == 1 and json.loads(records[0].read_text())["status"] == "complete"
        curves[name] = pd.read_csv(records[0].parent / "curve.csv")
        assert (root / "results" / "smoke" / "table.csv").exists()
        assert (root / "runs" / "hydra" / "rank1").exists() == (name == "two")  # rank 1's log, apart
    assert records[0].parent.name == next((tmp_path / "one" / "runs" / "train").iterdir()).name  # same identity
    pd.testing.assert_series_equal(curves["two"]["loss"], curves["one"]["loss"], rtol=1e-5)


def test_reused_training_is_loaded_for_a_new_evaluation(smoke_dirs):
    """A new evaluation of a recorded training (here: with output frames) must use the trained weights:
    same numbers as the first evaluation, and the frames written as EXR."""
    args, root = smoke_dirs
    before = pd.read_csv(root / "results" / "smoke" / "table.csv")
    out = bench_here("+experiment=smoke", "eval.save_exr=true", *args)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "train Ours: reusing run" in out.stdout + out.stderr
    after = pd.read_csv(root / "results" / "smoke" / "table.csv")
    pd.testing.assert_frame_equal(before[["method", "relMSE", "PSNR", "SSIM"]],
                                  after[["method", "relMSE", "PSNR", "SSIM"]])
    assert list((root / "runs" / "eval").glob("*/frames/*.exr"))


def test_fast_path_auto_is_measured_and_recorded_as_the_path_it_chose(smoke_dirs):
    args, root = smoke_dirs
    others = [a for a in args if not a.startswith("results_dir=")]
    out = bench_here("+experiment=smoke", "eval.fast_path=auto", f"results_dir={root / 'results_auto'}", *others)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "eval Ours: fast_path=auto chose " in out.stdout + out.stderr
    chosen = json.loads((root / "runs" / "fast_paths.json").read_text())
    (entry,) = chosen.values()
    fp32 = pd.read_csv(root / "results" / "smoke" / "table.csv").set_index("method")
    auto = pd.read_csv(root / "results_auto" / "smoke" / "table.csv").set_index("method")
    record = json.loads((root / "runs" / "eval" / auto.loc["Ours", "runs"] / "run.json").read_text())
    assert record["identity"]["fast_path"] == entry["path"]
    # chosen on the weights it scored (a path's error depends on them), not on an untrained copy
    from bench import archived
    from bench.measure import weights_digest
    from bench.models.factory import build_model
    train_dir = root / "runs" / "train" / record["metrics"]["train_run"]
    cfg = json.loads((train_dir / "run.json").read_text())["identity"]["model"]
    trained = archived.load_weights(build_model(cfg, 2), train_dir, "cpu")
    assert json.loads(next(iter(chosen)))["weights"] == weights_digest(trained)
    assert abs(auto.loc["Ours", "PSNR"] - fp32.loc["Ours", "PSNR"]) < 0.05


def test_recorded_models_score_another_dataset_without_retraining(smoke_dirs):
    """eval.data_dir: the smoke data's val split, copied as a user's dataset with the split renamed,
    scores the same as the original (same frames) with every training reused."""
    args, root = smoke_dirs
    mine = root / "mine"
    shutil.copytree(root / "data", mine)
    (mine / "val").rename(mine / "holdout")
    manifest = json.loads((mine / "manifest.json").read_text())
    for frame in manifest["frames"]:
        frame["split"] = "holdout" if frame["split"] == "val" else frame["split"]
    (mine / "manifest.json").write_text(json.dumps(manifest))

    wrong_split = bench_here("+experiment=smoke", f"eval.data_dir={mine}", *args)
    assert wrong_split.returncode == 2 and "Traceback" not in wrong_split.stderr
    assert "no frames in split 'val'" in wrong_split.stderr and "'holdout'" in wrong_split.stderr
    assert "eval.split=" in wrong_split.stderr

    others = [a for a in args if not a.startswith("results_dir=")]
    out = bench_here("+experiment=smoke", f"eval.data_dir={mine}", "eval.split=holdout",
                f"results_dir={root / 'results_mine'}", *others)
    assert out.returncode == 0, out.stderr[-3000:]
    log = out.stdout + out.stderr
    assert "train Ours: reusing run" in log and "trained in" not in log
    assert "eval Ours: reusing run" not in log                  # new evaluations: other data
    before = pd.read_csv(root / "results" / "smoke" / "table.csv")
    after = pd.read_csv(root / "results_mine" / "smoke" / "table.csv")
    pd.testing.assert_frame_equal(before[["method", "relMSE", "PSNR", "SSIM"]],
                                  after[["method", "relMSE", "PSNR", "SSIM"]])
    assert set(before["runs"]).isdisjoint(after["runs"])


def test_an_unknown_study_is_one_line_listing_the_studies():
    """`python -m bench +study=no_such_study`: it stops before Hydra."""
    out = bench_here("+study=no_such_study", "preset=smoke")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"error: +study=no_such_study: no conf/study/no_such_study.yaml; available: {', '.join(available_studies())}"]


def test_missing_experiment_lists_the_available_ones():
    code, said = exit_and_text()
    assert code == 2
    assert "+experiment=NAME" in said and "smoke" in said and "+study=NAME" in said and "dark_bias" in said


def test_unknown_model_is_a_clear_message(tmp_path):
    code, said = exit_and_text("+experiment=smoke", "experiment.rows=[{label:x,model:no_such_model}]",
                               f"runs_dir={tmp_path}/runs", f"results_dir={tmp_path}/results",
                               f"data_dir={tmp_path}/data")
    assert code == 2 and "unknown model 'no_such_model'" in said


def test_missing_data_directory_is_a_clear_message(tmp_path):
    code, said = exit_and_text("+experiment=smoke", "render_data=false", f"data_dir={tmp_path}/nowhere",
                               f"runs_dir={tmp_path}/runs", f"results_dir={tmp_path}/results")
    assert code == 2 and "has no manifest.json" in said


def test_bench_here_ends_as_the_command_in_its_own_process_and_leaves_this_one_as_it_was(tmp_path, monkeypatch):
    """conftest.bench_here, which the command tests use where a process adds nothing: a command that gets
    as far as Hydra's logging and then stops ends with the exit code and the output `python -m bench`
    gives in a process of its own (lines written to the file descriptors and warnings included), and
    leaves the logging, the SIGTERM handler, the environment, the working folder and sys.argv as it found
    them."""
    import logging
    import signal
    import warnings
    args = ("+experiment=smoke", "render_data=false", f"data_dir={tmp_path}/nowhere", f"runs_dir={tmp_path}/runs",
            f"results_dir={tmp_path}/results")
    root = logging.getLogger()
    state = lambda: (root.handlers[:], root.level, signal.getsignal(signal.SIGTERM), dict(os.environ), os.getcwd(),
                     sys.argv[:])
    before = state()
    here = bench_here(*args)
    assert state() == before
    assert list((tmp_path / "runs").glob("hydra/*/cli.log")), "the command got as far as Hydra's logging"
    there = subprocess.run([sys.executable, "-m", "bench", *args], cwd=REPO, capture_output=True, text=True,
                           timeout=300, env=dict(os.environ, HYDRA_FULL_ERROR="0"))   # a fresh interpreter: the reference
    assert here.returncode == there.returncode == 2
    assert here.stderr.strip().splitlines()[-1] == there.stderr.strip().splitlines()[-1]

    from bench.experiments import table
    ready_data = table.ready_data

    def loud(*a, **k):  # what a C++ library or a child process writes, and a warning, before the same stop
        os.write(2, b"written to fd 2\n")
        warnings.warn("a warning a fresh process prints")
        return ready_data(*a, **k)
    monkeypatch.setattr(table, "ready_data", loud)
    noisy = bench_here(*args)
    lines = noisy.stderr.strip().splitlines()
    assert lines[0] == "written to fd 2" and "UserWarning: a warning a fresh process prints" in lines[1]
    assert lines[-1] == here.stderr.strip().splitlines()[-1]


def test_unwritable_runs_directory_is_one_line_not_a_hydra_traceback(tmp_path):
    """Hydra makes its output folder under runs_dir before our code runs; it must not fail there."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, said = exit_and_text("+experiment=macs", "preset=smoke", f"runs_dir={blocker}/runs",
                               f"results_dir={tmp_path}/results")
    assert code == 2 and f"runs directory {blocker}/runs is not writable" in said


def test_unwritable_results_directory_is_a_clear_message(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, said = exit_and_text("+experiment=smoke", f"results_dir={blocker}/results",
                               f"runs_dir={tmp_path}/runs")
    assert code == 2 and "not writable" in said


def test_macs_experiment_audits_the_sota_models(tmp_path):
    out = bench_here("+experiment=macs", "preset=paper", f"results_dir={tmp_path}", f"runs_dir={tmp_path}/runs")
    assert out.returncode == 0, out.stderr[-3000:]
    table = pd.read_csv(tmp_path / "macs" / "table.csv")
    assert list(table["method"]) == ["EDSR", "RAE", "KPCN", "CFM", "Ours"]
    assert (table["budget deviation %"].abs() <= 5).all(), table
    # the two counters agree on conv/matmul work; only declared extra MACs (sampling, filtering) differ
    seen = table["GMac (analytic)"] - table["GMac not seen by torch counter"]
    assert ((seen - table["GMac (torch counter)"]).abs() <= 0.01 * table["GMac (torch counter)"]).all()
    assert (tmp_path / "macs" / "table.tex").exists() and (tmp_path / "macs" / "stages.csv").exists()


def test_data_experiment_summarises_every_split(smoke_dirs):
    args, root = smoke_dirs
    out = bench_here("+experiment=data", "preset=smoke", *args)
    assert out.returncode == 0, out.stderr[-3000:]
    table = pd.read_csv(root / "results" / "data" / "table.csv")
    assert set(table["split"]) == {"train", "val", "generalization"}
    assert (table["frames"] > 0).all()
    assert any(c.endswith(" s") for c in table.columns)           # per-pass render seconds
    assert len(list((root / "results" / "data" / "examples").glob("*.png"))) >= 4


def test_shard_parses_i_over_n_and_rejects_the_rest():
    from bench.cli import parse_shard
    assert parse_shard(None) is None and parse_shard("1/3") == (1, 3)
    for bad in ("3/3", "-1/2", "a/b", "2"):
        with pytest.raises(UserError, match="shard="):
            parse_shard(bad)


@pytest.mark.parametrize("override,message", [
    ("train.steps=0", "train.steps=0: expected a positive integer"),
    ("train.steps=-5", "train.steps=-5: expected a positive integer"),
    ("train.steps=abc", "train.steps='abc': expected a positive integer"),
    ("train.batch_size=0", "train.batch_size=0: expected a positive integer"),
    ("train.checkpoint_every=0", "train.checkpoint_every=0: expected a positive integer"),
    ("train.seq_len=0", "train.seq_len=0: expected a positive integer"),
    ("train.crop=-8", "train.crop=-8: expected a positive integer"),
    ("train.val_sequences=-1", "train.val_sequences=-1: expected an integer >= 0"),
    ("tracking=wandb", "tracking='wandb': expected mlflow or none"),
    ("train.checkpoint_every_s=0", "train.checkpoint_every_s=0: expected a positive number"),
    ("train.val_every=-1", "train.val_every=-1: expected an integer >= 0"),
    ("train.lr=0", "train.lr=0: expected a positive number"),
    ("workers=0", "workers=0: expected a positive integer"),
    ("jobs=0", "jobs=0: expected a positive integer"),
    ("seeds=0", "seeds=0: expected a non-empty list of integers"),
    ("seeds=[]", "seeds=[]: expected a non-empty list of integers"),
    ("seeds=[a]", "seeds=['a']: expected a non-empty list of integers"),
    ("seeds=[0,0]", "seeds=[0, 0]: a seed named twice"),
    ("experiment.rows=[]", "experiment.rows: expected a non-empty list of rows"),
    ("experiment.rows=[bilinear]", "row 'bilinear': expected a mapping with at least label and model"),
    ("experiment.rows=[{label:A,model:bilinear,task:nosuch}]", "row 'A': unknown task 'nosuch'"),
    ("+model_lr.srd=-1", "model_lr.srd=-1: expected a positive number"),
    ("eval.fast_path=turbo", "eval.fast_path='turbo': unknown fast path switch 'turbo'"),
    ("+eval.path=fp32", "eval or vgg: EvalSpec.__init__() got an unexpected keyword argument 'path'"),
    ("~eval.save_exr", "eval or vgg: EvalSpec.__init__() missing 1 required positional argument: 'save_exr'"),
    ("+train.lrr=1", "train: unknown train.* keys ['lrr']"),
    ("~train.precision", "train: missing train.* keys ['precision']"),
    ("eval.tile=0", "eval.tile=0: expected null (whole frames) or a positive integer"),
    ("experiment.rows.1.label=Input bilinear", "experiment.rows: the label 'Input bilinear' names 2 rows"),
    ("train.clip_grad_norm=-1", "train.clip_grad_norm=-1: expected null or a positive number"),
    ("train.warmup=5", "train.warmup=5: expected a fraction of the steps in [0, 1)"),
    ("train.ema=abc", "train.ema='abc': expected null or a decay in [0, 1)"),
    ("train.betas=[2,3]", "train.betas=[2, 3]: expected two numbers in [0, 1)"),
    ("train.colour_permute=maybe", "train.colour_permute='maybe': expected true or false"),
    ("train.emitters=2", "train.emitters=2: expected a share of the training items in [0, 1]"),
    ("train.fireflies=-0.1", "train.fireflies=-0.1: expected a share of the training items in [0, 1]"),
    ("train.emitters_exposure=room", "train.emitters_exposure='room': expected with or without"),
    ("train.loss_knee=0", "train.loss_knee=0: expected null or a number > 0"),
    ("train.loss.final.edge=-1", "train.loss.final.edge=-1: expected a number >= 0"),
    ("+train.loss.final.ssmi=1", "train.loss.final: unknown loss terms ['ssmi']"),
    ("force=maybe", "force='maybe': expected true or false"),
    ("eval.save_exr=maybe", "eval.save_exr='maybe': expected true or false"),
    ("+model_lr.srdd=1e-3", "model_lr.srdd: no model srdd (models: srd, "),
])
def test_every_bad_value_is_one_line_naming_key_value_and_rule(tmp_path, override, message):
    with pytest.raises(UserError) as err:
        make_context(compose_experiment("smoke", "preset=smoke", override, f"runs_dir={tmp_path}/runs"))
    assert message in str(err.value) and "nothing was run" in str(err.value)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("override", ["train.emitters=2", "train.fireflies=-0.1", "train.emitters_exposure=room",
                                      "train.loss_knee=0",
                                      "experiment.rows=[{label:a,model:srd,train:{emitters:2}}]"])
def test_a_value_the_recipe_checks_too_is_named_once(tmp_path, override):
    """The config checks and the training Recipe both check these values: one line says it, not two."""
    with pytest.raises(UserError) as err:
        make_context(compose_experiment("smoke", "preset=smoke", override, f"runs_dir={tmp_path}/runs"))
    said = str(err.value).removeprefix("bad config (nothing was run): ")
    assert said.count("\n") == 0 and said.count("train.") == 1, said


def test_a_bad_value_on_the_command_line_ends_in_one_message_before_any_run(tmp_path):
    code, said = exit_and_text("+experiment=smoke", "preset=smoke", "train.steps=0",
                               "train.batch_size=0", f"runs_dir={tmp_path}/runs", f"results_dir={tmp_path}/results",
                               f"data_dir={tmp_path}/data")
    assert code == 2 and "train.steps=0" in said and "train.batch_size=0" in said
    assert not list((tmp_path / "runs").glob("train/*"))


@pytest.mark.slow  # a joblib sweep of two processes; the launcher path also runs in test_tracking's shards; make test-slow
def test_sweep_jobs_write_distinct_tables_with_the_joblib_launcher(tmp_path):
    """The MAC audit needs no data or training: a cheap sweep of two jobs run in parallel by joblib."""
    out = bench("-m", "hydra/launcher=joblib", "+experiment=macs", "preset=smoke", "seeds=[0],[1]",
                f"runs_dir={tmp_path}/runs", f"results_dir={tmp_path}/results", f"data_dir={tmp_path}/data",
                "progress=false")
    assert out.returncode == 0, out.stderr[-2000:]
    tables = sorted(p.parent.parent.name for p in (tmp_path / "results" / "sweeps").glob("*/macs/table.csv"))
    assert tables == ["seeds=_0_", "seeds=_1_"]


def test_the_old_names_flops_scale_and_eval_path_are_gone():
    """Renamed names are not kept working beside the new ones: one name for each thing."""
    assert "flops" not in available_experiments()
    with pytest.raises(ConfigCompositionException, match=r"Could not override 'scale'"):
        compose_experiment("macs", "scale=smoke")
    with pytest.raises(ConfigCompositionException, match=r"Could not override 'eval\.path'"):
        compose_experiment("macs", "eval.path=fp32")


def test_all_counts_every_seed_and_each_shared_run_once(tmp_path, caplog):
    """The `all` table's compute column sums the recorded wall time of every seed's runs (not a seed
    average), its last row counts a run that two tables share once, and a run neither the store nor
    the archive holds is counted as not found, not as 0 minutes."""
    from bench.cli import compute_columns, table_summary
    from bench.experiments.row import recorded_minutes

    def record(root, kind, run_hash, seconds, train_run=None):
        folder = root / kind / run_hash
        folder.mkdir(parents=True)
        metrics = {"train_run": train_run} if kind == "eval" else {}
        (folder / "run.json").write_text(json.dumps({"status": "complete", "wall_time_s": seconds, "metrics": metrics}))

    store, archive = tmp_path / "runs", tmp_path / "archive"
    record(store, "train", "t0", 600), record(store, "train", "t1", 1200)        # one row, two seeds
    record(archive, "train", "s1", 60), record(archive, "train", "s2", 120)     # a Cascade's two stages
    record(store, "eval", "e0", 6, "t0"), record(store, "eval", "e1", 12, "t1")
    record(archive, "eval", "c0", 30, "s1+s2")
    record(store, "eval", "g0", 18, "t0")                                       # another table scores t0 again
    tables = {"a": "e0 e1\nc0", "b": "g0\ne_missing"}
    for name, cells in tables.items():
        (tmp_path / name).mkdir()
        pd.DataFrame({"method": ["x", "y"], "train (min)": [1.0, 1.0], "eval (min)": [0.1, 0.1],
                      "runs": cells.split("\n")}).to_csv(tmp_path / name / "table.csv", index=False)
    a, minutes_a = table_summary(tmp_path / "a", store, (archive,))
    with caplog.at_level("WARNING", logger="bench"):
        b, minutes_b = table_summary(tmp_path / "b", store, (archive,))
    assert "b: 1 of its runs are in neither the run store nor the archive" in caplog.text
    assert a["compute (min)"] == pytest.approx((600 + 1200 + 60 + 120 + 6 + 12 + 30) / 60) and a["trainings"] == 4
    assert b["compute (min)"] == pytest.approx((600 + 18) / 60) and b["trainings"] == 1
    assert a["runs not found"] == 0 and b["runs not found"] == 1                # e_missing: reported, not 0 min
    both = compute_columns({**minutes_a, **minutes_b})
    assert both["compute (min)"] == pytest.approx((600 + 1200 + 60 + 120 + 6 + 12 + 30 + 18) / 60)
    assert both["trainings"] == 4 and both["runs not found"] == 1
    record(store, "eval", "h0", 6, "t0+t_gone")                                 # a stage the store lost
    minutes = recorded_minutes(["h0"], store, (archive,))
    assert minutes == {"eval/h0": pytest.approx(0.1), "train/t0": pytest.approx(10.0), "train/t_gone": None}


def test_a_results_dir_elsewhere_says_the_committed_archive_is_not_read(tmp_path, caplog):
    """runs_archive follows results_dir: moved elsewhere, the committed runs are not read and every
    recorded run would be computed again; the first line says so and how to read them."""
    code, said = exit_and_text("+experiment=train", "experiment.model=nosuch", "preset=cpu",
                               "tracking=none", f"results_dir={tmp_path / 'results'}", f"runs_dir={tmp_path / 'runs'}",
                               f"data_dir={tmp_path / 'data'}")
    said += caplog.text  # the line is a warning of the bench logger
    assert code == 2 and "the committed archive results/cpu/runs is not read" in said, said[-2000:]
    assert f"runs_archive={REPO / 'results' / 'cpu' / 'runs'} reads it" in said
    assert not (tmp_path / "data").exists()
    for yours in ("render_data=false", f"eval.data_dir={tmp_path / 'yours'}"):  # your frames: never in it
        caplog.clear()
        code, said = exit_and_text("+experiment=train", "experiment.model=nosuch", "preset=cpu",
                                   "tracking=none", yours, f"results_dir={tmp_path / 'results'}",
                                   f"runs_dir={tmp_path / 'runs'}", f"data_dir={tmp_path / 'data'}")
        assert code == 2 and "committed archive" not in said + caplog.text, yours


def test_your_frames_never_replace_the_committed_tables(tmp_path):
    """Scoring or training on your frames with results_dir left at the preset's committed folder is one
    line naming results_dir=, before anything is read or written."""
    table = REPO / "results" / "cpu" / "sota" / "table.csv"
    before = table.stat().st_mtime_ns
    for yours in ([f"eval.data_dir={tmp_path / 'yours'}", "eval.split=holdout"],
                  ["render_data=false", f"data_dir={tmp_path / 'yours'}"]):
        code, said = exit_and_text("+experiment=sota", "preset=cpu", "tracking=none", *yours,
                                   f"runs_dir={tmp_path / 'runs'}")
        assert code == 2 and "Traceback" not in said, said[-2000:]
        assert "would replace the committed ones" in said and "results_dir=/tmp/mine" in said, said[-2000:]
    assert table.stat().st_mtime_ns == before
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["hydra"]  # Hydra's log folder, no run


def test_an_experiment_flag_that_is_not_true_or_false_is_refused():
    """`experiment.delete_dropped=no` is the string 'no', which is true: it would have deleted."""
    from bench.cli import check_experiment_keys
    from bench.experiments import migrate
    with pytest.raises(UserError, match=r"experiment.delete_dropped='no': expected true or false"):
        check_experiment_keys(migrate.run, {"name": "migrate", "delete_dropped": "no"}, "migrate")
    check_experiment_keys(migrate.run, {"name": "migrate", "delete_dropped": False}, "migrate")


@pytest.mark.parametrize("override, said", [("experiment.input_hw=[0,0]", "expected [height, width]"),
                                            ("experiment.repeats=0", "experiment.repeats=0: expected an integer >= 1"),
                                            ("experiment.fast_paths=[bogus]", "experiment.fast_paths: 'bogus'")])
def test_a_bad_speed_option_is_one_line_before_anything_is_timed(tmp_path, override, said):
    code, text = exit_and_text("+experiment=speed", "experiment.models=[srd]", override,
                               "preset=smoke", "tracking=none", f"results_dir={tmp_path / 'results'}",
                               f"runs_dir={tmp_path / 'runs'}")
    assert code == 2 and said in text and "Traceback" not in text, text[-2000:]
    assert not list((tmp_path / "results").rglob("table.csv"))


@pytest.mark.parametrize("tables", ["[]", "smoke"])
def test_all_with_no_list_of_tables_is_one_line(tmp_path, tables):
    from bench.cli import run_all
    with pytest.raises(UserError, match="expected a non-empty list of experiments"):
        run_all([], tmp_path, [] if tables == "[]" else tables)


def test_a_label_that_leaves_its_folder_is_refused(tmp_path):
    """`+experiment=train`'s label names the table's folder: `..` in it would write over other tables."""
    code, said = exit_and_text("+experiment=train", "experiment.model=bilinear",
                               "experiment.label=../../x", "preset=smoke", "tracking=none",
                               f"results_dir={tmp_path / 'results'}", f"runs_dir={tmp_path / 'runs'}",
                               f"data_dir={tmp_path / 'data'}")
    assert code == 2 and "one name without / or .." in said, said[-2000:]
    assert not (tmp_path / "x").exists() and not (tmp_path / "data").exists()


def test_a_misspelt_experiment_key_is_one_line(tmp_path):
    """`experiment.<key>` that the kind does not take ends in one line naming the keys it takes, before
    anything runs (nothing written)."""
    code, said = exit_and_text("+experiment=macs", "+experiment.input_size=[64,96]", "preset=cpu",
                               "tracking=none", f"results_dir={tmp_path / 'results'}", f"runs_dir={tmp_path / 'runs'}",
                               f"data_dir={tmp_path / 'data'}")
    assert code == 2, said
    assert "no key input_size; kind macs takes name, rows, input_hw, caption" in said
    assert not (tmp_path / "results").exists()


def test_the_unread_archive_warning_is_for_experiments_that_read_runs(tmp_path, caplog):
    import types
    from bench.cli import warn_if_committed_archive_unread
    ctx = types.SimpleNamespace(render_data=True, eval=types.SimpleNamespace(data_dir=None),
                                runs_archive=tmp_path / "results" / "runs")
    for kind, said in (("table", True), ("claims", True), ("macs", False), ("speed", False)):
        caplog.clear()
        with caplog.at_level("WARNING", logger="bench"):
            warn_if_committed_archive_unread(ctx, kind, "cpu")
        assert ("the committed archive results/cpu/runs is not read" in caplog.text) == said, kind


def test_check_experiment_keys_names_a_missing_key():
    from bench.cli import check_experiment_keys
    from bench.experiments import claims
    check_experiment_keys(claims.run, {"name": "c", "claims": [], "metric": "PSNR", "tables": None}, "claims")
    with pytest.raises(UserError, match="missing a required argument: 'metric'.*kind claims takes name, claims, metric"):
        check_experiment_keys(claims.run, {"name": "c", "claims": [], "tables": None}, "claims")
    from bench.cli import run_all
    with pytest.raises(UserError, match="no key overrides; kind all takes tables, name"):  # the caller's own
        check_experiment_keys(run_all, {"tables": [], "overrides": []}, "all", supplied=("overrides", "results_dir"))
    code, said = exit_and_text("+experiment=all", "~experiment.tables", "+experiment.table=[sota]",
                               "preset=cpu")
    assert code == 2 and "'all' (kind all): no key table; kind all takes tables, name" in said


@pytest.mark.parametrize("args, message", [
    (["train.step=5"], "train.step=5: the config has no key train.step (a new key is +train.step=5)"),
    (["+experiment=claims", "experiment.metrc=SSIM"], "experiment.metrc=SSIM: the config has no key experiment.metrc"),
    (["preset=nonexistent"], "Could not find 'preset/nonexistent'; Available options in 'preset': cpu, gpu, paper, smoke"),
    (["seeds=0,1"], "Ambiguous value for argument 'seeds=0,1'; 1. To use it as a list"),
    (["train.steps=3"], None), (["-m", "seeds=0,1"], None),   # composes; a sweep is Hydra's to expand
])
def test_what_hydra_cannot_compose_is_one_line(args, message):
    from bench.cli import composition_problem
    said = composition_problem(args)
    assert said == message if message is None else (message in said and "\n" not in said)


def test_unknown_names_stop_all_and_claims_before_anything_runs(tmp_path):
    from bench.cli import run_all
    from bench.experiments import claims
    with pytest.raises(UserError, match="unknown experiment 'sotaa'; available: .*macs"):
        run_all([], tmp_path, ["macs", "sotaa"])                  # macs is not run first
    assert not list(tmp_path.iterdir())
    rows = [{"claim": "c", "better": "sota:A", "worse": "sota:B"}]
    with pytest.raises(UserError, match="experiment.metric=psnr: the claims are decided on one of PSNR, SSIM"):
        claims.run(None, "claims", rows, "psnr", None)
    for tables in (["sota", "dilaton"], "sota"):
        with pytest.raises(UserError, match="a list of the tables the claims' rows come from.*they are sota"):
            claims.run(None, "claims", rows, "PSNR", tables)


def test_a_bad_model_argument_is_one_line_naming_the_model():
    from bench.models.factory import build_model
    with pytest.raises(UserError, match=r"model bench.models.srd.SRDNet with stage_order='foo': stage_order must be"):
        build_model({"_target_": "bench.models.srd.SRDNet", "stage_order": "foo"}, 2)


def test_a_stage_whose_loss_weights_are_all_zero_is_off_not_a_bad_value(tmp_path):
    cfg = compose_experiment("smoke", "preset=smoke", f"runs_dir={tmp_path}/runs",
                             "train.loss.intermediate={edge:0,temporal:0,spatial:0,perceptual:0}")
    assert make_context(cfg).train.loss["intermediate"]["spatial"] == 0


def test_run_from_another_folder_is_one_line_unless_every_path_is_given(tmp_path):
    """From elsewhere the default data/, runs/ and results/ would be new folders there: the committed
    archive unread, everything rendered and trained again. Refused before anything is written."""
    from bench.cli import working_dir_problem
    said = working_dir_problem(["+experiment=sota"], cwd=tmp_path)
    assert said and f"cd {REPO}" in said and "data_dir=... runs_dir=... results_dir=..." in said
    assert "results_dir=..." not in working_dir_problem(["results_dir=/x", "+experiment=sota"], cwd=tmp_path)
    assert working_dir_problem(["data_dir=/d", "runs_dir=/r", "++results_dir=/x"], cwd=tmp_path) is None
    assert working_dir_problem(["+experiment=sota"], cwd=REPO) is None
    assert working_dir_problem(["--cfg", "job"], cwd=tmp_path) is None and working_dir_problem(["-c", "job"], cwd=tmp_path) is None
    out = bench("+experiment=sota", cwd=tmp_path, timeout=120)
    assert out.returncode == 2 and "is not the project's" in out.stderr and "Traceback" not in out.stderr
    assert not list(tmp_path.iterdir())


def test_an_unwritable_hydra_dir_is_one_line_and_nothing_is_created(tmp_path):
    from bench.cli import hydra_dir_problem
    said = hydra_dir_problem(["hydra.run.dir=/proc/x/y"])
    assert said.startswith("hydra.run.dir=/proc/x/y: nothing can be written in /proc (") and said.endswith(
        "), so Hydra cannot write its log there; set hydra.run.dir=... to a writable place")
    assert hydra_dir_problem(["hydra.sweep.dir=/proc/y"]) is None                # used only with -m
    assert "hydra.sweep.dir=/proc/y: nothing can be written in /proc" in hydra_dir_problem(["-m", "+experiment=sota", "hydra.sweep.dir=/proc/y"])
    assert hydra_dir_problem(["hydra.run.dir=${runs_dir}/x"]) is None           # Hydra's to resolve
    assert hydra_dir_problem([f"hydra.run.dir='{tmp_path}/a b/c'"]) is None     # quoted as Hydra takes it
    assert not list(tmp_path.iterdir())


SCRIPTS = sorted(p.name for p in (REPO / "scripts").glob("*.py"))



@pytest.mark.parametrize("script", SCRIPTS)
def test_every_script_answers_help(script):
    said = python_process(f"scripts/{script}", "--help", env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=120)
    assert said.returncode == 0 and "Traceback" not in said.stderr and "usage" in said.stdout.lower(), \
        said.stdout[-500:] + said.stderr[-1500:]


def test_the_regeneration_check_takes_every_paper_table_and_table_study_with_the_seeds_their_captions_name(tmp_path):
    """scripts/regenerates_from_archive.py checks the paper tables `all` runs and the studies of kind table
    (not the verdicts or stability studies, which read other tables or compute cases), each with the
    seeds its committed caption names (a study run on seed 0 alone is checked as it ran)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("regenerates", REPO / "scripts" / "regenerates_from_archive.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.kind("studies/lr_range_ssim") == "lr_range" and script.kind("studies/fireflies_verdicts") == "claims"
    tables = script.committed_tables("cpu")
    assert {"sota", "perceptual", "studies/fireflies", "studies/domain"} <= set(tables)
    assert not {"stability", "macs", "studies/fireflies_verdicts", "studies/fireflies_stability"} & set(tables)
    (tmp_path / "table.md").write_text("A study. Preset cpu, split val, seeds [0, 2] (mean +- std over seeds).\n")
    assert script.recorded_seeds(tmp_path) == ["seeds=[0,2]"]
    (tmp_path / "table.md").write_text("A table with no seeds named.\n")
    assert script.recorded_seeds(tmp_path) == []

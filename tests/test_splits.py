"""The frozen test split: the paper's tables and the claims report it where the preset's data has one
(cpu), tuning experiments read val and refuse test, and a split's tables never land on another's."""
import json
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from bench import runs
from bench.cli import CONF_DIR, apply_pin, apply_split, make_context
from bench.errors import UserError
from bench.experiments import claims
from bench.experiments.context import split_note, working_split
from conftest import bench_here, smoke_context

REPO = Path(__file__).resolve().parent.parent


def composed(*overrides, group="experiment", name="sota"):
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=[f"+{group}={name}", *overrides])
    apply_pin(cfg)
    apply_split(cfg)
    return cfg


def test_the_cpu_tables_report_test_and_val_goes_beside_them_with_the_archive_where_it_was():
    cfg = composed("preset=cpu")
    assert cfg.eval.split == "test" and cfg.results_dir == "results/cpu"
    val = composed("preset=cpu", "eval.split=val")
    assert val.eval.split == "val" and val.results_dir == "results/cpu/val" and val.runs_archive == "results/cpu/runs"
    assert make_context(val).eval.split == "val"


def test_a_split_the_data_lacks_is_one_line_unless_the_frames_are_yours():
    with pytest.raises(UserError, match="eval.split=nosuch: the cpu preset's data has no such split; it has train, val"):
        composed("preset=cpu", "eval.split=nosuch")
    assert composed("preset=cpu", "eval.split=holdout", "eval.data_dir=/mine").eval.split == "holdout"


def test_your_frames_are_scored_with_the_committed_archive_wherever_results_dir_points():
    """eval.data_dir archives nothing and trains nothing: its models come from the preset's committed
    archive, also when results_dir is elsewhere (README's command), unless runs_archive is given."""
    cfg = composed("preset=cpu", "eval.split=holdout", "eval.data_dir=/mine", "results_dir=/tmp/mine")
    assert Path(cfg.runs_archive) == REPO / "results" / "cpu" / "runs" and cfg.results_dir == "/tmp/mine"
    given = composed("preset=cpu", "eval.data_dir=/mine", "results_dir=/tmp/mine", "runs_archive=/tmp/store")
    assert given.runs_archive == "/tmp/store"
    trained_on_yours = composed("preset=cpu", "render_data=false", "data_dir=/mine", "results_dir=/tmp/mine")
    assert trained_on_yours.runs_archive == "/tmp/mine/runs"  # its trainings are archived with its tables


@pytest.mark.parametrize("preset", ["smoke", "gpu"])
def test_a_preset_without_a_test_split_reports_val(preset):
    cfg = composed(f"preset={preset}")
    assert cfg.eval.split == "val" and cfg.results_dir == f"results/{preset}"


@pytest.mark.parametrize("group, name", [("experiment", "lr_range"), ("study", "dark_bias"), ("study", "lr_range_ssim"),
                                         ("study", "domain")])
def test_what_tunes_reads_val_at_cpu_and_refuses_test(group, name):
    cfg = composed("preset=cpu", group=group, name=name)
    assert cfg.eval.split == "val" and not cfg.results_dir.endswith("/val")   # val is its own split
    with pytest.raises(UserError, match="frozen"):
        composed("preset=cpu", "eval.split=test", group=group, name=name)


def test_a_tuning_command_on_test_is_one_line_and_exit_2_before_anything_runs(tmp_path):
    out = bench_here("+experiment=lr_range", "preset=cpu", "eval.split=test", f"runs_dir={tmp_path / 'runs'}",
                     f"data_dir={tmp_path / 'data'}")
    assert out.returncode == 2 and "frozen" in out.stderr and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and not (tmp_path / "data").exists()


def test_learning_curves_and_captions_never_lean_on_test():
    ctx = smoke_context()
    test = ctx.__class__(**{**ctx.__dict__, "eval": ctx.eval.__class__(**{**ctx.eval.__dict__, "split": "test"}),
                            "data_spec": {**ctx.data_spec, "splits": {**ctx.data_spec["splits"], "test": {}}}})
    assert working_split(test) == "val" and working_split(ctx) == "val"
    assert "frozen" in split_note(test, "test") and "the one to quote" in split_note(test, "val")
    assert "no test split" in split_note(ctx, "val")


@pytest.mark.parametrize("asked, in_split, scored", [(4, 2, [0, 1]), (4, 10, [0, 3, 6, 9]), (1, 10, [0]),
                                                     (3, 3, [0, 1, 2])])
def test_the_learning_curve_scores_the_sequences_it_asks_for_spread_over_the_working_split(
        monkeypatch, asked, in_split, scored):
    """train.val_sequences=4 on a val split of 2 scored only its first (the spread divided by 3, not 1)."""
    from bench.experiments import training
    seen = []
    monkeypatch.setattr(training, "dataset", lambda ctx, split, task, training: list(range(in_split)))
    monkeypatch.setattr(training, "evaluate", lambda model, subset, task, **_: (
        seen.append(list(subset)), {"relMSE": 0.0, "PSNR": 0.0, "SSIM": 0.0}))
    training.validation(smoke_context(), None, asked)(model=None)
    assert seen == [scored]


def test_claims_never_mix_the_rows_of_two_splits(tmp_path):
    """A claims table at eval.split=test refuses an evaluation that scored val (a table left from before)."""
    ctx = smoke_context(runs_dir=tmp_path / "runs", runs_archive=None)
    ctx = ctx.__class__(**{**ctx.__dict__, "eval": ctx.eval.__class__(**{**ctx.eval.__dict__, "split": "test"})})
    run = tmp_path / "runs" / "eval" / "abc"
    run.mkdir(parents=True)
    (run / runs.RECORD).write_text(json.dumps({"hash": "abc", "kind": "eval", "status": "complete",
                                               "identity": {"split": "val"}, "metrics": {}}))
    pd.DataFrame({"sequence": ["a"], "frame": [0], "PSNR": [30.0], "SSIM": [0.9], "relMSE": [0.01]}).to_csv(
        run / "per_image.csv", index=False)
    with pytest.raises(UserError, match="scored split 'val'"):
        claims._per_sequence_means(ctx, "abc", {})


def test_a_tables_caption_names_rows_left_out_scored_with_rounded_weights_or_trained_by_older_code():
    from bench.experiments import table
    note = table._weights_note(["Ours", "EDSR", "Input bilinear"], [3, 1, 0], [3, 0, 0], seeds=3)
    assert "float16-rounded weights" in note and ": Ours, EDSR (1 of 3 seeds)." in note
    assert "reuse_stale=true" in note and "re-stamps them): Ours." in note
    assert table._weights_note(["Input bilinear"], [0], [0], seeds=3) == ""


def test_a_table_refuses_a_row_to_leave_out_or_a_paper_table_it_does_not_have_before_it_runs():
    from bench.experiments import table
    rows = [{"label": "Input bilinear", "model": "bilinear"}]
    with pytest.raises(UserError, match="experiment.leave_out: no row 'RAE'"):
        table.run(smoke_context(), "t", rows=rows, leave_out=["RAE"])
    with pytest.raises(UserError, match="experiment.paper_table='Table 5': expected auto, null or one of sr_denoise"):
        table.run(smoke_context(), "t", rows=rows, paper_table="Table 5")


class _Rendering(Exception):
    """Stops an experiment at its first render, once the splits it asked for are known."""


@pytest.mark.parametrize("name", ["stability", "lr_range"])
def test_an_experiment_that_only_trains_renders_train_and_val_never_test(name, tmp_path, monkeypatch):
    """At the cpu preset the test split's references are hours of rendering: stability and the range
    test train and read val, so they ask for those two splits only."""
    from bench.cli import run_experiment
    import bench.experiments.lr_range
    import bench.experiments.stability
    asked = []

    def ensure_data(ctx, passes, splits=None, scoring=False):
        asked.append(splits)
        raise _Rendering

    monkeypatch.setattr(getattr(bench.experiments, name), "ensure_data", ensure_data)
    cfg = composed("preset=cpu", f"data_dir={tmp_path / 'data'}", f"runs_dir={tmp_path / 'runs'}",
                   f"results_dir={tmp_path / 'results'}", name=name)
    with pytest.raises(_Rendering):
        run_experiment(cfg)
    assert asked == [{"train", "val"}]

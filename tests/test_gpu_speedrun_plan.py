"""scripts/gpu_speedrun_plan.py: its rates are the committed GPU records', its render projection agrees with
the render probe's own, it renders the splits a table renders, leaves out the rows the GPU job leaves out,
and its arithmetic is the formula. (Its power is bench.stats.power: tests/test_stats.py.)"""
from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

import gpu_speedrun_plan as plan  # noqa: E402

PROBE = REPO / "results/gpu/data/cuda-nvidia-h200-render-probe.md"
SPEED = REPO / "results/gpu/speed/cuda-nvidia-h200"
SIZE = "4x7 frames of 64x64 LR"   # the gpu preset's training batch


def test_the_render_projection_is_the_probes_own_for_the_splits_it_projected():
    """The probe projects each split of the preset it rendered (one process); the plan, reading the
    probe's record back, gives the same minutes; the passes' walls are the record's."""
    rates = plan.render_rates(PROBE)
    text = PROBE.read_text()
    assert rates["lr"] == (192, 128) and (rates["spp"], rates["ref_spp"]) == (8, 256)
    assert rates["walls"] == {"pass 1": 40.7, "pass 2": 23.6} and rates["workers"] == (4, 20.9)
    data = plan.composed("gpu", [])["data"]
    projected = re.findall(r"^- (\w+): \d+ sequences, \d+ frames at ref \d+ spp: about ([\d.]+) min$", text, re.M)
    assert [split for split, _ in projected] == ["train", "val", "generalization"]
    for split, minutes in projected:
        # the record prints minutes to 0.1 and each buffer's seconds to 0.001 (about 1% of the smallest)
        assert abs(plan.split_seconds(data, split, rates) / 60 - float(minutes)) <= 0.05 + 0.02 * float(minutes), split


def test_a_cold_several_process_pass_divides_the_render_where_the_preset_renders_with_as_many(tmp_path, monkeypatch):
    """The committed record's 4-process pass had the kernel cache warm: not used. A record whose pass 1 and
    pass 3 (the probe's own lines) both started from an empty kernel cache is, at the preset's `workers`;
    pass 3's workers see an empty HOME and the user's site-packages, and the environment is restored."""
    import os
    import site
    import gpu_render_probe as probe
    assert plan.render_rates(PROBE)["workers_cold"] is False
    seen = {}

    def build_dataset(root, spec, buffers, workers, **_):
        seen.update(home=os.environ["HOME"], userbase=os.environ["PYTHONUSERBASE"])
        (Path(os.environ["HOME"]) / ".drjit").mkdir()
        return [None] * 56
    monkeypatch.setattr(probe.datagen, "build_dataset", build_dataset)
    home = os.environ.get("HOME")
    first = [{"job": {"sequence": f"s{i}"}, "wall_s": 40.7 / 8, "records": [{"time_s": {"hr_ref_s": 1.0}}] * 7}
             for i in range(8)]
    probed = {"splits": {"train": {"sequences": 8}}}
    pass_3 = probe.concurrent_pass(tmp_path / "p3", probed, "train", 4, "cuda_ad_rgb", first)
    assert seen["home"] == str(tmp_path / "p3" / "home") and seen["userbase"] == site.getuserbase()
    assert os.environ.get("HOME") == home and "from an empty kernel cache" in pass_3
    pass_1 = probe.passes_section(first, first, 10, {}, cold=True)[-2]
    text = PROBE.read_text()
    text = re.sub(r"^- pass 1: .*$", pass_1, text, count=1, flags=re.M)
    text = re.sub(r"^- pass 3: .*$", pass_3.replace(re.search(r"([\d.]+) s wall", pass_3).group(0), "20.9 s wall"),
                  text, count=1, flags=re.M)
    cold = tmp_path / "probe.md"
    cold.write_text(text)
    rates = plan.render_rates(cold)
    assert rates["workers_cold"] is True and rates["workers"] == (4, 20.9) and rates["walls"]["pass 1"] == 40.7
    labels = ["EDSR", "RAE", "KPCN", "CFM", "Ours"]
    steps = {label: {"ms": 1.0, "compile_s": 0.0} for label in labels}
    learned = ["edsr", "rae", "kpcn", "cfm", "srd"]
    for workers, gain in ((4, 40.7 / 20.9), (2, 1.0)):
        cfg = plan.composed("gpu", ["+experiment=sota", f"workers={workers}"])
        render = [r for r in plan.plan(cfg, rates, steps, 1.0, 1.0, learned, []) if r["phase"] == "render"]
        assert [r["seconds"] for r in render] == pytest.approx(
            [plan.split_seconds(cfg["data"], split, rates) / gain for split in ("train", "val")])
        assert ("4 processes" in render[0]["source"]) == (workers == 4)
    cold.write_text(text.replace("s wall from an empty kernel cache; pass 2", "s wall from the kernel cache the host had; pass 2"))
    assert plan.render_rates(cold)["workers_cold"] is False   # pass 1 from the host's cache: the walls do not compare


def test_the_step_rates_are_the_speed_tables_rows_at_the_presets_widths_and_batch():
    rows = pd.read_csv(SPEED / "table.csv")
    ours = rows[(rows["section"] == "training step") & (rows["method"] == "Ours")].set_index("fast path")
    eager = plan.step_rates(SPEED, "gpu", SIZE, "fp32")
    graphed = plan.step_rates(SPEED, "gpu", SIZE, plan.PATHS["reduce-overhead"])
    inference = rows[(rows["section"] == "inference") & (rows["method"] == "Ours")]
    assert eager["Ours"] == {"ms": ours.loc["fp32", "ms"], "compile_s": 0.0,        # "960x540 -> 1920x1080":
                             "frame": {"gmac": inference["GMac"].iloc[0], "lr_hw": (540, 960)}}  # H, W
    assert graphed["Ours"]["ms"] == ours.loc[plan.PATHS["reduce-overhead"], "ms"]
    assert graphed["Ours"]["compile_s"] == float(
        re.search(r"\(compile\) (\d+) s", ours.loc[plan.PATHS["reduce-overhead"], "note"]).group(1))
    assert set(eager) == {"Ours", "EDSR", "RAE", "KPCN", "CFM", "3x3 conv stack (56 x 32 ch)"}
    assert "CFM" not in graphed                                            # not timed: PARTIAL
    assert plan.step_rates(SPEED, "gpu", "4x5 frames of 32x32 LR", "fp32") == {}   # another batch: no rate
    with pytest.raises(ValueError, match="not timed at preset cpu's widths"):
        plan.step_rates(SPEED, "cpu", SIZE, "fp32")


def test_a_model_configured_unlike_the_one_timed_has_no_rate():
    """A width set with --set changes the model the table's step would stand for: its frame's MACs differ
    from the inference row's, and its train row says so instead of using another model's step; a model
    the table has no inference row for cannot be checked, and is not rated either."""
    steps = plan.step_rates(SPEED, "gpu", SIZE, "fp32")
    learned = ["edsr", "rae", "kpcn", "cfm", "srd"]
    assert all(steps[label]["frame"] for label in ["EDSR", "RAE", "KPCN", "CFM", "Ours"])   # each one checked
    assert plan.models_not_timed(plan.composed("gpu", ["+experiment=sota"]), steps, learned) == {}
    cfg = plan.composed("gpu", ["+experiment=sota", "models.srd.channels=24"])
    not_timed = plan.models_not_timed(cfg, steps, learned)
    assert list(not_timed) == ["Ours"]
    assert re.fullmatch(r"its step was timed on a model of 267\.8 GMac a 960x540 frame; this configuration's is "
                        r"\d+\.\d", not_timed["Ours"])
    rows = plan.plan(cfg, plan.render_rates(PROBE), steps, 100.0, 40.0, learned, [], not_timed)
    (ours,) = [r for r in rows if r.get("label") == "Ours"]
    assert math.isnan(ours["seconds"]) and ours["what"] == f"Ours: {not_timed['Ours']}"
    unchecked = {**steps, "KPCN": {**steps["KPCN"], "frame": None}}
    assert plan.models_not_timed(plan.composed("gpu", ["+experiment=sota"]), unchecked, learned) == {
        "KPCN": "no inference row in the speed table to check the configured model against"}


def test_the_plan_renders_what_the_table_renders_and_is_steps_times_step_time_and_frames_times_scoring():
    """At the cpu preset (a frozen test split): the trainings render train and val (their curve's split,
    rendered whether or not a curve is scored), the table test; steps x step time x seeds, the curve's
    points every val_every steps and the last; evaluations x scored frames x scoring time."""
    cfg = plan.composed("cpu", ["+experiment=sota", "train.steps=30", "train.val_every=10", "train.val_sequences=2"])
    render = plan.render_rates(PROBE)
    labels = ["EDSR", "RAE", "KPCN", "CFM", "Ours"]
    steps = {label: {"ms": 10.0 * (i + 1), "compile_s": 5.0 * (label == "Ours")} for i, label in enumerate(labels)}
    learned, fixed = ["edsr", "rae", "kpcn", "cfm", "srd"], ["bilinear", "bicubic"]
    rows = plan.plan(cfg, render, steps, score_ms=100.0, curve_ms=40.0, learned=learned, fixed=fixed)
    data, seeds = cfg["data"], len(cfg["seeds"])
    assert [r["what"].split(":")[0] for r in rows if r["phase"] == "render"] == ["train", "val", "test"]
    assert [r["seconds"] for r in rows if r["phase"] == "render"] == [
        plan.split_seconds(data, split, render) for split in ("train", "val", "test")]
    val = data["splits"]["val"]   # its refined sequences render their references at their own spp
    plain = {**data, "splits": {"val": {k: v for k, v in val.items() if k != "sequence_ref_spp"}}}
    ref_s = (render["buffers"]["lr_ref_s"] + render["buffers"]["hr_ref_s"]) / render["ref_spp"]
    pixels = data["lr_width"] * data["lr_height"] / (192 * 128)
    extra = sum(data["seq_len"] * (spp - val["ref_spp"]) for spp in val["sequence_ref_spp"].values())
    assert plan.split_seconds(data, "val", render) - plan.split_seconds(plain, "val", render) == pytest.approx(
        pixels * extra * ref_s) and extra > 0
    curve_frames = 2 * data["seq_len"]
    train = [r for r in rows if r["phase"] == "train"]
    assert [r["what"].split(":")[0] for r in train] == labels
    for i, row in enumerate(train):   # curve points at steps 0 (before training), 10, 20 and 30, the last
        compile_s = 5.0 * (labels[i] == "Ours")
        assert row["seconds"] == pytest.approx(seeds * (30 * 10.0 * (i + 1) / 1000 + compile_s + 4 * curve_frames * 0.040))
    evaluate = [r for r in rows if r["phase"] == "evaluate"]
    frames = data["splits"]["test"]["sequences"] * data["seq_len"]
    assert evaluate[0]["seconds"] == pytest.approx((5 * seeds + 2) * frames * 0.1) and "test frames" in evaluate[0]["what"]
    no_curve = plan.plan(plan.composed("cpu", ["+experiment=sota", "train.steps=30", "train.val_sequences=0"]),
                         render, {k: v for k, v in steps.items() if k != "CFM"}, 100.0, 40.0, learned, fixed)
    assert [r["what"].split(":")[0] for r in no_curve if r["phase"] == "render"] == ["train", "val", "test"]
    assert [r["seconds"] for r in no_curve if r["phase"] == "train"][0] == pytest.approx(seeds * 30 * 10.0 / 1000)
    (cfm,) = [r for r in no_curve if r["what"].startswith("CFM")]
    assert math.isnan(cfm["seconds"]) and cfm["what"] == "CFM: no speed row for this path and batch"


def test_a_row_whose_package_is_missing_is_left_out_and_a_broken_model_is_an_error():
    cfg = plan.composed("smoke", ["+experiment=sota"])
    cfg["models"]["oidn_lr"] = {"_target_": "no_such_package.Denoiser"}   # as OIDN without pyoidn
    learned, fixed, left_out = plan.table_rows(cfg)
    assert learned == ["edsr", "rae", "kpcn", "cfm", "srd"] and "bilinear" in fixed and "oidn_lr" not in fixed
    assert list(left_out) == ["oidn_lr"] and "no_such_package" in left_out["oidn_lr"]
    cfg["experiment"]["leave_out"] = ["Input bicubic"]
    assert "bicubic" not in plan.table_rows(cfg)[1]
    cfg["models"]["oidn_lr"] = {"_target_": "baselines.no_such_module.Denoiser"}   # a typo in the project
    with pytest.raises(Exception, match="no_such_module"):
        plan.table_rows(cfg)


def test_the_script_prints_the_phases_the_total_and_the_power_and_names_what_it_could_not_rate(tmp_path):
    out = subprocess.run([sys.executable, "scripts/gpu_speedrun_plan.py", "--out", str(tmp_path / "plan.md"),
                          "--set", "data.lr_width=32", "data.lr_height=16", "train.compile=reduce-overhead",
                          "models.rae.width=40"],
                         cwd=REPO, capture_output=True, text=True, timeout=300, env={"PYTHONPATH": str(REPO),
                                                                                     "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert "| render | train: 100 sequences at ref 256 spp |" in out.stdout
    assert re.search(r"\| evaluate \| (17|19) evaluations x 140 val frames of 64x32 x \d+ ms", out.stdout)
    assert "| train | Ours: 3 x (2000 steps x 36.9 ms + compile 104 s + 21 curve points" in out.stdout
    assert "| train | CFM: no speed row for this path and batch | - | speed table |" in out.stdout
    assert re.search(r"\| train \| RAE: its step was timed on a model of 256\.4 GMac a 960x540 frame; this "
                     r"configuration's is \d+\.\d \| - \| speed table \|", out.stdout)  # another width: not RAE's step
    assert re.search(r"^total: \d+ s \([\d.]+ min\) against a budget of 780 s: (fits|over by \d+ s); without RAE, "
                     r"CFM: not rated \(the rows say why\)$", out.stdout, re.M)
    assert "(Dr.Jit's kernel cache warm on disk) took 20.9 s" in out.stdout and "x1.95 and x1.13); not used" in out.stdout
    assert re.search(r"power at 0.1 dB, 3 seeds x 20 val sequences, with the variance components of the \d+ claim "
                     r"pairs in results/cpu/claims/table.csv: median 0\.\d\d", out.stdout)
    assert (tmp_path / "plan.md").read_text() == out.stdout   # --out: the record is what it printed
    refused = subprocess.run([sys.executable, "scripts/gpu_speedrun_plan.py", "--set", "train.precision=bf16"],
                             cwd=REPO, capture_output=True, text=True, timeout=300, env={"PYTHONPATH": str(REPO)})
    assert refused.returncode == 2 and "no speed rows for train.precision=bf16" in refused.stderr

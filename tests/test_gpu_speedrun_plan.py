"""scripts/gpu_speedrun_plan.py: its rates are the committed GPU records', its render projection agrees with
the render probe's own, its power is the claims' test's rejection rate, and its arithmetic is the formula."""
from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

import gpu_speedrun_plan as plan  # noqa: E402

PROBE = REPO / "results/gpu/data/cuda-nvidia-h200-render-probe.md"
SPEED = REPO / "results/gpu/speed/cuda-nvidia-h200/table.csv"


def test_the_render_projection_is_the_probes_own_for_the_split_it_measured():
    """The probe projects each split of the preset it rendered (one process); the plan, reading the
    probe's record back, gives the same minutes, and the 4-process pass's gain is its wall-clock ratio."""
    rates = plan.render_rates(PROBE)
    text = PROBE.read_text()
    assert rates["lr"] == (192, 128) and (rates["spp"], rates["ref_spp"]) == (8, 256)
    spec = plan.composed("gpu", [])["data"]
    for split, minutes in re.findall(r"^- (\w+): \d+ sequences, \d+ frames at ref \d+ spp: about ([\d.]+) min$",
                                     text, re.M):
        seconds, how = plan.split_seconds(spec, split, rates, workers=1)
        # the record prints minutes to 0.1 and each buffer's seconds to 0.001 (about 1% of the smallest)
        assert abs(seconds / 60 - float(minutes)) <= 0.05 + 0.02 * float(minutes), split
        assert "processes" not in how
    seconds, how = plan.split_seconds(spec, "train", rates, workers=rates["workers"])
    assert rates["workers"] == 4 and how.endswith("(4 processes)")
    assert seconds == pytest.approx(plan.split_seconds(spec, "train", rates, 1)[0] / rates["workers_gain"])


def test_the_step_rates_are_the_speed_tables_rows():
    import pandas as pd
    rows = pd.read_csv(SPEED)
    ours = rows[(rows["section"] == "training step") & (rows["method"] == "Ours")].set_index("fast path")
    rates = plan.step_rates(SPEED)["Ours"]
    assert rates["eager_ms"] == ours.loc["fp32", "ms"] and rates["compiled_ms"] == ours.loc[plan.COMPILED, "ms"]
    assert rates["compile_s"] == float(re.search(r"\(compile\) (\d+) s", ours.loc[plan.COMPILED, "note"]).group(1))


def test_the_power_is_the_claims_tests_rejection_rate():
    """At no difference it is the test's level; at a difference, the rate at which bench.stats.compare
    rejects simulated designs with those variance components (within Monte Carlo error)."""
    from bench.stats import compare
    assert plan.power(0.0, 0.05, 0.3, 0.2, 3, 20) == pytest.approx(0.05, abs=1e-9)
    rng = np.random.default_rng(0)
    sd_seed, sd_sequence, sd_residual, seeds, sequences, diff = 0.0, 0.3, 0.2, 3, 20, 0.15
    n = 1500
    rejected = 0
    for _ in range(n):
        d = (diff + sd_seed * rng.standard_normal((seeds, 1)) + sd_sequence * rng.standard_normal((1, sequences))
             + sd_residual * rng.standard_normal((seeds, sequences)))
        rejected += compare(d).p < 0.05
    stated = plan.power(diff, sd_seed, sd_sequence, sd_residual, seeds, sequences)
    assert 0.3 < stated < 0.9
    assert rejected / n == pytest.approx(stated, abs=4 * math.sqrt(stated * (1 - stated) / n))


def test_the_plan_is_steps_times_step_time_and_frames_times_scoring():
    cfg = plan.composed("smoke", ["+experiment=sota", "train.steps=30", "train.val_every=10", "train.val_sequences=2"])
    render = plan.render_rates(PROBE)
    steps = {label: {"eager_ms": 10.0 * (i + 1), "compiled_ms": 1.0, "compile_s": 5.0}
             for i, label in enumerate(["EDSR", "RAE", "KPCN", "CFM", "Ours"])}
    rows = plan.plan(cfg, render, steps, score_ms=100.0, curve_ms=40.0)
    spec, seeds = cfg["data"], len(cfg["seeds"])
    curve_frames = min(2, spec["splits"]["val"]["sequences"]) * spec["seq_len"]
    train = [r for r in rows if r["phase"] == "train"]
    assert [r["what"].split(":")[0] for r in train] == ["EDSR", "RAE", "KPCN", "CFM", "Ours"]   # the learned rows
    for i, row in enumerate(train):   # curve points at steps 10, 20 and 30, the last
        assert row["seconds"] == pytest.approx(seeds * (30 * 10.0 * (i + 1) / 1000 + 3 * curve_frames * 0.040))
    split = "test" if "test" in spec["splits"] else "val"
    frames = spec["splits"][split]["sequences"] * spec["seq_len"]
    rows_total = len(cfg["experiment"]["rows"])
    evaluate = [r for r in rows if r["phase"] == "evaluate"]
    assert evaluate[0]["seconds"] == pytest.approx((5 * seeds + rows_total - 5) * frames * 0.1)
    graphed = plan.plan({**cfg, "train": {**cfg["train"], "compile": "reduce-overhead"}}, render, steps, 100.0, 40.0)
    assert [r["seconds"] for r in graphed if r["phase"] == "train"][0] == pytest.approx(
        seeds * (30 * 1.0 / 1000 + 5.0 + 3 * curve_frames * 0.040))
    assert {r["what"].split(":")[0] for r in rows if r["phase"] == "render"} == {"train", split} | {"val"}


def test_the_script_prints_the_phases_the_total_and_the_power(tmp_path):
    out = subprocess.run([sys.executable, "scripts/gpu_speedrun_plan.py", "--out", str(tmp_path / "plan.md"),
                          "--set", "data.lr_width=32", "data.lr_height=16", "train.val_sequences=0"],
                         cwd=REPO, capture_output=True, text=True, timeout=300, env={"PYTHONPATH": str(REPO),
                                                                                     "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert "| render | train: 100 sequences" in out.stdout and "| evaluate | 19 evaluations x 140 frames of 64x32" in out.stdout
    assert re.search(r"^total: \d+ s \([\d.]+ min\) against a budget of 780 s: (fits|over by \d+ s)$", out.stdout, re.M)
    assert re.search(r"power at 0.1 dB, 3 seeds x 20 val sequences, with the variance components of the \d+ claim "
                     r"pairs in results/cpu/claims/table.csv: median 0\.\d\d", out.stdout)
    assert (tmp_path / "plan.md").read_text() == out.stdout   # --out: the record is what it printed

"""`+experiment=time` (error against run time): the pure curve arithmetic on synthetic curves, and one tiny
end-to-end run at the smoke preset (one view, spp up to 4, three methods, a 4-step training)."""
import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from bench.cli import CONF_DIR, run_experiment
from bench.machine import device_tag
from bench.experiments.time_curves import (BRUTE_FORCE, brute_force_spp, equal_time_table, fit_curve, loglog_slope,
                                           pareto_front, reference_noise_slope, rising_steps, slope_ok, speedup_table)
from bench.experiments.timing import _reference_spp, hr_lr_ratio, paper_axis, paper_equal_time, render_table, speed_ms


# ---------------------------------------------------------------- pure functions

def test_slope_check_on_synthetic_curves():
    spp = [1, 2, 4, 8, 16, 32]
    assert loglog_slope(spp, [0.3 / k for k in spp]) == pytest.approx(-1.0)
    assert slope_ok(loglog_slope(spp, [0.3 / k for k in spp]))
    assert not slope_ok(loglog_slope(spp, [0.3 / math.sqrt(k) for k in spp]))  # -0.5: too flat
    assert not slope_ok(loglog_slope(spp, [0.3 / k ** 2 for k in spp]))        # -2: too steep
    flattened = reference_noise_slope(spp, 64)  # the reference's own noise flattens an exact 1/k law
    assert -1.0 < flattened < -0.7


def test_brute_force_spp_stops_below_the_reference():
    assert brute_force_spp(256) == [1, 2, 4, 8, 16, 32, 64, 128]
    assert brute_force_spp(256, cap=4) == [1, 2, 4]
    assert brute_force_spp(2) == [1]


def test_curves_recover_power_laws_in_each_metric_and_invert():
    times = [1.0, 2.0, 4.0, 8.0]
    rel = fit_curve(times, [0.3 / t for t in times], "relMSE")
    assert rel.slope == pytest.approx(-1.0)
    assert rel.time_for(0.1) == (pytest.approx(3.0), False)
    assert rel.at_time(16.0) == (pytest.approx(0.3 / 16), True)      # beyond the measured times: says so
    psnr = fit_curve(times, [20 + 10 * math.log10(t) for t in times], "PSNR")
    assert psnr.time_for(25.0) == (pytest.approx(10 ** 0.5), False)
    ssim = fit_curve(times, [1 - 0.5 / t for t in times], "SSIM")
    assert ssim.time_for(0.9)[0] == pytest.approx(5.0) and ssim.at_time(2.0)[0] == pytest.approx(0.75)
    flat = fit_curve(times, [0.2] * 4, "relMSE")                      # no progress: never reaches better
    assert flat.time_for(0.1) == (math.inf, True)


def test_a_noisy_longer_render_pulls_the_fit_and_is_not_dropped():
    times, errors = [1.0, 2.0, 4.0, 8.0], [1.0, 0.5, 0.9, 0.125]
    curve = fit_curve(times, errors, "relMSE")
    assert curve.slope == pytest.approx(np.polyfit(np.log(times), np.log(errors), 1)[0])
    assert -1.0 < curve.slope < -0.5                                  # flatter than without the 0.9 point


def test_rising_steps_are_paired_over_views_and_need_more_than_noise():
    def per_view(values):  # view -> relMSE at spp 1, 2, 4
        return pd.DataFrame([{"view": v, "spp": k, "relMSE": e} for v, errs in values.items()
                             for k, e in zip((1, 2, 4), errs)])
    assert rising_steps(per_view({"a": [1.0, 0.5, 0.6], "b": [2.0, 1.0, 1.1], "c": [0.4, 0.2, 0.25]})) == [(2, 4)]
    # one view rising (a firefly), the others falling: within noise
    assert rising_steps(per_view({"a": [1.0, 0.5, 0.9], "b": [2.0, 1.0, 0.5], "c": [0.4, 0.2, 0.1]})) == []


def _synthetic_table():
    """Path tracing with relMSE = 0.4 / t, PSNR = 20 + 10 log10 t, SSIM = 1 - 0.4 / t; one SRD method at
    LR 8 spp; one HR denoiser whose relMSE = 0.05 / t."""
    rows = [{"method": BRUTE_FORCE, "input": "HR", "spp": k, "total s": float(k), "relMSE": 0.4 / k,
             "PSNR": 20 + 10 * math.log10(k), "SSIM": 1 - 0.4 / k} for k in (1, 2, 4, 8, 16)]
    rows.append({"method": "SRD", "input": "LR", "spp": 8, "total s": 0.5, "relMSE": 0.05, "PSNR": 28.0,
                 "SSIM": 0.96})
    rows += [{"method": "HR denoiser", "input": "HR", "spp": k, "total s": 2.0 * k, "relMSE": 0.05 / (2 * k),
              "PSNR": 25 + 10 * math.log10(2 * k), "SSIM": 0.9} for k in (1, 2, 4)]
    return pd.DataFrame(rows)


def test_speedup_table_gives_equal_quality_in_relmse_psnr_and_ssim():
    speed = speedup_table(_synthetic_table(), 8).set_index("method")
    assert speed.loc["SRD", "speed-up at equal relMSE"] == pytest.approx(8.0 / 0.5)   # PT needs 8 s
    assert speed.loc["SRD", "speed-up at equal PSNR"] == pytest.approx(10 ** 0.8 / 0.5)
    assert speed.loc["SRD", "speed-up at equal SSIM"] == pytest.approx(10.0 / 0.5)
    assert speed.loc["SRD", "PT relMSE at equal time"] == pytest.approx(0.8)
    assert "relMSE" in speed.loc["SRD", "extrapolated"]                                # 0.5 s < PT's 1 s


def test_equal_time_table_reads_each_hr_denoiser_at_the_srd_methods_time():
    (row,) = equal_time_table(_synthetic_table(), 8).to_dict("records")
    assert row["SRD method"] == "SRD" and row["HR denoiser"] == "HR denoiser"
    assert row["denoiser relMSE"] == pytest.approx(0.05 / 0.5)                         # on its line at 0.5 s
    assert row["PSNR difference (dB)"] == pytest.approx(28.0 - (25 + 10 * math.log10(0.5)))
    assert row["extrapolated"] == "relMSE, PSNR"                                       # below its 2 s


def test_the_paper_axis_replaces_seconds_only_and_flags_verdicts_that_change_sign():
    cpu = _synthetic_table()
    cpu = cpu.assign(**{"LDR-FLIP": 0.1 + cpu["relMSE"], "HDR-FLIP": 0.2 + cpu["relMSE"]})  # scored with FLIP
    renders = render_table([{"input": res, "size": size, "spp": k, "wall_s": wall, "cpu_s": 2 * wall,
                             "render_threads": 2, "load_1min": 3.0}
                            for res, size, ks, per_spp in (("LR", "4x2", (8,), 0.01), ("HR", "8x4", (1, 2, 4, 8), 1.0))
                            for k in ks for wall in (per_spp * k, per_spp * k * 3)])   # median: 2 x the first
    assert renders.set_index(["input", "spp"]).loc[("HR", 2), "render s"] == pytest.approx(4.0)  # CPU s / threads
    assert hr_lr_ratio(renders, 8, "CPU s") == pytest.approx(100.0)
    networks = {"SRD": (10.0, "speed table"), "HR denoiser": (0.5, "measured here")}
    axis = paper_axis(cpu, renders, networks)
    assert set(axis["method"]) == {"SRD", "HR denoiser"}                                # path tracing is left out
    srd = axis[axis["method"] == "SRD"].iloc[0]
    assert srd["total s"] == pytest.approx(0.16 + 10.0) and srd["PSNR"] == 28.0         # quality as it was
    assert srd["HDR-FLIP"] == pytest.approx(0.25) and srd["LDR-FLIP"] == pytest.approx(0.15)
    (row,) = paper_equal_time(axis, cpu, 8).to_dict("records")
    assert math.isfinite(row["HDR-FLIP difference"])                                  # FLIP's verdict too
    # cpu-size axis: SRD (0.5 s) ahead of the denoiser read at 0.5 s; here the SRD network is slow (10.16 s)
    assert row["PSNR difference, cpu-size axis (dB)"] > 0 > row["PSNR difference (dB)"]
    assert row["sign differs from cpu-size axis"] == "yes"
    assert math.isfinite(row["PSNR difference, wall axis (dB)"])


def test_network_times_come_from_the_speed_table_at_these_sizes_only():
    speed = pd.DataFrame([
        {"section": "inference", "method": "Ours", "fast path": "fp32", "size": "960x540 -> 1920x1080", "per": "frame", "ms": 2000.0},
        {"section": "inference", "method": "Ours", "fast path": "channels_last", "size": "960x540 -> 1920x1080", "per": "frame", "ms": 1500.0},
        {"section": "reference", "method": "OIDN (albedo + normal)", "fast path": "its own (fp32)", "size": "1920x1080", "per": "frame", "ms": 3000.0}])
    sizes = ((960, 540), (1920, 1080))
    assert speed_ms(speed, {"model": "srd", "task": "srd"}, *sizes) == 2000.0            # the fp32 row, as timed here
    assert speed_ms(speed, {"model": "oidn_hr", "task": "denoise"}, *sizes) == 3000.0
    assert speed_ms(speed, {"model": "rae", "task": "denoise"}, *sizes) is None          # not in it: measured
    assert speed_ms(speed, {"model": "srd", "task": "srd"}, (96, 64), (192, 128)) is None
    assert speed_ms(None, {"model": "srd", "task": "srd"}, *sizes) is None


def test_pareto_front():
    times, errors = [1, 2, 3, 4, 2], [1.0, 0.5, 0.6, 0.1, 0.5]
    assert pareto_front(times, errors).tolist() == [True, True, False, True, True]


# ---------------------------------------------------------------- end to end at the smoke preset

@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("time")
    overrides = [
        "+experiment=time", "preset=smoke", f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}",
        f"data_dir={root / 'data'}", "progress=false", "workers=1", "train.steps=4", "train.checkpoint_every=2",
        "data.ref_spp=16", "data.splits.train.sequences=2", "data.splits.val.sequences=1",
        "data.splits.generalization.sequences=0", "experiment.views=1", "experiment.max_spp=4",
        "experiment.lr_spp=[1,4]", "experiment.hr_spp=[1,4]", "experiment.operating_spp=4", "experiment.repeats=2",
        "experiment.paper_resolution.lr_size=[16,8]", "experiment.paper_resolution.hr_size=[32,16]",
        "experiment.paper_resolution.frames=1", "experiment.paper_resolution.repeats=1",
        "experiment.methods=[{label:Ours,model:srd},{label:Bilinear,model:bilinear},"
        "{label:OIDN HR,model:oidn_hr,task:denoise}]"]
    return overrides, root


def run_time(overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        run_experiment(compose("config", overrides=overrides))


def test_time_end_to_end_then_reuses_its_renders(tiny, caplog):
    overrides, root = tiny
    out = root / "results" / "time"
    with caplog.at_level("INFO", logger="bench"):
        run_time(overrides)  # no recorded training run and train_missing=false: Ours is skipped
    assert "Ours skipped" in caplog.text
    table = pd.read_csv(out / "table.csv")
    assert set(table["method"]) == {BRUTE_FORCE, "Bilinear", "OIDN HR"}
    assert "Skipped" in (out / "table.md").read_text() and "Ours" in (out / "table.md").read_text()
    assert "spp in the network domain " in (out / "table.md").read_text()  # the domain its networks trained in

    caplog.clear()
    with caplog.at_level("INFO", logger="bench"):
        run_time(overrides + ["experiment.train_missing=true"])
    assert "time: 15 of 15 renders reused" in caplog.text  # 3 brute force + 2 spp x 3 frames x (LR, HR)
    table = pd.read_csv(out / "table.csv")
    assert list(dict.fromkeys(table["method"])) == [BRUTE_FORCE, "Ours", "Bilinear", "OIDN HR"]
    assert table.loc[table["method"] == BRUTE_FORCE, "spp"].tolist() == [1, 2, 4]
    assert table.loc[table["method"] == "Ours", "spp"].tolist() == [1, 4]
    numbers = table[["render s", "network s", "total s", "relMSE", "PSNR", "SSIM"]]
    assert np.isfinite(numbers.to_numpy()).all() and (table["render s"] > 0).all()
    assert np.allclose(table["total s"], table["render s"] + table["network s"])
    assert table["Pareto"].eq("yes").any()
    for name in ("table", "speedup"):
        for ext in ("csv", "md", "tex"):
            assert (out / f"{name}.{ext}").stat().st_size > 0
    assert (out / "error_vs_time.png").stat().st_size > 0
    speed = pd.read_csv(out / "speedup.csv")
    assert list(speed["method"]) == ["Ours", "Bilinear", "OIDN HR"] and (speed["spp"] == 4).all()
    assert (speed["speed-up at equal relMSE"] > 0).all() and (speed["speed-up at equal PSNR"] > 0).all()
    assert "log-log slope" in (out / "table.md").read_text() and "not checked (one view)" in (out / "table.md").read_text()
    assert {"relMSE se", "PSNR se", "speed-up (PSNR)"} <= set(table.columns)
    assert (out / "equal_time.csv").exists()
    for name in ("render_16p", "axis_16p", "equal_time_16p"):
        for ext in ("csv", "md", "tex"):
            assert (out / f"{name}.{ext}").stat().st_size > 0


def test_paper_resolution_alone_reuses_its_renders_and_the_speed_table(tiny, caplog):
    overrides, root = tiny
    out = root / "results" / "time"
    before = (out / "table.csv").read_text()
    speed_dir = root / "results" / "speed" / device_tag("cpu")
    speed_dir.mkdir(parents=True)
    pd.DataFrame([{"section": "inference", "method": "Ours", "fast path": "fp32", "size": "16x8 -> 32x16",
                   "per": "frame", "ms": 250.0}]).to_csv(speed_dir / "table.csv", index=False)
    with caplog.at_level("INFO", logger="bench"):
        run_time(overrides + ["experiment.paper_resolution.only=true"])
    assert "3 renders at 16x8 (LR) and 32x16 (HR)" in caplog.text             # said before rendering
    assert "3 of 3 paper-resolution renders reused" in caplog.text           # 1 frame x (LR 4 spp, HR 1 and 4)
    assert (out / "table.csv").read_text() == before                          # the cpu-size table left as recorded
    renders = pd.read_csv(out / "render_16p.csv")
    assert renders[["input", "spp"]].values.tolist() == [["LR", 4], ["HR", 1], ["HR", 4]]
    assert (renders["CPU s"] > 0).all() and (renders["wall s"] > 0).all()
    axis = pd.read_csv(out / "axis_16p.csv").set_index("method")
    assert axis.loc["Ours", "network s"] == pytest.approx(0.25)
    assert axis.loc["Ours", "network from"].startswith("speed table")
    assert axis.loc["Bilinear", "network from"].startswith("measured here")
    quality = pd.read_csv(out / "table.csv").set_index(["method", "spp"])
    assert axis.loc["Ours", "PSNR"] == pytest.approx(quality.loc[("Ours", 4), "PSNR"])
    equal = pd.read_csv(out / "equal_time_16p.csv")
    assert set(equal["SRD method"]) == {"Ours", "Bilinear"} and set(equal["HR denoiser"]) == {"OIDN HR"}
    caption = (out / "equal_time_16p.md").read_text()
    assert "quality axis" in caption and "still the cpu preset's" in caption and "CPU time" in caption
    assert "HR/LR render time at 4 spp" in (out / "render_16p.md").read_text()


def test_renders_recorded_under_the_old_run_kind_are_adopted(tmp_path):
    from bench.experiments.timing import RUN_KIND, _move_legacy_render_runs
    (tmp_path / "timing" / "abc").mkdir(parents=True)
    (tmp_path / "timing" / "abc" / "run.json").write_text("{}")
    _move_legacy_render_runs(tmp_path)
    assert (tmp_path / RUN_KIND / "abc" / "run.json").exists() and not (tmp_path / "timing").exists()
    _move_legacy_render_runs(tmp_path)  # nothing left to move: a no-op
    assert (tmp_path / RUN_KIND / "abc" / "run.json").exists()


def test_brute_force_stops_below_the_fewest_sample_reference_of_the_views():
    """Views whose references have different spp (refined sequences): no view may score a brute-force render
    with as many samples as its own reference, so the least-sampled reference decides, whichever view is first."""
    views = [SimpleNamespace(frames=[{"ref_spp": n}]) for n in (4096, 8192, 1024, 2048)]
    assert _reference_spp(views) == 1024 and brute_force_spp(_reference_spp(views))[-1] == 512

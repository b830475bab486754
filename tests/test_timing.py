"""`+experiment=time` (error against run time): the pure curve arithmetic on synthetic curves, and one tiny
end-to-end run at the smoke preset (one view, spp up to 4, three methods, a 4-step training)."""
import math

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from bench.cli import CONF_DIR, run_experiment
from bench.experiments.timing import (BRUTE_FORCE, brute_force_spp, equal_quality_time, equal_time_error,
                                      loglog_slope, pareto_front, reference_noise_slope, slope_ok)


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


def test_equal_quality_and_equal_time_interpolate_log_log():
    times, errors = [1.0, 2.0, 4.0, 8.0], [1.0, 0.5, 0.25, 0.125]  # error = 1 / time
    seconds, extrapolated = equal_quality_time(times, errors, 0.3)
    assert seconds == pytest.approx(1 / 0.3) and not extrapolated  # exact on a power law
    error, extrapolated = equal_time_error(times, errors, 3.0)
    assert error == pytest.approx(1 / 3) and not extrapolated
    seconds, extrapolated = equal_quality_time(times, errors, 0.05)  # better than the longest render:
    assert seconds == pytest.approx(20.0) and extrapolated         # continued by the 1/spp law
    seconds, extrapolated = equal_quality_time(times, errors, 2.0)   # worse than the quickest render
    assert seconds == pytest.approx(0.5) and extrapolated
    error, extrapolated = equal_time_error(times, errors, 16.0)
    assert error == pytest.approx(1 / 16) and extrapolated
    seconds, _ = equal_quality_time(times[::-1], errors[::-1], 0.25)  # order of the points does not matter
    assert seconds == pytest.approx(4.0)


def test_a_noisy_longer_render_does_not_bend_the_curve_back():
    """Fireflies can make a longer render score worse; the time to reach an error is the first time it
    is reached."""
    times, errors = [1.0, 2.0, 4.0, 8.0], [1.0, 0.5, 0.9, 0.125]
    seconds, _ = equal_quality_time(times, errors, 0.25)
    assert 2.0 < seconds < 8.0
    assert seconds == pytest.approx(2 * (8 / 2) ** (math.log(2) / math.log(4)))  # on the 2 s -> 8 s segment


def test_renders_that_never_improve_keep_the_curve_flat_up_to_the_longest():
    """No progress was measured after 2 s, so none is assumed until the last measured 8 s."""
    times, errors = [1.0, 2.0, 4.0, 8.0], [1.0, 0.5, 0.6, 0.7]
    assert equal_time_error(times, errors, 4.0) == (pytest.approx(0.5), False)
    assert equal_quality_time(times, errors, 0.5) == (pytest.approx(2.0), False)
    seconds, extrapolated = equal_quality_time(times, errors, 0.4)
    assert seconds == pytest.approx(10.0) and extrapolated


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
    assert (speed["speed-up at equal relMSE"] > 0).all()
    assert "log-log slope" in (out / "table.md").read_text()


def test_renders_recorded_under_the_old_run_kind_are_adopted(tmp_path):
    from bench.experiments.timing import RUN_KIND, _adopt_legacy_runs
    (tmp_path / "timing" / "abc").mkdir(parents=True)
    (tmp_path / "timing" / "abc" / "run.json").write_text("{}")
    _adopt_legacy_runs(tmp_path)
    assert (tmp_path / RUN_KIND / "abc" / "run.json").exists() and not (tmp_path / "timing").exists()
    _adopt_legacy_runs(tmp_path)  # nothing left to move: a no-op
    assert (tmp_path / RUN_KIND / "abc" / "run.json").exists()

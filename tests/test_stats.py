"""bench/stats.py: the paired seed x sequence comparison against scipy's t-tests in the cases it reduces
to, a hand-worked two-way example, Holm against a hand example, and its calibration on synthetic data with
the claims table's design."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sp

from bench import stats

ROOT = Path(__file__).resolve().parent.parent


def test_one_seed_is_the_paired_t_test_over_sequences():
    rng = np.random.default_rng(1)
    better, worse = rng.normal(30, 3, 10), rng.normal(29.5, 3, 10)
    c = stats.compare(stats.paired_differences(better, worse))
    ref = sp.ttest_rel(better, worse)
    assert c.diff / c.se == pytest.approx(ref.statistic) and c.p == pytest.approx(ref.pvalue)
    assert c.df == pytest.approx(ref.df)
    assert (c.low, c.high) == pytest.approx(tuple(ref.confidence_interval(0.95)))


def test_one_sequence_is_the_one_sample_t_test_over_seeds():
    d = np.array([[0.3], [0.1], [0.5], [0.2]])
    c, ref = stats.compare(d), sp.ttest_1samp(d[:, 0], 0.0)
    assert c.p == pytest.approx(ref.pvalue) and c.df == 3
    assert (c.low, c.high) == pytest.approx(tuple(ref.confidence_interval(0.95)))


# zero row and column means: adds residual spread and nothing to the seed or sequence means
CHECKER = np.array([[1.0, -1.0, 1.0, -1.0], [-1.0, 1.0, -1.0, 1.0], [0.0, 0.0, 0.0, 0.0]])


def test_a_lost_sequence_component_leaves_the_t_test_over_seed_means():
    d = np.array([[0.5], [1.5], [3.5]]) + CHECKER    # MS_sequence = 0 < MS_residual: truncated
    c = stats.compare(d)
    assert stats.variance_components(stats.mean_squares(d))["sequence"] == 0
    assert c.p == pytest.approx(sp.ttest_1samp(d.mean(axis=1), 0.0).pvalue) and c.df == pytest.approx(2)


def test_a_lost_seed_component_leaves_the_t_test_over_sequence_means():
    d = np.array([[0.2, 3.0, 1.5, -0.5]]) + CHECKER  # MS_seed = 0 < MS_residual: truncated
    c = stats.compare(d)
    assert stats.variance_components(stats.mean_squares(d))["seed"] == 0
    assert c.p == pytest.approx(sp.ttest_1samp(d.mean(axis=0), 0.0).pvalue) and c.df == pytest.approx(3)


def test_both_components_kept_by_hand():
    """d = [[0,2,4],[2,3,7]]: seed means 2, 4; sequence means 1, 2.5, 5.5; grand 3. MS_seed = 3*2/1 = 6,
    MS_sequence = 2*10.5/2 = 10.5, residuals +-0.5 (four of them) so MS_residual = 1/2 = 0.5.
    Var = (6 + 10.5 - 0.5)/6. Satterthwaite: df = 16^2 / (6^2/1 + 10.5^2/2 + 0.5^2/2) = 256/91.25 = 2.8,
    capped at the largest term's (MS_sequence, 2)."""
    d = np.array([[0.0, 2.0, 4.0], [2.0, 3.0, 7.0]])
    ms = stats.mean_squares(d)
    assert (ms.seed, ms.sequence, ms.residual) == pytest.approx((6.0, 10.5, 0.5))
    c = stats.compare(d)
    se, df = np.sqrt(16 / 6), 2.0
    assert (c.diff, c.se, c.df) == pytest.approx((3.0, se, df))
    assert c.p == pytest.approx(2 * sp.t.sf(3.0 / se, df))
    assert c.high - c.diff == pytest.approx(sp.t.ppf(0.975, df) * se)


def test_paired_differences_broadcast_a_deterministic_row_and_pair_seeds_by_index():
    three, one = np.arange(12.0).reshape(3, 4), np.ones((1, 4))
    assert np.array_equal(stats.paired_differences(three, one), three - 1)
    assert np.array_equal(stats.paired_differences(one, three), 1 - three)
    assert stats.paired_differences(three, three[:2] + 1).shape == (2, 4)   # first two seeds paired
    with pytest.raises(ValueError, match="sequences"):
        stats.paired_differences(three, np.ones((3, 5)))


def test_no_spread_at_all():
    c = stats.compare(np.full((3, 4), 0.25))   # exact in binary: no rounding spread
    assert c.se == 0 and c.p == 0 and c.low == c.high == 0.25
    assert stats.compare(np.zeros((3, 4))).p == 1


def test_holm_by_hand():
    """Sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1: 0.02, 0.03, 0.06, 0.04 -> running max 0.06."""
    assert stats.holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    adjusted = stats.holm([0.01, np.nan, 0.04, 0.6])   # NaN: not a test, m = 3
    assert np.isnan(adjusted[1]) and adjusted[[0, 2, 3]] == pytest.approx([0.03, 0.08, 0.6])


def test_verdict():
    assert stats.verdict(0.1, 0.01) == "holds" and stats.verdict(-0.1, 0.049) == "reversed"
    assert stats.verdict(0.1, 0.05) == stats.verdict(0.1, float("nan")) == "within noise"


# ------------------------------------------------------------------------------------------------------
# Calibration on synthetic data with the claims table's design: 3 seeds per row, 20 sequences (the
# frozen test split the claims report; val, beside it, has 10: "val" designs). The
# standard deviations are per row and about what the claims CSV's variance-component columns show for
# the difference of two rows (PSNR sd seed ~0.1, sd sequence ~0.3, sd residual ~0.2 dB; a difference has
# twice a row's variance): seed (training noise), sequence x row interaction (a row's own scene
# preferences), residual (seed x sequence). A common scene effect (5 dB) cancels in the pairing.
SEEDS, ALPHA = 3, 0.05
TYPICAL = {"seed": 0.07, "interaction": 0.21, "residual": 0.14, "sequences": 20}
DESIGNS = {
    "typical": TYPICAL,
    "seed-dominated": {"seed": 0.2, "interaction": 0.05, "residual": 0.1, "sequences": 20},
    "heavy-tailed scenes": {**TYPICAL, "heavy": True},   # one scene far off (dining): t, 3 df
    "worse row deterministic": {**TYPICAL, "deterministic": True},
    "val": {**TYPICAL, "sequences": 10},
    "val, heavy-tailed scenes": {**TYPICAL, "sequences": 10, "heavy": True},
}


def _row(rng, scene, mean, design, seeds):
    n = design["sequences"]
    draw = rng.standard_t(3, n) / np.sqrt(3) if design.get("heavy") else rng.normal(size=n)
    values = mean + scene + design["interaction"] * draw
    if seeds == 1:   # a deterministic method: one evaluation, no training noise
        return values[None, :]
    return values + rng.normal(0, design["seed"], (seeds, 1)) + rng.normal(0, design["residual"], (seeds, n))


def rejection_rate(design: dict, effect: float, n: int, seed: int = 0) -> float:
    """Fraction of n synthetic pairs (true difference `effect`) that compare() calls significant."""
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(n):
        scene = rng.normal(0, 5, design["sequences"])
        better = _row(rng, scene, effect, design, SEEDS)
        worse = _row(rng, scene, 0.0, design, 1 if design.get("deterministic") else SEEDS)
        hits += stats.compare(stats.paired_differences(better, worse)).p < ALPHA
    return hits / n


@pytest.mark.parametrize("name", DESIGNS)
def test_a_null_difference_is_called_at_most_five_percent_of_the_time(name):
    n = 3000
    rate = rejection_rate(DESIGNS[name], 0.0, n)
    assert rate <= ALPHA + 3 * np.sqrt(ALPHA * (1 - ALPHA) / n)   # + three Monte Carlo SE (0.012)


def smallest_claimed_difference() -> float:
    """The smallest |PSNR diff| of a pair the committed claims table says holds (by either test)."""
    table = pd.read_csv(ROOT / "results" / "cpu" / "claims" / "table.csv")
    holds = (table["PSNR verdict"] == "holds") | (table["PSNR 2SE verdict"] == "holds")
    return float(table.loc[holds, "PSNR diff"].abs().min())


# Power found at that effect (0.166 dB, "IPT: CFM helps" by the 2 SE test, 3 seeds x 20 test sequences):
# about 32% (47% against a deterministic row); the design cannot resolve it (typical design at 0.1 dB:
# about 16%, 0.2 dB: 42%, 0.3 dB: 67%). More seeds are the fix. Stated here so a change to the method,
# the design or the table fails this test: a table scored again moves the effect, and this with it.
STATED_POWER = {"typical": 0.32, "worse row deterministic": 0.47}


@pytest.mark.parametrize("name", STATED_POWER)
def test_power_at_the_smallest_claimed_difference(name):
    n = 2000
    power = rejection_rate(DESIGNS[name], smallest_claimed_difference(), n, seed=1)
    assert power == pytest.approx(STATED_POWER[name], abs=3 * np.sqrt(0.25 / n))   # +- 0.034


def test_a_large_difference_is_found():
    assert rejection_rate(TYPICAL, 0.6, 500, seed=2) > 0.9


def test_power_is_the_rate_compare_calls_a_difference_and_the_paired_t_tests_power_with_one_seed():
    """stats.power simulates the design and asks compare(): at no difference it is the level; with one seed
    compare() is the paired t-test over sequences, whose power is the noncentral t's."""
    from scipy import stats as scipy_stats
    draws = 2000
    assert stats.power(0.0, 0.1, 0.3, 0.2, 3, 20, draws=draws) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / draws)
    sd, sequences, diff = np.hypot(0.3, 0.2), 20, 0.15   # one seed: sequence and residual add up
    critical = scipy_stats.t.ppf(0.975, sequences - 1)
    shift = diff * np.sqrt(sequences) / sd
    exact = scipy_stats.nct.sf(critical, sequences - 1, shift) + scipy_stats.nct.sf(critical, sequences - 1, -shift)
    simulated = stats.power(diff, 0.0, 0.3, 0.2, 1, sequences, draws=draws)
    assert 0.3 < exact < 0.9 and simulated == pytest.approx(exact, abs=3 * np.sqrt(exact * (1 - exact) / draws))

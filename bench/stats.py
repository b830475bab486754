"""Paired comparison of two rows over a crossed seed x sequence design, and Holm's correction.

A row of a table is a model trained with a few seeds (training noise) and scored on a set of sequences
(scene noise). The difference of two rows is taken per (seed, sequence), d[s, q], seeds paired by index
(the same seed draws the same data order), sequences paired by name; a deterministic row (one evaluation)
is broadcast against every seed of the other. d is modelled as a two-way random crossed design

    d[s, q] = delta + B[s] + A[q] + E[s, q],   B ~ (0, seed var), A ~ (0, sequence var), E ~ (0, residual var)

so the mean difference has variance  sequence var / Q + seed var / S + residual var / (S Q).  The
components come from the ANOVA mean squares (truncated at zero), its degrees of freedom from
Satterthwaite's approximation (capped at the df of the largest mean square), and the interval and
p-value from Student's t. With one seed this is the paired t-test over sequences; with one sequence, the
one-sample t-test over seeds. Pure: numpy and scipy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special


@dataclass(frozen=True)
class MeanSquares:
    """Two-way ANOVA without replication of d[s, q]; a mean square with 0 degrees of freedom is 0."""
    seed: float
    sequence: float
    residual: float
    df_seed: int
    df_sequence: int
    df_residual: int
    seeds: int
    sequences: int


@dataclass(frozen=True)
class Comparison:
    """The mean difference, its standard error, Satterthwaite df, a t interval and a two-sided p-value."""
    diff: float
    se: float
    df: float
    low: float
    high: float
    p: float


def paired_differences(better: np.ndarray, worse: np.ndarray) -> np.ndarray:
    """d[s, q] = better[s, q] - worse[s, q], each (seeds, sequences). A one-seed row is broadcast against
    the other's seeds; with two different seed counts the first seeds common to both are paired."""
    better, worse = np.atleast_2d(np.asarray(better, float)), np.atleast_2d(np.asarray(worse, float))
    if better.shape[1] != worse.shape[1]:
        raise ValueError(f"rows have {better.shape[1]} and {worse.shape[1]} sequences")
    if 1 not in (len(better), len(worse)):
        n = min(len(better), len(worse))
        better, worse = better[:n], worse[:n]
    return better - worse


def mean_squares(d: np.ndarray) -> MeanSquares:
    d = np.atleast_2d(np.asarray(d, float))
    s, q = d.shape
    seed_means, sequence_means, grand = d.mean(axis=1), d.mean(axis=0), d.mean()
    residual = d - seed_means[:, None] - sequence_means[None, :] + grand
    df_seed, df_sequence, df_residual = s - 1, q - 1, (s - 1) * (q - 1)

    def ms(sum_of_squares: float, df: int) -> float:
        return sum_of_squares / df if df > 0 else 0.0
    return MeanSquares(seed=ms(q * ((seed_means - grand) ** 2).sum(), df_seed),
                       sequence=ms(s * ((sequence_means - grand) ** 2).sum(), df_sequence),
                       residual=ms((residual ** 2).sum(), df_residual),
                       df_seed=df_seed, df_sequence=df_sequence, df_residual=df_residual, seeds=s, sequences=q)


def variance_components(ms: MeanSquares) -> dict[str, float]:
    """Seed, sequence and residual variance, the first two truncated at zero (a negative estimate means
    that source is lost in the residual noise)."""
    return {"seed": max(ms.seed - ms.residual, 0.0) / ms.sequences,
            "sequence": max(ms.sequence - ms.residual, 0.0) / ms.seeds,
            "residual": ms.residual}


def _variance_of_mean(ms: MeanSquares) -> tuple[float, float]:
    """Var(mean d) = sum_i c_i MS_i / (S Q) and its degrees of freedom. A truncated component drops its
    mean square, and the residual keeps what is left of the coefficient (1 - kept components): so
    both kept gives MS_seed + MS_sequence - MS_residual, one kept gives its own mean square alone.
    df: Satterthwaite's, capped at the df of the largest term. Why the cap: Satterthwaite's df is
    estimated from the same mean squares, so a chance-small MS_seed (2 df with 3 seeds) raises df just
    when the SE is too small; uncapped, a null difference was called 6.2% of the time at 5% where seeds
    dominate (tests/test_stats.py's seed-dominated design), capped 4.6%."""
    keep_seed = ms.df_seed > 0 and ms.seed > ms.residual
    keep_sequence = ms.df_sequence > 0 and ms.sequence > ms.residual
    terms = [(float(keep_seed), ms.seed, ms.df_seed), (float(keep_sequence), ms.sequence, ms.df_sequence),
             (1.0 - keep_seed - keep_sequence, ms.residual, ms.df_residual)]
    terms = [(c * m, df) for c, m, df in terms if c != 0 and df > 0]
    total = sum(cm for cm, _ in terms)
    denominator = sum(cm ** 2 / df for cm, df in terms)
    df = total ** 2 / denominator if denominator > 0 else float("nan")
    if terms:
        df = min(df, max(terms)[1])
    return total / (ms.seeds * ms.sequences), df


def compare(d: np.ndarray, level: float = 0.95) -> Comparison:
    """Mean of d[s, q] with its t interval at `level` and two-sided p-value against zero."""
    d = np.atleast_2d(np.asarray(d, float))
    diff = float(d.mean())
    variance, df = _variance_of_mean(mean_squares(d))
    if not variance > 0:   # no spread at all (or a single cell): nothing to test against
        known = variance == 0 and d.size > 1
        p = (0.0 if diff != 0 else 1.0) if known else float("nan")
        return Comparison(diff, 0.0 if known else float("nan"), float("nan"),
                          diff if known else float("nan"), diff if known else float("nan"), p)
    se = float(np.sqrt(variance))
    half = float(special.stdtrit(df, 0.5 + level / 2)) * se   # Student's t quantile and tail (the
    p = float(2 * special.stdtr(df, -abs(diff) / se))           # ufuncs: calibration calls this 10^4 times)
    return Comparison(diff, se, float(df), diff - half, diff + half, p)


def power(diff: float, sd_seed: float, sd_sequence: float, sd_residual: float, seeds: int, sequences: int,
          alpha: float = 0.05, draws: int = 500, seed: int = 0) -> float:
    """The rate at which `compare` calls a true mean difference `diff` significant (p < `alpha`, before
    Holm) over `draws` designs d[s, q] = diff + B[s] + A[q] + E[s, q] drawn with these standard deviations
    (the model above, normal): the test's power there, within about sqrt(power (1 - power) / draws)."""
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(draws):
        d = (diff + sd_seed * rng.standard_normal((seeds, 1)) + sd_sequence * rng.standard_normal((1, sequences))
             + sd_residual * rng.standard_normal((seeds, sequences)))
        hits += compare(d).p < alpha
    return hits / draws


def holm(p_values) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error), in the input order; NaN stays NaN and is
    not counted among the tests."""
    p = np.asarray(p_values, float)
    adjusted = np.full(p.shape, np.nan)
    tested = np.flatnonzero(~np.isnan(p))
    order = tested[np.argsort(p[tested], kind="stable")]
    m = len(order)
    steps = np.minimum(1.0, (m - np.arange(m)) * p[order])
    adjusted[order] = np.maximum.accumulate(steps)
    return adjusted


def verdict(diff: float, p: float, alpha: float = 0.05) -> str:
    """'holds' / 'reversed' when p < alpha (the sign of diff decides which), else 'within noise'."""
    if not p < alpha:
        return "within noise"
    return "holds" if diff > 0 else "reversed"

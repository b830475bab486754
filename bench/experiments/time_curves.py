"""The time table's curves and the tables derived from them (bench.experiments.timing measures the rows):
pure functions of measured (method, spp, seconds, metric) rows. A metric against total time is a straight
line in log time after its transform (`CURVE_SCALES`); path tracing's curves give each method's
equal-quality speed-up and path tracing's value at the method's time (`speedup_table`), and each
denoiser's own curve the paper's equal-time head-to-head (`equal_time_table`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

BRUTE_FORCE = "Path tracing (HR)"
EXPECTED_SLOPE = (-1.3, -0.7)               # MSE of a k-spp image falls as 1/k


def brute_force_spp(ref_spp: int, cap: int | None = None) -> list[int]:
    """1, 2, 4, ... up to half the reference's spp (the reference itself is ref_spp), at most `cap`."""
    out, k = [], 1
    while 2 * k <= ref_spp and (cap is None or k <= cap):
        out.append(k)
        k *= 2
    return out


def loglog_slope(x, y) -> float:
    """Least-squares slope of log y against log x: the exponent of a power law y ~ x^slope."""
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def reference_noise_slope(spp, ref_spp: int) -> float:
    """The slope an exact 1/k law shows when measured against a reference of ref_spp samples: the
    reference's own error adds sigma^2/ref_spp to every point and flattens the curve a little."""
    return loglog_slope(spp, [1 / k + 1 / ref_spp for k in spp])


def slope_ok(slope: float, expected=EXPECTED_SLOPE) -> bool:
    return expected[0] <= slope <= expected[1]


# How a metric is made a straight line in log time for a curve fit: relMSE ~ c t^b (its log), PSNR (dB,
# already logarithmic), SSIM through its dissimilarity 1 - SSIM ~ c t^b. (transform, inverse)
CURVE_SCALES = {
    "relMSE": (np.log, np.exp),
    "PSNR": (lambda v: np.asarray(v, float), lambda y: y),
    "SSIM": (lambda v: np.log(np.maximum(1 - np.asarray(v, float), 1e-12)), lambda y: 1 - np.exp(y)),
    "LDR-FLIP": (np.log, np.exp),    # a mean error in (0, 1] that falls with time, as relMSE
    "HDR-FLIP": (np.log, np.exp),
}

IMPROVES = {"relMSE": -1, "PSNR": 1, "SSIM": -1, "LDR-FLIP": -1, "HDR-FLIP": -1}  # sign of a better value's change on the transformed scale


@dataclass
class Curve:
    """A method's metric against its total time: the least-squares line through (log seconds,
    transformed metric) over its measured points, none dropped (a noisy point pulls the line a little
    instead of being hidden). Beyond the measured times the line is extrapolated, and says so."""
    metric: str
    intercept: float
    slope: float
    log_t: tuple          # the measured times' range (log seconds)

    def at_time(self, seconds: float) -> tuple[float, bool]:
        """The metric after `seconds`; (value, extrapolated)."""
        x = math.log(seconds)
        return float(CURVE_SCALES[self.metric][1](self.intercept + self.slope * x)), not self._inside(x)

    def time_for(self, value: float) -> tuple[float, bool]:
        """Seconds to reach `value` of the metric; (seconds, extrapolated). inf when the line never
        reaches it (a flat or wrong-way fit)."""
        if not math.isfinite(value):  # a method that produced no number (diverged) has no speed-up
            return math.nan, True
        y = float(CURVE_SCALES[self.metric][0](value))
        if self.slope * IMPROVES[self.metric] <= 1e-9 or not math.isfinite(y):
            return math.inf, True  # a flat or wrong-way line: more time does not buy quality
        x = (y - self.intercept) / self.slope
        return math.exp(x) if x < 700 else math.inf, not self._inside(x)

    def _inside(self, x: float) -> bool:
        return self.log_t[0] - 1e-9 <= x <= self.log_t[1] + 1e-9


def fit_curve(times, values, metric: str) -> Curve:
    x = np.log(np.asarray(times, float))
    y = CURVE_SCALES[metric][0](np.asarray(values, float))
    slope, intercept = np.polyfit(x, y, 1) if len(x) > 1 else (0.0, float(y[0]))
    return Curve(metric, float(intercept), float(slope), (float(x.min()), float(x.max())))


def rising_steps(per_view: pd.DataFrame, metric: str = "relMSE", z: float = 2.0) -> list[tuple[int, int]]:
    """Consecutive spp (k, 2k) of the brute-force curve where the error rises by more than `z` standard
    errors of the paired per-view difference (`per_view`: columns view, spp, metric): more samples
    must not score worse, beyond noise."""
    wide = per_view.pivot_table(index="view", columns="spp", values=metric, aggfunc="mean").sort_index(axis=1)
    if len(wide) < 2:  # one view: no noise estimate, nothing to decide
        return []
    out = []
    for a, b in zip(wide.columns[:-1], wide.columns[1:]):
        diff = (wide[b] - wide[a]).dropna()
        se = diff.std(ddof=1) / math.sqrt(len(diff)) if len(diff) > 1 else 0.0
        if diff.mean() > z * se:
            out.append((int(a), int(b)))
    return out


def pareto_front(times, errors) -> np.ndarray:
    """Mask of the points no other point beats in both time and error (at least as good in both, better
    in one): the methods worth running at some time budget."""
    t, e = np.asarray(times, float), np.asarray(errors, float)
    dominated = [bool(np.any((t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i])))) for i in range(len(t))]
    return ~np.array(dominated, dtype=bool)


# ---------------------------------------------------------------- tables and figure

SCORED = ("relMSE", "PSNR", "SSIM")


def average(rows: list[dict]) -> pd.DataFrame:
    """Mean over views per (method, spp), methods in the order measured, each by spp, with the standard
    error over views of each metric (`relMSE se`, ...; NaN for one view); total s = render s + network s."""
    df = pd.DataFrame(rows).drop(columns=["view"], errors="ignore")
    keys = ["method", "input", "spp", "network on"]
    groups = df.groupby(keys, sort=False)
    table = groups.mean(numeric_only=True).reset_index()
    for metric in SCORED:
        table[f"{metric} se"] = (groups[metric].std(ddof=1) / np.sqrt(groups[metric].count())).to_numpy()
    rank = {method: i for i, method in enumerate(dict.fromkeys(df["method"]))}
    table = table.sort_values(["method", "spp"], key=lambda c: c.map(rank) if c.name == "method" else c,
                              kind="stable").reset_index(drop=True)
    table.insert(table.columns.get_loc("network s") + 1, "total s", table["render s"] + table["network s"])
    return table


def pt_curves(table: pd.DataFrame) -> dict[str, Curve]:
    """Brute-force path tracing's curve for each scored metric."""
    bf = table[table["method"] == BRUTE_FORCE]
    return {m: fit_curve(bf["total s"], bf[m], m) for m in SCORED}


def add_speedups(table: pd.DataFrame) -> pd.DataFrame:
    """Equal-quality speed-up of every row against path tracing's curve, in relMSE and in PSNR (so that
    blur, which relMSE rewards, does not decide it alone), and the Pareto mask (relMSE)."""
    curves = pt_curves(table)
    extrapolated = pd.Series("", index=table.index)
    for metric in ("relMSE", "PSNR"):
        values = []
        for i, r in table.iterrows():
            if r["method"] == BRUTE_FORCE:
                values.append(math.nan)
                continue
            seconds, beyond = curves[metric].time_for(r[metric])
            values.append(seconds / r["total s"])
            if beyond:
                extrapolated[i] = ", ".join(filter(None, [extrapolated[i], metric]))
        table[f"speed-up ({metric})"] = values
    table["extrapolated"] = extrapolated
    table["Pareto"] = pareto_front(table["total s"], table["relMSE"])
    return table


def operating_rows(table: pd.DataFrame, operating_spp: int, inputs=("LR", "HR")) -> pd.DataFrame:
    """Per method (path tracing aside) with input in `inputs`, its row nearest the operating spp."""
    picked = []
    for _, part in table[(table["method"] != BRUTE_FORCE) & table["input"].isin(inputs)].groupby("method", sort=False):
        picked.append(part.iloc[int(np.argmin(np.abs(np.log2(part["spp"].to_numpy(float)) - math.log2(operating_spp))))])
    return pd.DataFrame(picked)


SPEEDUP_COLUMNS = ["method", "input", "spp", "total s",
                   *[c for m in SCORED for c in (m, f"speed-up at equal {m}", f"PT {m} at equal time")], "extrapolated"]
EQUAL_TIME_METRICS = ("relMSE", "PSNR", "LDR-FLIP", "HDR-FLIP")
EQUAL_TIME_COLUMNS = ["SRD method", "total s", "HR denoiser",
                      *[c for m in EQUAL_TIME_METRICS for c in (f"SRD {m}", f"denoiser {m}")],
                      "PSNR difference (dB)", "HDR-FLIP difference", "extrapolated"]


def speedup_table(table: pd.DataFrame, operating_spp: int) -> pd.DataFrame:
    """One row per method at the operating point: for relMSE, PSNR and SSIM, the seconds path tracing
    needs to match it and the speed-up that makes, and path tracing's value at the method's time."""
    curves = pt_curves(table)
    rows = []
    for _, r in operating_rows(table, operating_spp).iterrows():
        out = {"method": r["method"], "input": r["input"], "spp": int(r["spp"]), "total s": r["total s"]}
        beyond = []
        for metric in SCORED:
            seconds, extra_q = curves[metric].time_for(r[metric])
            value, extra_t = curves[metric].at_time(r["total s"])
            out |= {metric: r[metric], f"speed-up at equal {metric}": seconds / r["total s"],
                    f"PT {metric} at equal time": value}
            beyond += [metric] if (extra_q or extra_t) else []
        out["extrapolated"] = ", ".join(beyond) or "no"
        rows.append(out)
    return pd.DataFrame(rows, columns=SPEEDUP_COLUMNS)  # the columns even when every method was skipped


def equal_time_table(table: pd.DataFrame, operating_spp: int) -> pd.DataFrame:
    """The paper's motivation, head to head: each SRD method at LR `operating_spp` against each denoiser
    of HR renders (task denoise) given the same total seconds, the denoiser's values read off its own
    curve (fitted over its HR spp) at the SRD method's time. FLIP where the table has it (a time table
    measured before the suite scored FLIP has not): an HDR-FLIP difference below 0 is the SRD method's win."""
    rows = []
    hr_methods = table[(table["method"] != BRUTE_FORCE) & (table["input"] == "HR")]
    metrics = [m for m in EQUAL_TIME_METRICS if m in table and table[m].notna().all()]
    for _, r in operating_rows(table, operating_spp, ("LR",)).iterrows():
        for denoiser, part in hr_methods.groupby("method", sort=False):
            out = {"SRD method": r["method"], "total s": r["total s"], "HR denoiser": denoiser}
            beyond = []
            for metric in metrics:
                value, extra = fit_curve(part["total s"], part[metric], metric).at_time(r["total s"])
                out |= {f"SRD {metric}": r[metric], f"denoiser {metric}": value}
                beyond += [metric] if extra else []
            out["PSNR difference (dB)"] = out["SRD PSNR"] - out["denoiser PSNR"]
            if "HDR-FLIP" in metrics:
                out["HDR-FLIP difference"] = out["SRD HDR-FLIP"] - out["denoiser HDR-FLIP"]
            out["extrapolated"] = ", ".join(beyond) or "no"
            rows.append(out)
    return pd.DataFrame(rows, columns=EQUAL_TIME_COLUMNS)


def plot(table: pd.DataFrame, path, title: str) -> None:
    """Log-log relMSE against total time, one curve per method (points labelled by spp, bars: the standard
    error over views), and the Pareto front."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5.5))
    for method, part in table.groupby("method", sort=False):
        brute = method == BRUTE_FORCE
        ax.errorbar(part["total s"], part["relMSE"], yerr=part["relMSE se"].fillna(0), capsize=2,
                    marker="o" if part["input"].iloc[0] == "LR" else "s", ms=4, lw=2.5 if brute else 1.2,
                    color="black" if brute else None, label=method)
        for _, r in part.iterrows():
            ax.annotate(f"{int(r['spp'])}", (r["total s"], r["relMSE"]), fontsize=6, xytext=(2, 2),
                        textcoords="offset points")
    front = table[table["Pareto"]].sort_values("total s")
    ax.step(front["total s"], front["relMSE"], where="post", color="red", ls="--", lw=1, label="Pareto front")
    ax.scatter(front["total s"], front["relMSE"], s=110, facecolors="none", edgecolors="red", zorder=3)
    ax.set(xscale="log", yscale="log", xlabel="total time per frame (s): render + network",
           ylabel="relMSE vs HR reference", title=title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)

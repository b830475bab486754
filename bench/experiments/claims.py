"""`+experiment=claims`: each of the paper's claims as comparisons of recorded table rows, with a verdict.

A claim names pairs of rows, "table:row label" (`better` is the row the paper says wins). For each pair
and metric the difference is oriented so that a positive value supports the claim, and judged against
twice its standard error (SE):
  - with 2+ seeds on both rows: SE over seeds, sqrt(sd_a^2 / n_a + sd_b^2 / n_b) from the table's
    mean and std columns (training noise and data noise);
  - with one seed: the paired per-sequence SE, std of the per-sequence mean differences / sqrt(sequences),
    from the evaluation runs' per_image.csv (data noise only: it does not see how another seed would
    have trained, so a "holds" on one seed is weaker evidence, and the table says which basis it used).
Verdict: |difference| < 2 SE is "within noise"; otherwise "holds" or "reversed". A claim made of
several pairs holds when all of them hold, is reversed when any is reversed, and is within noise else.

The rows are read from the tables' CSVs (views of the run store) and their evaluation runs: run the
tables first (`+experiment=all`, then `+experiment=claims`). A claim with a row that no recorded table has (its
table not run, or run before the row was added) is listed as "not run", with the command that records
it; the others are still judged. Writes `<results_dir>/claims/table.{csv,md,tex}`.
"""
from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd

from bench import runs
from bench.errors import UserError
from bench.experiments.pipeline import Context
from bench.table_writer import write_table

log = logging.getLogger("bench")

METRICS = {"PSNR": 1, "SSIM": 1, "relMSE": -1}   # +1: higher is better
NOT_RUN = "not run"   # the verdict of a claim with a row missing from the recorded tables


class MissingRow(LookupError):
    """A claim's row is not in the recorded tables (its table not run, or run before the row existed)."""


def _table(ctx: Context, name: str, cache: dict) -> pd.DataFrame:
    if name not in cache:
        path = ctx.results_dir / name / "table.csv"
        if not path.exists():
            raise MissingRow(f"{path} does not exist: run `python -m bench +experiment={name} preset={ctx.preset}`")
        cache[name] = pd.read_csv(path)
    return cache[name]


def _row(ctx: Context, ref: str, cache: dict) -> pd.Series:
    name, _, label = ref.partition(":")
    table = _table(ctx, name, cache)
    found = table[table["method"] == label]
    if found.empty:
        raise MissingRow(f"no row {label!r} in {ctx.results_dir / name / 'table.csv'}: rerun "
                         f"`python -m bench +experiment={name} preset={ctx.preset}`")
    return found.iloc[0]


def _per_sequence(ctx: Context, eval_hash: str, metric: str) -> pd.Series:
    if ctx.runs_archive is not None:  # a fresh clone: the committed archive has the tables' evaluations
        runs.restore(ctx.runs_dir, ctx.runs_archive, "eval", eval_hash)
    path = ctx.runs_dir / "eval" / eval_hash / "per_image.csv"
    if not path.exists():
        raise UserError(f"claims: evaluation run {eval_hash} has no per_image.csv in {ctx.runs_dir}; "
                        "rerun its table with this runs_dir")
    return pd.read_csv(path).groupby("sequence")[metric].mean()


def _record(ctx: Context, kind: str, run_hash: str) -> dict | None:
    archives = [ctx.runs_archive] if ctx.runs_archive is not None else []
    path = runs.record_path(kind, run_hash, ctx.runs_dir, archives)
    return runs.read_record(path) if path is not None else None


def recipe(ctx: Context, row: pd.Series) -> str:
    """How a row's model was trained, as far as the cpu preset's history goes: its steps and SSIM term,
    from the training run of its first evaluation; "untrained" for a row that trains nothing, "runs not
    recorded" when neither the run store nor the archive has them. Tables are rerun at different times,
    so the claims of one table can stand on an earlier recipe than another's."""
    evaluation = _record(ctx, "eval", str(row["runs"]).split()[0])
    if evaluation is None:
        return "runs not recorded"
    trained = evaluation["identity"].get("trained")
    if not isinstance(trained, str):   # a model that trains nothing is named by its config instead
        return "untrained"
    training = _record(ctx, "train", trained.split("+")[0])   # a Cascade's stages share one recipe
    if training is None:
        return "runs not recorded"
    train = training["identity"]["train"]
    ssim = train["loss"]["final"].get("ssim")
    return f"{train['steps']} steps" + (f" + SSIM term {ssim:g}" if ssim else "")


def pair_recipe(better: str, worse: str) -> str:
    """One recipe when both rows share it (or one trains nothing), else 'better vs worse'."""
    if better == worse or worse == "untrained":
        return better
    return worse if better == "untrained" else f"{better} vs {worse}"


def compare(ctx: Context, better: pd.Series, worse: pd.Series, metric: str) -> dict:
    """Oriented difference, its SE and the basis of the SE for one pair and metric."""
    sign = METRICS[metric]
    diff = sign * (float(better[metric]) - float(worse[metric]))
    runs_b, runs_w = str(better["runs"]).split(), str(worse["runs"]).split()
    std = f"{metric} std"
    if len(runs_b) > 1 and len(runs_w) > 1 and std in better and not pd.isna(better[std]):
        se = math.sqrt(float(better[std]) ** 2 / len(runs_b) + float(worse[std]) ** 2 / len(runs_w))
        return {"diff": diff, "se": se, "basis": f"seeds ({len(runs_b)}, {len(runs_w)})"}
    a, b = _per_sequence(ctx, runs_b[0], metric), _per_sequence(ctx, runs_w[0], metric)
    paired = (a - b).dropna() * sign
    se = float(paired.std(ddof=1) / np.sqrt(len(paired))) if len(paired) > 1 else float("nan")
    return {"diff": diff, "se": se, "basis": f"{len(paired)} sequences, 1 seed"}


def verdict(diff: float, se: float) -> str:
    if not math.isfinite(se) or abs(diff) < 2 * se:
        return "within noise"
    return "holds" if diff > 0 else "reversed"


def combine(verdicts: list[str]) -> str:
    """A claim's verdict from its pairs': a reversed pair decides it even with another pair not run."""
    if "reversed" in verdicts:
        return "reversed"
    if NOT_RUN in verdicts:
        return NOT_RUN
    return "holds" if all(v == "holds" for v in verdicts) else "within noise"


def _tables_of(claim: dict) -> set[str]:
    worse = [claim["worse"]] if isinstance(claim["worse"], str) else claim["worse"]
    return {ref.partition(":")[0] for ref in [claim["better"], *worse]}


def run(ctx: Context, name: str, claims: list[dict], metric: str, tables: list[str] | None) -> pd.DataFrame:
    """`tables`: judge only the claims whose rows all come from these tables (e.g. the ones rerun with
    the current recipe); None: every claim."""
    if tables is not None:
        claims = [c for c in claims if _tables_of(c) <= set(tables)]
        if not claims:
            raise UserError(f"claims: no claim is made of rows of only {tables}")
    cache, rows = {}, []
    for claim in claims:
        pairs = [(claim["better"], worse) for worse in
                 ([claim["worse"]] if isinstance(claim["worse"], str) else claim["worse"])]
        for better_ref, worse_ref in pairs:
            row = {"claim": claim["claim"], "better (paper)": better_ref, "worse (paper)": worse_ref}
            try:
                better, worse = _row(ctx, better_ref, cache), _row(ctx, worse_ref, cache)
            except MissingRow as missing:  # judged when its table has it; the others still are
                log.warning("claims: %r not judged: %s", claim["claim"], missing)
                rows.append({**row, **{f"{m} verdict": NOT_RUN for m in METRICS}, "basis": str(missing)})
                continue
            row["recipe"] = pair_recipe(recipe(ctx, better), recipe(ctx, worse))
            for m in METRICS:
                c = compare(ctx, better, worse, m)
                row[f"{m} diff"], row[f"{m} 2SE"], row[f"{m} verdict"] = c["diff"], 2 * c["se"], verdict(c["diff"], c["se"])
                row["basis"] = c["basis"]
            rows.append(row)
    columns = ["claim", "better (paper)", "worse (paper)", "recipe", *(f"{m} {c}" for m in METRICS
                                                             for c in ("diff", "2SE", "verdict")), "basis"]
    table = pd.DataFrame(rows, columns=columns)   # the same columns whichever claim comes first
    table.insert(1, "verdict", table.groupby("claim", sort=False)[f"{metric} verdict"].transform(
        lambda v: combine(list(v))))
    if (table[f"{metric} verdict"] == NOT_RUN).all():   # not one pair recorded: nothing to judge
        raise UserError("claims: none of the claims' rows are recorded: " + "; ".join(table["basis"].unique()))
    write_table(table, ctx.results_dir / name, caption=(
        f"The paper's claims at preset {ctx.preset}, from the recorded tables. diff: the better row minus the "
        f"worse one as the paper orders them, signed so that > 0 supports the claim (relMSE: worse minus "
        f"better). 2SE: twice the standard error, over seeds when both rows have several, else over the "
        f"per-sequence paired differences of one seed (data noise only). A pair's verdict: within noise when "
        f"|diff| < 2SE, else holds or reversed. verdict (the claim, on {metric}): holds when every pair "
        f"holds, reversed when any is reversed, else within noise; {NOT_RUN}: a row is missing from the recorded "
        f"tables (basis says which and the command that records it) and no recorded pair is reversed. "
        f"recipe: the training steps (and SSIM term) of the pair's learned rows, better vs worse where they "
        f"differ (runs not recorded: neither the run store nor the archive has them); a table rerun after the "
        f"preset changed stands on the new recipe, one not yet rerun on the earlier."
        + (f" Judged: the claims made of rows of {', '.join(tables)} only." if tables is not None else "")))
    log.info("%s: %d comparisons, %s", name, len(table),
             ", ".join(f"{c}: {v}" for c, v in table.drop_duplicates("claim")[["claim", "verdict"]].values))
    return table

"""`+experiment=claims`: each of the paper's claims as comparisons of recorded table rows, with a verdict.

A claim names pairs of rows, "table:row label" (`better` is the row the paper says wins). For each pair
and metric the difference is taken per (seed, sequence), oriented so that a positive value supports the
claim (relMSE: worse minus better), from the evaluation runs' per-frame scores: seeds paired by index,
sequences by name, a deterministic row (one evaluation: OIDN, bilinear) against every seed of the other.
`bench.stats` gives its mean, a 95% t interval and a p-value from a seed x sequence variance decomposition
(training noise and scene noise, both random).
Verdict, on `metric` only: the p-value Holm-adjusted over the table's distinct comparisons below ALPHA is
"holds" or "reversed" by the sign, else "within noise". A claim made of several pairs holds when all of
them hold, is reversed when any is reversed, and is within noise else. The other metrics get their
intervals beside it. The earlier test (|difference| < 2 SE, SE over seeds from the tables' std columns,
unpaired) stays as the "2SE" columns, so the change is visible.
Scene robustness: each verdict is recomputed with each scene family's sequences left out (Holm again over
the table); the families whose removal changes it are named in "rests on". The per-family mean
differences and the variance components are in the CSV only.

The rows are read from the tables' CSVs (views of the run store) and their evaluation runs: run the
tables first (`+experiment=all`, then `+experiment=claims`). A claim with a row that no recorded table has (its
table not run, or run before the row was added) is listed as "not run", with the command that records
it; the others are still judged. Writes `<results_dir>/claims/table.{csv,md,tex}`, then rewrites the results
page `<results_dir>/README.md` from the tables (bench/experiments/results_page.py).
"""
from __future__ import annotations

import difflib
import logging
import math
import re

import numpy as np
import pandas as pd

from bench import archived, runs, stats
from bench.errors import UserError
from bench.experiments import results_page
from bench.experiments.context import Context, split_note
from bench.table_writer import SCORED_ON, listed_evaluations, read_table, write_table

log = logging.getLogger("bench")

METRICS = {"PSNR": 1, "SSIM": 1, "relMSE": -1, "LDR-FLIP": -1, "HDR-FLIP": -1}   # +1: higher is better
NOT_RUN = "not run"   # the verdict of a claim with a row missing from the recorded tables
ALPHA = 0.05          # family-wise error over the table's distinct comparisons (Holm)


class MissingRow(LookupError):
    """A claim's row is not in the recorded tables (its table not run, or run before the row existed)."""

    def __init__(self, message: str, table_not_run: str | None = None):
        super().__init__(message)
        self.table_not_run = table_not_run


def command_of(name: str, preset: str) -> str:
    """The command that writes table `name` (a paper table's or a study's)."""
    choice = f"+study={name.removeprefix('studies/')}" if name.startswith("studies/") else f"+experiment={name}"
    return f"python -m bench {choice} preset={preset}"


def _table(ctx: Context, name: str, cache: dict) -> pd.DataFrame:
    if name not in cache:
        path = ctx.results_dir / name / "table.csv"
        if not path.exists():
            raise MissingRow(f"{path} does not exist: run `{command_of(name, ctx.preset)}`", table_not_run=name)
        cache[name] = read_table(path)
    return cache[name]


def _row(ctx: Context, ref: str, cache: dict) -> pd.Series:
    name, _, label = ref.partition(":")
    table = _table(ctx, name, cache)
    found = table[table["method"] == label]
    if found.empty:  # a misspelt claim, or a row the table's config gained since the table was written
        close = difflib.get_close_matches(label, list(table["method"]), n=1)
        raise MissingRow(f"no row {label!r} in {ctx.results_dir / name / 'table.csv'}"
                         + (f" (did you mean {close[0]!r}?)" if close else
                            f" (its rows: {', '.join(map(repr, table['method']))})")
                         + f"; a row its config has gained since: rerun `{command_of(name, ctx.preset)}`")
    return found.iloc[0]


def _record(ctx: Context, kind: str, run_hash: str) -> dict | None:
    return runs.find_record(kind, run_hash, ctx.runs_dir, ctx.archives)[1]


def recipe(ctx: Context, row: pd.Series) -> str:
    """How a row's model was trained, as far as the cpu preset's history goes: its steps and SSIM term,
    from the training run of its first evaluation; "untrained" for a row that trains nothing, "runs not
    recorded" when neither the run store nor the archive has them. Tables are rerun at different times,
    so the claims of one table can stand on an earlier recipe than another's."""
    listed = listed_evaluations(row["runs"])
    evaluation = _record(ctx, "eval", listed[0]) if listed else None
    if evaluation is None:
        return "runs not recorded"
    trained = evaluation["identity"].get("trained")
    if not isinstance(trained, str):   # a model that trains nothing is named by its config instead
        return "untrained"
    training = _record(ctx, "train", runs.split_trainings(trained)[0])   # a Cascade's stages share one recipe
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


def _per_sequence_means(ctx: Context, eval_hash: str, cache: dict) -> pd.DataFrame:
    """Every metric's mean over each sequence's frames (index: sequence) of one evaluation run."""
    if eval_hash not in cache:
        if ctx.runs_archive is not None:  # a fresh clone: the committed archive has the tables' evaluations
            runs.restore(ctx.runs_dir, ctx.runs_archive, "eval", eval_hash)
        scored = (_record(ctx, "eval", eval_hash) or {}).get("identity", {}).get("split")
        if scored not in (None, ctx.eval.split):  # never a verdict from two splits' rows
            raise UserError(f"claims: evaluation run {eval_hash} scored split {scored!r}, these claims "
                            f"eval.split={ctx.eval.split!r}; rerun its table with eval.split={ctx.eval.split}")
        frames = archived.read_per_image(ctx.runs_dir / "eval" / eval_hash)
        if frames is None:
            raise UserError(f"claims: evaluation run {eval_hash} has no per-frame scores in {ctx.runs_dir}; "
                            "rerun its table with this runs_dir")
        recorded = [m for m in METRICS if m in frames]  # FLIP: not in evaluations recorded before it was scored
        cache[eval_hash] = frames.groupby("sequence")[recorded].mean().reindex(columns=list(METRICS))
    return cache[eval_hash]


def _evaluations(row: pd.Series) -> list[str]:
    """A row's evaluation runs, one per seed; a deterministic row repeats one run, listed here once."""
    return list(dict.fromkeys(listed_evaluations(row["runs"])))


def seeds_by_sequence(ctx: Context, row: pd.Series, metric: str, cache: dict) -> pd.DataFrame:
    """(evaluation runs, sequences) of one metric's per-sequence means."""
    return pd.DataFrame([_per_sequence_means(ctx, h, cache)[metric] for h in _evaluations(row)])


def paired(ctx: Context, better: pd.Series, worse: pd.Series, metric: str, cache: dict) -> pd.DataFrame:
    """d[seed, sequence], signed so that > 0 supports the claim (bench.stats.paired_differences)."""
    b, w = seeds_by_sequence(ctx, better, metric, cache), seeds_by_sequence(ctx, worse, metric, cache)
    if set(b.columns) != set(w.columns):
        raise UserError(f"claims: {better['method']!r} and {worse['method']!r} were scored on different "
                        "sequences; rerun their tables on one split")
    d = stats.paired_differences(b.to_numpy(), w[b.columns].to_numpy()) * METRICS[metric]
    return pd.DataFrame(d, columns=b.columns)


SEQUENCE_NAME = re.compile(r"(.+)-\d+-v\d+")   # bench.datagen names a sequence <family>-<scene seed>-v<view>


def family_of(sequence: str) -> str:
    """A sequence's scene family, from its name; a name not in that form (user data) is its own family."""
    match = SEQUENCE_NAME.fullmatch(sequence)
    return match.group(1) if match else sequence


def basis(better: pd.Series, worse: pd.Series, d: pd.DataFrame) -> str:
    seeds = [len(_evaluations(r)) for r in (better, worse)]
    how = "deterministic row broadcast" if 1 in seeds else "paired by index"
    return f"seeds {seeds[0]} vs {seeds[1]} ({how}), {d.shape[1]} sequences"


def two_se(ctx: Context, better: pd.Series, worse: pd.Series, metric: str, cache: dict) -> dict:
    """The earlier test, kept beside the new one: the tables' difference against twice its SE, over seeds
    (unpaired, from the std columns) when both rows have several, else over one seed's per-sequence
    paired differences."""
    diff = METRICS[metric] * (float(better.get(metric, math.nan)) - float(worse.get(metric, math.nan)))
    runs_b, runs_w = listed_evaluations(better["runs"]), listed_evaluations(worse["runs"])
    std = f"{metric} std"
    if len(runs_b) > 1 and len(runs_w) > 1 and std in better and not pd.isna(better[std]):
        se = math.sqrt(float(better[std]) ** 2 / len(runs_b) + float(worse[std]) ** 2 / len(runs_w))
    else:
        per_sequence = (_per_sequence_means(ctx, runs_b[0], cache)[metric]
                        - _per_sequence_means(ctx, runs_w[0], cache)[metric]).dropna()
        se = float(per_sequence.std(ddof=1) / np.sqrt(len(per_sequence))) if len(per_sequence) > 1 else float("nan")
    verdict = ("within noise" if not math.isfinite(se) or abs(diff) < 2 * se
               else "holds" if diff > 0 else "reversed")
    return {f"{metric} 2SE": 2 * se, f"{metric} 2SE verdict": verdict}


def interval_columns(metric: str, d: pd.DataFrame) -> dict:
    c = stats.compare(d.to_numpy())
    return {f"{metric} diff": c.diff, f"{metric} low": c.low, f"{metric} high": c.high, f"{metric} p": c.p}


def component_columns(metric: str, d: pd.DataFrame) -> dict:
    """Satterthwaite df and the standard deviations of d's seed, sequence and residual components."""
    components = stats.variance_components(stats.mean_squares(d.to_numpy()))
    return {f"{metric} df": stats.compare(d.to_numpy()).df,
            **{f"{metric} sd {k}": math.sqrt(v) for k, v in components.items()}}


def family_columns(metric: str, d: pd.DataFrame) -> dict:
    """Mean difference over each scene family's sequences (and the seeds)."""
    by_family = d.T.groupby(family_of).mean().mean(axis=1)
    return {f"{metric} diff {family}": float(v) for family, v in by_family.items()}


def comparison_key(better: pd.Series, worse: pd.Series) -> frozenset:
    """One hypothesis per distinct pair of run sets, whichever tables or order name them (the same runs
    stand in several tables: Holm counts them once)."""
    return frozenset({tuple(_evaluations(better)), tuple(_evaluations(worse))})


def judged_verdicts(differences: list, keys: list, leave_out: str | None = None) -> tuple[list, list]:
    """Each pair's Holm-adjusted p-value and verdict over the distinct comparisons (a pair not recorded,
    None: NaN and NOT_RUN). leave_out: a scene family whose sequences are dropped first."""
    diffs, p_values = [], {}
    for d, key in zip(differences, keys):
        if d is None:
            diffs.append(float("nan"))
            continue
        kept = d.loc[:, [family_of(q) != leave_out for q in d.columns]]
        c = stats.compare(kept.to_numpy())
        diffs.append(c.diff)
        p_values.setdefault(key, c.p)
    adjusted = dict(zip(p_values, stats.holm(list(p_values.values()))))
    p = [adjusted[k] if d is not None else float("nan") for d, k in zip(differences, keys)]
    verdicts = [stats.verdict(x, q) if d is not None else NOT_RUN for x, q, d in zip(diffs, p, differences)]
    return p, verdicts


def claim_verdicts(claims: pd.Series, pair_verdicts: list) -> pd.Series:
    return pd.Series(pair_verdicts, index=claims.index).groupby(claims, sort=False).transform(
        lambda v: combine(list(v)))


def rests_on(baseline: pd.Series, left_out: dict[str, pd.Series]) -> list[str]:
    """Per entry, the families whose leaving out changes its verdict, grouped by the verdict it changes
    to ("dining, office -> holds"; "-": none)."""
    texts = []
    for i in range(len(baseline)):
        changed = {}
        for family, verdicts in left_out.items():
            if verdicts.iloc[i] != baseline.iloc[i]:
                changed.setdefault(verdicts.iloc[i], []).append(family)
        texts.append("; ".join(f"{', '.join(f)} -> {v}" for v, f in changed.items()) or "-")
    return texts


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


def judge_pair(ctx: Context, better: pd.Series, worse: pd.Series, metric: str,
               cache: dict) -> tuple[dict, pd.DataFrame]:
    """A recorded pair's columns, and its d[seed, sequence] on the verdict's metric."""
    differences = {m: paired(ctx, better, worse, m, cache) for m in METRICS}
    d = differences[metric]
    row = {"recipe": pair_recipe(recipe(ctx, better), recipe(ctx, worse)),
           **{k: v for m in METRICS for k, v in interval_columns(m, differences[m]).items()},
           **two_se(ctx, better, worse, metric, cache), **component_columns(metric, d),
           **family_columns(metric, d), "basis": basis(better, worse, d)}
    return row, d


def _caption(ctx: Context, metric: str, tables: list[str] | None, subject: str) -> str:
    return (
        f"{subject} at {SCORED_ON.format(preset=ctx.preset, split=ctx.eval.split)}, from the recorded tables and their "
        f"evaluation runs.{split_note(ctx, ctx.eval.split)} "
        f"Method (bench/stats.py, docs/claims_statistics.md): per pair, d[seed, sequence] = the better row "
        f"minus the worse one as the paper orders them, signed so that > 0 supports the claim (relMSE: worse "
        f"minus better), seeds paired by index, sequences by name, a deterministic row (one evaluation) "
        f"against every seed of the other. diff: the mean of d; low, high: its 95% t interval, p: two-sided, "
        f"from a seed x sequence random-effects decomposition of d (SE^2 = sequence var / sequences + seed "
        f"var / seeds + residual var / cells, from ANOVA mean squares, components truncated at 0; "
        f"Satterthwaite df capped at the largest term's). Calibrated on synthetic data with this design "
        f"(tests/test_stats.py: 3 seeds x 20 sequences as on test, x 10 as on val; a null difference called at most 5% of the time). "
        f"{metric} verdict (a pair): p Holm-adjusted over the table's distinct comparisons (p Holm) below "
        f"{ALPHA:g}: holds or reversed by the sign of diff, else within noise. verdict (the claim, on {metric}): "
        f"holds when every pair holds, reversed when any is reversed, else within noise; {NOT_RUN}: a row is "
        f"missing from the recorded tables (basis says which and the command that records it) and no "
        f"recorded pair is reversed. The other metrics (PSNR, SSIM, relMSE, LDR-FLIP, HDR-FLIP; FLIP is lower-is-"
        f"better, so its d is worse minus better): their intervals only, blank where a row was evaluated before "
        f"the suite scored FLIP. rests on: the scene families "
        f"whose leaving out (Holm again over the table) changes the verdict, and what it changes to; the "
        f"CSV has each pair's mean difference per family and the variance components. 2SE, 2SE verdict "
        f"and verdict (2SE): the earlier test, |diff| < twice the SE over seeds (unpaired, from the tables' "
        f"std columns), kept to show the change. recipe: the training steps (and SSIM term) of the pair's "
        f"learned rows, better vs worse where they differ (runs not recorded: neither the run store nor the archive has them)."
        + (f" Judged: the claims made of rows of {', '.join(tables)} only." if tables is not None else ""))


def run(ctx: Context, name: str, claims: list[dict], metric: str, tables: list[str] | None,
        subject: str = "The paper's claims") -> pd.DataFrame:
    """`tables`: judge only the claims whose rows all come from these tables (e.g. the ones rerun with
    the current recipe); None: every claim. `subject`: what the comparisons are, the caption's first words
    (a study's own comparisons: conf/study/domain_verdicts.yaml)."""
    if metric not in METRICS:
        raise UserError(f"experiment.metric={metric}: the claims are decided on one of {', '.join(METRICS)}")
    if tables is not None:
        named = set().union(*map(_tables_of, claims))
        if isinstance(tables, str) or not set(tables) <= named:
            raise UserError(f"experiment.tables={tables}: a list of the tables the claims' rows come from, "
                            f"e.g. [sota,dilation]; they are {', '.join(sorted(named))}")
        claims = [c for c in claims if _tables_of(c) <= set(tables)]
        if not claims:
            raise UserError(f"claims: no claim is made of rows of only {tables}")
    cache, rows, differences, keys, not_run = {}, [], [], [], set()
    for claim in claims:
        pairs = [(claim["better"], worse) for worse in
                 ([claim["worse"]] if isinstance(claim["worse"], str) else claim["worse"])]
        for better_ref, worse_ref in pairs:
            row = {"claim": claim["claim"], "better (paper)": better_ref, "worse (paper)": worse_ref}
            try:
                better, worse = _row(ctx, better_ref, cache), _row(ctx, worse_ref, cache)
            except MissingRow as missing:  # judged when its table has it; the others still are
                log.warning("claims: %r not judged: %s", claim["claim"], missing)
                not_run.add(missing.table_not_run)
                rows.append({**row, f"{metric} 2SE verdict": NOT_RUN, "basis": str(missing)})
                differences.append(None)
                keys.append(None)
                continue
            columns, d = judge_pair(ctx, better, worse, metric, cache)
            if d.isna().all().all():  # a row evaluated before the suite scored `metric` (FLIP)
                unscored = (f"{metric} not recorded for {better['method']!r} or {worse['method']!r} (evaluated "
                            f"before it was scored): rerun their tables with force=true")
                log.warning("claims: %r not judged: %s", claim["claim"], unscored)
                rows.append({**row, **columns, f"{metric} 2SE verdict": NOT_RUN, "basis": unscored})
                differences.append(None)
                keys.append(None)
                continue
            rows.append({**row, **columns})
            differences.append(d)
            keys.append(comparison_key(better, worse))
    if all(d is None for d in differences):   # not one pair recorded: nothing to judge
        reasons = "; ".join(dict.fromkeys(r["basis"] for r in rows))  # each once: a table not run is many claims' reason
        paper_tables = {t for t in not_run if t and not t.startswith("studies/")}
        every = f" (`python -m bench +experiment=all preset={ctx.preset}` runs every paper table)" if paper_tables else ""
        raise UserError(f"claims: none of the claims' rows are recorded: {reasons}{every}")
    table = pd.DataFrame(rows)
    families = sorted({family_of(q) for d in differences if d is not None for q in d.columns})
    p_holm, verdicts = judged_verdicts(differences, keys)
    left_out = {f: judged_verdicts(differences, keys, leave_out=f)[1] for f in families}
    pair = pd.Series(verdicts)
    claim = claim_verdicts(table["claim"], verdicts)
    front = {"claim": table["claim"], "verdict": claim,
             "verdict (2SE)": claim_verdicts(table["claim"], list(table[f"{metric} 2SE verdict"])),
             "rests on": rests_on(claim, {f: claim_verdicts(table["claim"], v) for f, v in left_out.items()})}
    stats_columns = [f"{m} {c}" for m in METRICS for c in ("diff", "low", "high", "p")]
    table = pd.concat([pd.DataFrame(front), table.reindex(columns=[
        "better (paper)", "worse (paper)", "recipe", *stats_columns, f"{metric} 2SE", f"{metric} 2SE verdict",
        f"{metric} df", *(f"{metric} sd {k}" for k in ("seed", "sequence", "residual")),
        *(f"{metric} diff {f}" for f in families), "basis"])], axis=1)
    table.insert(table.columns.get_loc(f"{metric} p") + 1, f"{metric} p Holm", p_holm)
    table.insert(table.columns.get_loc(f"{metric} p Holm") + 1, f"{metric} verdict", verdicts)
    table.insert(table.columns.get_loc(f"{metric} verdict") + 1, f"{metric} rests on",
                 rests_on(pair, {f: pd.Series(v) for f, v in left_out.items()}))
    detail = [f"{metric} diff {f}" for f in families] + [f"{metric} sd {k}" for k in ("seed", "sequence", "residual")]
    # the CSV keeps the per-family differences and components
    write_table(table.drop(columns=detail), ctx.results_dir / name, caption=_caption(ctx, metric, tables, subject),
                csv_table=table)
    log.info("%s: %d comparisons, %s", name, len(table),
             ", ".join(f"{c}: {v}" for c, v in table.drop_duplicates("claim")[["claim", "verdict"]].values))
    log.info("results page: %s", results_page.write(ctx.results_dir, ctx.preset))
    return table

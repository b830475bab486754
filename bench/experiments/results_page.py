"""The results page, `<results_dir>/README.md`: what the recorded tables say, in words and their numbers.

`page(results_dir, preset)` reads only the tables under `results_dir` (each `table.csv`, and the caption
at the top of its `table.md`) and returns Markdown: per table what it compares, its rows with their
numbers, and per claim the verdict, difference, 95% interval and p-value of `claims/table.csv`. Every
number on the page is copied from a table, and the table's file is named beside it. No run store, no
config, no clock: the same tables give the same page, so a test regenerates the committed page and
compares. `+experiment=claims` and `+experiment=all` rewrite it at their end;
`python -m bench.experiments.results_page results/<preset>` rewrites it by hand. Studies
(`+study=NAME`, conf/study/) and the retired ones (docs/studies.md) keep their tables in
`<results_dir>/studies/<name>/`.
"""
from __future__ import annotations

import math
import re
import sys
from pathlib import Path

import pandas as pd

from bench.atomic import write_atomic
from bench.runs import ROOT
from bench.table_writer import PARTIAL_CAPTION, SCORED_ON_PATTERN, listed_evaluations, read_caption, read_table

PAGE = "README.md"

# (folder, what it compares). The paper's tables, then the controls the claims read, the studies, the tools.
PAPER_TABLES = [
    ("sr_denoise", "Table 1: EDSR and RAE on super-resolution alone and on denoising alone."),
    ("dilation", "Table 2: the dilation rate of the residual blocks' second conv, on SR and on denoising."),
    ("stage_order", "Table 3: stage order (SR->dn, dn->SR) and coupling (Cascade of stages trained apart, "
                    "or one End2End network)."),
    ("deform", "Table 4: deformable convs in one stage (ours), in both stages, and in the CFM baseline."),
    ("sota", "Table 5: the baselines at a matched compute budget, ours, and OIDN before or after upscaling."),
    ("ipt", "Table 6: information propagation added one by one to Simple End2End (SR->dn)."),
    ("deform_num", "Table 7: how many of the denoiser's decoder blocks are deformable."),
    ("perceptual", "Fig. 11: ours with and without the VGG16 perceptual term."),
    ("generalization", "Fig. 10: the Table 5 methods on scene families never seen in training."),
]
CONTROLS = [
    ("dilation_crop", "A control for Table 2: its denoising rows at rates 1 and 5, trained on twice the crop."),
]
STUDIES = "studies"   # the folder of the studies' tables: <results_dir>/studies/<name>/
# the studies of conf/study/ (`+study=NAME`)
KEPT_STUDIES = [
    ("dark_bias", "A dark scene's colour: a linear bilinear base, a relative-MSE term, permuted colour channels."),
    ("dark_bias_verdicts", "The dark_bias study's pairs, judged: each candidate against 'Ours + SSIM term 8', the "
                           "row it is added to."),
    ("lr_range_ssim", "The learning-rate range test with the SSIM term in the loss; its suggestions are the "
                      "cpu preset's `model_lr`."),
    ("domain", "The learned models' network domain: PU21 against per-frame exposure + log1p, without and with "
               "highlights passed through, on Table 5's learned rows (its caption gives the seeds)."),
    ("domain_verdicts", "The domain study's pairs, judged: each learned model's exposure row against its PU21 "
                        "row (exposure is the 'better' side: a reversed verdict would say PU21 wins)."),
    ("domain_pass_verdicts", "The domain study's pairs, judged: each learned model's exposure_pass row (highlights "
                             "passed through) against its exposure row."),
    ("emitters", "Lamps pasted into a quarter of the training items against none, on Table 5's learned rows "
                 "(its caption gives the seeds)."),
    ("emitters_verdicts", "The emitters study's pairs, judged: each learned model trained with lamps against "
                          "its row without."),
    ("fireflies", "Fireflies pasted into the input of a quarter of the training items beside the lamps, against "
                  "lamps alone and against neither, on Table 5's learned rows (its caption gives the seeds)."),
    ("fireflies_verdicts", "The fireflies study's pairs, judged: lamps and fireflies against neither, and "
                           "against lamps alone."),
    ("fireflies_stability", "The stability cases through the fireflies study's seed-0 'lamps and fireflies' "
                            "trainings."),
    ("emitters_stability", "The stability cases through the emitters study's seed-0 'lamps' trainings: the "
                           "lamp cases pass, the firefly cases show the cost."),
    ("emitters_causes", "Candidate causes of the lamps' cost (lamp items encoded at the exposure without their "
                        "lamp; the losses behind a knee; the share of lamp items), on Ours, EDSR and CFM, seed 0."),
    ("emitters_causes_stability", "The stability cases through the emitters_causes study's seed-0 'lamps in a "
                                  "tenth' trainings."),
]
# studies whose conclusion is now the preset: their configs are in git history (docs/studies.md)
RETIRED_STUDIES = [
    ("recipe", "What each change of the training recipe buys (the proposed model, one seed)."),
    ("headroom", "The proposed model with more steps or a larger crop, against OIDN at LR then bilinear."),
    ("ssim_term", "An SSIM term in the loss, at two weights, at 3x the steps, and on linear radiance."),
    ("baseline_lr", "EDSR and CFM at the learning rates of the range test without and with the SSIM term."),
]
METRICS = [("PSNR", 2), ("SSIM", 3), ("relMSE", 4)]   # (column, decimals), the verdict's metric first


def _num(value, digits: int) -> str:
    """A table's number as the page prints it: `digits` decimals, or two significant digits when that
    would show none (a small difference or spread)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    value = float(value)
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if value != 0 and abs(value) < 10 ** -digits:
        if abs(value) < 1e-6:
            return f"{value:.1e}"
        return f"{value:.{1 - math.floor(math.log10(abs(value)))}f}"
    return f"{value:.{digits}f}"


def _p(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{float(value):.3f}" if value >= 0.001 else f"{float(value):.1e}"


def _link(results_dir: Path, relative: str) -> str:
    """A table's file, named by its path from the repository's results folder and linked from the page."""
    return f"[`{results_dir.as_posix().rstrip('/')}/{relative}`]({relative})"


def _markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    cells = [[str(c).replace("|", "\\|") for c in row] for row in rows]
    return (["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
            + ["| " + " | ".join(row) + " |" for row in cells] + [""])


def _recipe(caption: str) -> list[str]:
    """The caption's sentences on how the rows were made and scored (preset, split, steps, loss, seeds)
    and on the references, as the table states them."""
    sentences = re.split(r"(?<=\.) ", caption)
    said = [s.split("; time_ms")[0].rstrip(".") + "." for s in sentences if s.startswith(("Preset ", "Scale "))]
    return said + [s for s in sentences if s.startswith("References")]


def _seeds(row: pd.Series) -> int:
    """Distinct evaluations of a row (a deterministic row repeats one per seed)."""
    return len(set(listed_evaluations(row.get("runs"))))


def _mean_std(row: pd.Series, column: str, digits: int) -> str:
    text = _num(row.get(column), digits)
    std, mean = row.get(f"{column} std"), row.get(column)
    if std is not None and not pd.isna(std) and float(std) > 1e-9 * max(1.0, abs(float(mean))):
        text += " ± " + _num(std, digits)
    return text


def _claims(results_dir: Path) -> pd.DataFrame | None:
    path = results_dir / "claims" / "table.csv"
    return pd.read_csv(path) if path.exists() else None


def _verdict_metric(claims: pd.DataFrame) -> str:
    holm = [c for c in claims.columns if c.endswith(" p Holm")]
    return holm[0][: -len(" p Holm")] if holm else "PSNR"


def _claims_of(claims: pd.DataFrame | None, table: str) -> list[str]:
    if claims is None:
        return []
    mine = claims[claims["better (paper)"].str.startswith(f"{table}:")
                  | claims["worse (paper)"].str.startswith(f"{table}:")]
    return [f"\"{c}\": **{v}**" for c, v in mine.drop_duplicates("claim")[["claim", "verdict"]].values]


def metrics_section(results_dir: Path, name: str, what: str, claims: pd.DataFrame | None) -> list[str]:
    """A metrics table: what it compares, each row's mean (± std over seeds) of PSNR, SSIM and relMSE."""
    folder = results_dir / name
    table = read_table(folder / "table.csv")
    caption = read_caption(folder / "table.md")
    lines = [f"### {name}", "", what, "",
             f"Numbers: {_link(results_dir, f'{name}/table.csv')} (mean ± std over seeds; "
             f"[`table.md`]({name}/table.md) has every column)."]
    said = _recipe(caption)
    if said:
        lines += [f"The table's caption: \"{' '.join(said)}\""]
    lines.append("")
    header = ["row", "seeds", *(f"{m} {'(dB) ↑' if m == 'PSNR' else '↑' if m == 'SSIM' else '↓'}" for m, _ in METRICS)]
    rows = [[r["method"], str(_seeds(r) or "-"), *(_mean_std(r, m, d) for m, d in METRICS)]
            for _, r in table.iterrows()]
    lines += _markdown_table(header, rows)
    verdicts = _claims_of(claims, name)
    if verdicts:
        lines += ["Claims on this table (from the claims table below): " + "; ".join(verdicts) + ".", ""]
    return lines


def claims_section(results_dir: Path, claims: pd.DataFrame | None) -> list[str]:
    lines = ["## The paper's claims", ""]
    if claims is None:
        return lines + ["Not judged at this preset: there is no `claims/table.csv` "
                        "(`python -m bench +experiment=claims`, after the tables).", ""]
    return lines + comparisons(results_dir, "claims", claims)


def comparisons(results_dir: Path, name: str, claims: pd.DataFrame) -> list[str]:
    """A claims-kind table (`<results_dir>/<name>/table.csv`): its verdicts, one line per compared pair."""
    metric = _verdict_metric(claims)
    unit = " (dB)" if metric == "PSNR" else ""
    lines = [f"From {_link(results_dir, f'{name}/table.csv')}. Each claim compares rows of the tables; the "
             f"verdict is taken on {metric}, from the difference per (seed, sequence), with Holm's correction "
             f"over the table (method: [`docs/claims_statistics.md`](../../docs/claims_statistics.md)). "
             f"diff: better minus worse as the paper orders them (> 0 supports the claim); interval: 95%; "
             f"p: Holm-adjusted; 2SE: the earlier verdict, kept to show the change; rests on: the scene "
             f"families whose leaving out changes the verdict.", ""]
    header = ["claim", "verdict", "pair (better vs worse)", f"{metric} diff{unit}", "95% interval",
              "p (Holm)", "pair verdict", "2SE verdict", "rests on"]
    digits = dict(METRICS).get(metric, 3)
    rows, seen = [], set()
    for _, r in claims.iterrows():
        first = r["claim"] not in seen
        seen.add(r["claim"])
        better = str(r["better (paper)"]).partition(":")[2]
        worse = str(r["worse (paper)"])
        worse = worse.partition(":")[2] if worse.partition(":")[0] == str(r["better (paper)"]).partition(":")[0] else worse
        interval = (f"[{_num(r.get(f'{metric} low'), digits)}, {_num(r.get(f'{metric} high'), digits)}]"
                    if not pd.isna(r.get(f"{metric} low", float("nan"))) else "-")
        rows.append([r["claim"] if first else "", f"**{r['verdict']}**" if first else "",
                     f"{better} vs {worse}", _num(r.get(f"{metric} diff"), digits), interval,
                     _p(r.get(f"{metric} p Holm")), r.get(f"{metric} verdict", "-"),
                     r.get(f"{metric} 2SE verdict", "-"), r.get(f"{metric} rests on", "-")])
    lines += _markdown_table(header, rows)
    counts = claims.drop_duplicates("claim")["verdict"].value_counts()
    lines += [f"{int(counts.sum())} claims: "
              + ", ".join(f"{int(n)} {v}" for v, n in counts.items()) + ".", ""]
    return lines


def macs_section(results_dir: Path) -> list[str]:
    table = pd.read_csv(results_dir / "macs" / "table.csv")
    size = re.search(r"per (\d+x\d+) input frame", read_caption(results_dir / "macs" / "table.md"))
    lines = ["### macs", "", "The MAC audit: each learned model's multiply-accumulates per "
             f"{size.group(1) + ' ' if size else ''}input frame, "
             f"counted two ways, at the widths fitted to the preset's budget. Numbers: "
             f"{_link(results_dir, 'macs/table.csv')}.", ""]
    rows = [[r["method"], str(r["width"]), str(int(r["params"])), _num(r["GMac (analytic)"], 1),
             _num(r["budget deviation %"], 1)] for _, r in table.iterrows()]
    return lines + _markdown_table(["model", "width", "params", "GMac", "off budget (%)"], rows)


def time_section(results_dir: Path) -> list[str]:
    folder = results_dir / "time"
    lines = ["### time", "", "Error against run time on the machine that ran it: brute-force path tracing "
             "(PT) against low-sample renders plus each method."]
    operating = "its operating spp"  # the LR input's samples per pixel, as speedup.csv records them
    if (folder / "speedup.csv").exists():
        speed = pd.read_csv(folder / "speedup.csv")
        spp = sorted({int(n) for n in speed.loc[speed["input"] == "LR", "spp"]}) if "spp" in speed else []
        operating = " or ".join(str(n) for n in spp) + " spp" if spp else operating
        lines += [f"Equal quality at {operating} ({_link(results_dir, 'time/speedup.csv')}): the seconds PT needs to "
                  "reach the method's error, over the method's seconds.", ""]
        rows = [[r["method"], r["input"], _num(r["total s"], 3), _num(r["PSNR"], 2),
                 _num(r["speed-up at equal PSNR"], 1), _num(r["speed-up at equal relMSE"], 1),
                 _num(r["speed-up at equal SSIM"], 1), str(r.get("extrapolated", "-"))] for _, r in speed.iterrows()]
        lines += _markdown_table(["method", "input", "s per frame", "PSNR (dB)", "x at equal PSNR",
                                  "x at equal relMSE", "x at equal SSIM", "extrapolated"], rows)
    if (folder / "equal_time.csv").exists():
        equal = pd.read_csv(folder / "equal_time.csv")
        lines += [f"Equal time ({_link(results_dir, 'time/equal_time.csv')}): each SRD method at LR {operating} "
                  "against a denoiser of HR renders given the same seconds.", ""]
        rows = [[r["SRD method"], r["HR denoiser"], _num(r["SRD PSNR"], 2), _num(r["denoiser PSNR"], 2),
                 _num(r["PSNR difference (dB)"], 2), str(r.get("extrapolated", "-"))] for _, r in equal.iterrows()]
        lines += _markdown_table(["SRD method", "HR denoiser", "SRD PSNR", "denoiser PSNR", "difference (dB)",
                                  "extrapolated"], rows)
    for path in sorted(folder.glob("equal_time_*.csv")):
        lines += paper_axis_lines(results_dir, path)
    return lines


def paper_axis_lines(results_dir: Path, path: Path) -> list[str]:
    """The equal-time table on the paper resolution's time axis, its verdicts beside the cpu-size axis's."""
    tag = path.stem.removeprefix("equal_time_")
    renders = path.with_name(f"render_{tag}.csv")
    lines = ["", f"Equal time on the {tag} time axis ({_link(results_dir, f'time/{path.name}')}; render seconds: "
             f"{_link(results_dir, f'time/{renders.name}')}, CPU time / render threads): the same head-to-head with "
             f"the renders at the paper's resolution; its quality axis is still the cpu preset's.", ""]
    equal = pd.read_csv(path)
    rows = [[r["SRD method"], r["HR denoiser"], _num(r["total s"], 2), _num(r["PSNR difference (dB)"], 2),
             _num(r["PSNR difference, wall axis (dB)"], 2), _num(r["PSNR difference, cpu-size axis (dB)"], 2),
             str(r["sign differs from cpu-size axis"]) if isinstance(r["sign differs from cpu-size axis"], str) else "",
             str(r.get("extrapolated", "-"))] for _, r in equal.iterrows()]
    return lines + _markdown_table(["SRD method", "HR denoiser", "s per frame", f"difference (dB), {tag}",
                                    "same, wall time", "cpu-size axis", "sign differs", "extrapolated"], rows)


def stability_section(results_dir: Path, name: str = "stability", what: str = "") -> list[str]:
    table = pd.read_csv(results_dir / name / "table.csv")
    lines = [f"### {name}", "", *([what, ""] if what else []), "Every model on fireflies, NaN/Inf, broken "
             "gBuffers, odd sizes, long sequences, bf16 and extreme offsets. Numbers: "
             f"{_link(results_dir, f'{name}/table.csv')}; "
             "largest output: the largest |output| (linear radiance) over the cases that ran; a case passes when "
             "finite and right (its table's caption gives the rules); not judged: measured before a rule.", ""]
    rows = []
    for model, cases in table.groupby("model", sort=False):
        status = cases["status"].astype(str)
        counts = [str(int(status.str.startswith(word).sum())) for word in ("ok", "error", "FAIL", "not judged")]
        rows.append([model, str(len(cases)), *counts, _num(pd.to_numeric(cases["max |output|"], errors="coerce").max(), 1)])
    return lines + _markdown_table(["model", "cases", "ok", "refused (clear error)", "FAIL", "not judged",
                                    "largest output"], rows)


def speed_table_label(table_md: Path) -> str:
    """What the page says of a speed table, from its caption: which weights it ran (`+experiment=speed`'s
    weights_caption), and PARTIAL where not every section is in."""
    caption = table_md.read_text().split("\n", 1)[0] if table_md.exists() else ""
    partial = ", PARTIAL (not every section timed)" if caption.startswith(PARTIAL_CAPTION) else ""
    if "widths, trained weights (" in caption:
        return "trained weights" + (" for some models" if "), untrained for " in caption else "") + partial
    return ("untrained weights" if "widths, untrained weights" in caption else "weights not said") + partial


def speed_section(results_dir: Path) -> list[str]:
    lines = ["### speed", "", "Milliseconds per input frame (its size and the output's in each table) and per "
             "training step, per machine: a speed table describes the machine it ran on. auto: the fast path `fast_path=auto` "
             "picks there for the weights the table ran, since its accuracy check depends on them (a path "
             "refused on untrained weights may pass on trained ones).", ""]
    for table_path in sorted((results_dir / "speed").glob("*/table.csv")):
        device = table_path.parent.name
        table = pd.read_csv(table_path)
        inference = table[table["section"] == "inference"]
        steps = table[table["section"] == "training step"]
        compiled = steps[steps["fast path"].astype(str).str.startswith("fp32, compiled")]  # not bf16's (on CUDA)
        lines += [f"{device}, {speed_table_label(table_path.with_suffix('.md'))}: "
                  f"{_link(results_dir, f'speed/{device}/table.csv')}", ""]
        rows = []
        for model, paths in inference.groupby("method", sort=False):
            fp32 = paths[paths["fast path"] == "fp32"]["ms"]
            picked = paths[paths["note"].astype(str).str.startswith("fast_path=auto picks")]
            auto = "-"
            if not picked.empty:
                note = str(picked.iloc[0]["note"])
                chosen = note.split("picks ", 1)[1].split(" of ", 1)[0]
                chosen = picked.iloc[0]["fast path"] if chosen == "this" else chosen
                timed = paths[paths["fast path"] == chosen]["ms"]
                auto = f"{chosen}" + (f" ({_num(timed.iloc[0], 1)})" if not timed.empty else "")
            step = steps[steps["method"] == model]["ms"]
            rows.append([model, _num(fp32.iloc[0], 1) if not fp32.empty else "-", auto,
                         _num(step.iloc[0], 1) if not step.empty else "-"])
            if len(compiled):
                graphed = compiled[compiled["method"] == model]["ms"]
                rows[-1].append(_num(graphed.iloc[0], 1) if not graphed.empty else "-")
        columns = ["model", "fp32 ms/frame", "auto (ms/frame)", "training step ms"]
        if len(compiled):  # the trainer's train.compile, timed for some models and the conv stack
            columns.append(f"step ms, {compiled['fast path'].iloc[0].split(', ', 1)[-1]}")
        lines += _markdown_table(columns, rows)
        stack = steps[steps["method"].astype(str).str.startswith("3x3 conv stack")]
        if len(stack):
            lines += [f"The {stack['method'].iloc[0]}, of Ours' MACs per pixel, for scale: a training step of "
                      + ", ".join(f"{_num(r['ms'], 1)} ms ({r['fast path']})" for _, r in stack.iterrows()) + ".", ""]
    return lines


def data_section(results_dir: Path) -> list[str]:
    table = pd.read_csv(results_dir / "data" / "table.csv")
    lines = ["### data", "", "The rendered dataset per split. ref error: a reference's estimated relMSE against "
             "the converged image, from its two half-sample renders (blank: one render). Numbers: "
             f"{_link(results_dir, 'data/table.csv')}.", ""]
    rows = [[r["split"], str(r["sequences"]), str(r["frames"]), str(r["ref spp"]),
             _num(r.get("hr ref error median"), 4), _num(r.get("hr ref error max"), 4)] for _, r in table.iterrows()]
    return lines + _markdown_table(["split", "sequences", "frames", "ref spp", "HR ref error median",
                                    "HR ref error max"], rows)


def lr_range_section(results_dir: Path, name: str, what: str = "") -> list[str]:
    table = pd.read_csv(results_dir / name / "table.csv")
    lines = [f"### {name}", "", *([what, ""] if what else []), "The learning-rate range test per model: the "
             "suggested peak rate is a tenth of the rate where the smoothed loss blows up (the test's top rate / "
             f"10 when it never does). Numbers: {_link(results_dir, f'{name}/table.csv')}.", ""]
    rows = [[r["model"], f"{float(r['suggested lr']):.2g}", str(bool(r["diverged"])).lower()]
            for _, r in table.iterrows()]
    return lines + _markdown_table(["model", "suggested lr", "diverged"], rows)


def all_section(results_dir: Path) -> list[str]:
    table = pd.read_csv(results_dir / "all" / "table.csv")
    lines = ["### all", "", "What `+experiment=all` costs: the recorded training and evaluation minutes of each "
             "table's runs (a run shared by tables counts in each; the last row counts it once). Numbers: "
             f"{_link(results_dir, 'all/table.csv')}.", ""]
    rows = [[r["experiment"], _num(r.get("compute (min)"), 0),
             "-" if pd.isna(r.get("trainings")) else str(int(r["trainings"]))] for _, r in table.iterrows()]
    return lines + _markdown_table(["experiment", "compute (min)", "trainings"], rows)


def adopt_section(results_dir: Path) -> list[str]:
    table = pd.read_csv(results_dir / "adopt" / "table.csv")
    verdicts = table["verdict"].astype(str).str.split(" ").str[0].value_counts()
    return ["### adopt", "", "The last check of stale trainings against the current code (replayed, then "
            "re-stamped when they reproduce): " + ", ".join(f"{int(n)} {v}" for v, n in verdicts.items())
            + f" of {len(table)} groups. Numbers: {_link(results_dir, 'adopt/table.csv')}.", ""]


TOOLS = {"macs": macs_section, "time": time_section, "stability": stability_section, "data": data_section,
         "all": all_section, "adopt": adopt_section}


def _is_metrics_table(path: Path) -> bool:
    if not path.exists():
        return False
    columns = pd.read_csv(path, nrows=0).columns
    return "method" in columns and all(m in columns for m, _ in METRICS)


def page(results_dir: str | Path, preset: str, shown_as: str | None = None) -> str:
    """The results page of `results_dir`, from its tables only; `shown_as`: the folder's name on the page
    (e.g. results/cpu; default: results_dir as given)."""
    results_dir = Path(results_dir)
    shown = shown_as or results_dir.as_posix()
    text = _page(results_dir, preset).replace(results_dir.as_posix(), shown)
    # links to docs/ are relative to the page: results/<preset>/ or results/<preset>/<split>/
    return text.replace("](../../docs/", f"]({'../' * len(Path(shown).parts)}docs/")


def scored_split(results_dir: Path) -> str | None:
    """The split the folder's tables and claims scored, as their captions state it (table_writer.SCORED_ON),
    when they agree on one."""
    splits = set()
    for name in [n for n, _ in PAPER_TABLES + CONTROLS if n != "generalization"] + ["claims"]:
        match = re.search(SCORED_ON_PATTERN, read_caption(results_dir / name / "table.md"))
        if match:
            splits.add(match.group(2))
    return splits.pop() if len(splits) == 1 else None


def split_lines(results_dir: Path) -> list[str]:
    """What the scored split is for, and a link to the page of the other split's tables, where there is one."""
    split = scored_split(results_dir)
    if split == "test":
        lines = ["Scored on the frozen `test` split: rendered apart (its own seeds) and only scored; nothing "
                 "was chosen on it."]
        if (results_dir / "val" / PAGE).exists():
            lines[0] += (" The same tables on `val`, the split the recipe and learning rates were chosen on: "
                         f"[`{results_dir.as_posix()}/val/{PAGE}`](val/{PAGE}).")
        return lines + [""]
    if split == "val" and results_dir.name == "val" and (results_dir.parent / PAGE).exists():
        return [f"Scored on `val`, the split the recipe and learning rates were chosen on. The frozen `test` "
                f"split's page, the one to quote, is one folder up: [`../{PAGE}`](../{PAGE}).", ""]
    return [f"Scored on `{split}`.", ""] if split else []


def _page(results_dir: Path, preset: str) -> str:
    claims = _claims(results_dir)
    split = scored_split(results_dir)
    lines = [f"# Results at preset `{preset}`" + (f", split `{split}`" if split else ""), "",
             f"Written by `bench/experiments/results_page.py` from the tables in `{results_dir.as_posix()}/` "
             f"(`+experiment=claims` and `+experiment=all` rewrite it; by hand: `python -m "
             f"bench.experiments.results_page {results_dir.as_posix()}`). Every number below is copied from "
             "the table file named beside it; a test regenerates this page from the committed tables, so it "
             "cannot drift from them. Do not edit it. Why the preset is what it is: "
             "[`docs/decisions.md`](../../docs/decisions.md).", ""] + split_lines(results_dir)
    known = {n for n, _ in PAPER_TABLES + CONTROLS} | set(TOOLS) | {"claims", "speed", "lr_range", STUDIES, "runs",
                                                                   "val"}
    present = lambda n: _is_metrics_table(results_dir / n / "table.csv")   # noqa: E731
    paper = [(n, w) for n, w in PAPER_TABLES if present(n)]
    if claims is None and not paper:
        lines += [f"No paper table and no claims are recorded at preset `{preset}` yet: the tools' tables "
                  "below are all this folder holds.", ""]
    if claims is not None or paper:
        lines += claims_section(results_dir, claims)
    others = [(p.parent.name, read_caption(p.parent / "table.md").split(". ")[0] + ".")
              for p in sorted(results_dir.glob("*/table.csv")) if p.parent.name not in known and present(p.parent.name)]
    lines += group_section(results_dir, "The paper's tables", paper, claims)
    lines += group_section(results_dir, "Controls", [(n, w) for n, w in CONTROLS if present(n)], claims)
    lines += studies_section(results_dir, claims)
    lines += group_section(results_dir, "Other tables", others, claims)
    tools = [name for name in ("macs", "time", "stability", "speed", "data", "lr_range", "all", "adopt")
             if (results_dir / name).is_dir() and (name == "speed" or (results_dir / name / "table.csv").exists()
                                                     or (results_dir / name / "speedup.csv").exists())]
    if tools:
        lines += ["## Tools", ""]
        for name in tools:
            if name == "speed":
                lines += speed_section(results_dir)
            elif name == "lr_range":
                lines += lr_range_section(results_dir, name)
            else:
                lines += TOOLS[name](results_dir)
    missing = [n for n, _ in PAPER_TABLES if not present(n)]
    if missing:
        lines += ["## Not recorded at this preset", "",
                  ", ".join(f"`{n}`" for n in missing) + f": no table in `{results_dir.as_posix()}/` "
                  f"(`python -m bench +experiment=NAME preset={preset}` records one).", ""]
    return "\n".join(lines).rstrip("\n") + "\n"


def group_section(results_dir: Path, title: str, tables: list[tuple[str, str]],
                  claims: pd.DataFrame | None) -> list[str]:
    """A titled group of metrics tables, (folder, what it compares) each; nothing when there is none."""
    lines = [f"## {title}", ""] if tables else []
    for name, what in tables:
        lines += metrics_section(results_dir, name, what, claims)
    return lines


def studies_section(results_dir: Path, claims: pd.DataFrame | None) -> list[str]:
    """The studies' tables under `<results_dir>/studies/`: those of conf/study/, then the retired ones."""
    lines = []
    for title, intro, studies in [
            ("Studies", "Beside the paper: `python -m bench +study=NAME` (conf/study/, "
                        "[`docs/studies.md`](../../docs/studies.md)).", KEPT_STUDIES),
            ("Retired studies", "Their conclusion is now the preset; their configs are in git history "
                                "([`docs/studies.md`](../../docs/studies.md)).", RETIRED_STUDIES)]:
        recorded = [(f"{STUDIES}/{n}", w) for n, w in studies if (results_dir / STUDIES / n / "table.csv").exists()]
        if not recorded:
            continue
        lines += [f"## {title}", "", intro, ""]
        for name, what in recorded:
            path = results_dir / name / "table.csv"
            if _is_metrics_table(path):
                lines += metrics_section(results_dir, name, what, claims)
            elif "verdict" in pd.read_csv(path, nrows=0).columns:   # a study's own comparisons (kind claims)
                lines += [f"### {name}", "", what, ""] + comparisons(results_dir, name, read_table(path))
            elif {"case", "status"} <= set(pd.read_csv(path, nrows=0).columns):   # kind stability
                lines += stability_section(results_dir, name, what)
            else:
                lines += lr_range_section(results_dir, name, what)
    return lines


def write(results_dir: str | Path, preset: str, repository: str | Path = ROOT) -> Path:
    """Write `<results_dir>/README.md`, naming the folder relative to `repository` when inside it."""
    results_dir = Path(results_dir)
    try:
        shown = results_dir.resolve().relative_to(Path(repository).resolve()).as_posix()
    except ValueError:
        shown = None
    path, text = results_dir / PAGE, page(results_dir, preset, shown)
    write_atomic(path, lambda tmp: tmp.write_text(text))
    return path


def preset_of(folder: str | Path) -> str:
    """The preset a results folder holds: results/<preset>, or results/<preset>/<split> for a split's tables
    beside the preset's own."""
    folder = Path(folder)
    return folder.parent.name if folder.name in ("val", "test") else folder.name


if __name__ == "__main__":
    for folder in sys.argv[1:] or ["results/cpu", "results/cpu/val"]:
        print(write(folder, preset_of(folder)))

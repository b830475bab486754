"""Write a results DataFrame as CSV (raw numbers), Markdown and LaTeX (booktabs).

Metric columns get an arrow (down: lower is better, up: higher is better) and the best value of each such
column is bold. Rows can be excluded from the best-of competition (e.g. the paper's numbers shown beside
ours) with `compete=False` in a boolean column named `compete`; that column is not printed.
A column "X std" beside a column "X" (several seeds) is printed inside X's cells as "mean ± std" in
Markdown and LaTeX, and a column "X se" (standard error over the evaluated sequences) as "(se ...)" after
it; the CSV keeps every column.
"""
from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from bench.atomic import write_atomic

DOWN, UP = "\u2193", "\u2191"

# How a caption says what it scored (the tables' and the claims'); the results page and the references
# tool read the split back with SCORED_ON_PATTERN.
SCORED_ON = "preset {preset}, split {split}"
SCORED_ON_PATTERN = r"[Pp]reset (\w+), split (\w+)"

# Opens a record written part by part until its last part is in (the speed table's caption, the GPU
# probes' and the deform sweep's first line): a run stopped before then leaves a record that says so, and
# scripts/gpu_job.sh (which greps for it) runs the step again, once.
PARTIAL = "PARTIAL: "
PARTIAL_CAPTION = f"{PARTIAL}not every section is timed yet (a run stopped part way leaves this)."


def write_record(out: Path, lines: list[str], missing: str | None) -> None:
    """A Markdown record as it stands, atomically, under a first line saying what is `missing` until
    nothing is: a probe or sweep killed at its limit leaves what it measured, marked PARTIAL."""
    text = (f"{PARTIAL}{missing}\n" if missing else "") + "\n".join(lines) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, lambda tmp: tmp.write_text(text))


def read_table(path: str | Path) -> pd.DataFrame:
    """A table.csv as `write_table` wrote it, its `runs` column as text: a single seed's hash of digits
    would otherwise read back as a number."""
    return pd.read_csv(path, dtype={"runs": str})


def listed_evaluations(cell) -> list[str]:
    """The evaluation runs a table row lists in its `runs` column (experiments/row.py writes it, `read_table`
    reads it): one hash per seed, in seed order, so a deterministic row repeats one; [] for none."""
    return cell.split() if isinstance(cell, str) else []


def read_caption(path: Path) -> str:
    """The caption of a table.md that write_table wrote (the paragraph before its table), or ''."""
    path = Path(path)
    if not path.exists():
        return ""
    first = path.read_text().split("\n\n", 1)[0]
    return "" if first.startswith("|") else first.strip()


def _fmt(value, digits: int) -> str:
    if isinstance(value, str):
        return value
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if isinstance(value, (int,)) and not isinstance(value, bool):
        return str(value)
    if isinstance(value, float):
        if value != 0 and abs(value) < 10 ** -(digits - 1):
            return f"{value:.{digits - 1}e}"
        return f"{value:.{digits}f}"
    return str(value)


def _best_rows(df: pd.DataFrame, lower: tuple, higher: tuple) -> dict[str, set]:
    """Column -> index labels holding that column's best value among competing rows."""
    competing = df[df["compete"].astype(bool)] if "compete" in df.columns else df
    best = {}
    for col in list(lower) + list(higher):
        if col not in competing.columns:
            continue
        values = pd.to_numeric(competing[col], errors="coerce").dropna()
        if values.empty:
            continue
        target = values.min() if col in lower else values.max()
        best[col] = set(values.index[values == target])
    return best


def _header(col: str, lower: tuple, higher: tuple) -> str:
    if col in lower:
        return f"{col} {DOWN}"
    if col in higher:
        return f"{col} {UP}"
    return col


_INSIDE = (" std", " se")  # suffixes of columns printed inside their metric's cells


def _shown(df: pd.DataFrame) -> list:
    def inside(col: str) -> bool:
        return any(col.endswith(s) and col[:-len(s)] in df.columns for s in _INSIDE)
    return [c for c in df.columns if c != "compete" and not inside(str(c))]


def _cell(row, col, digits: int) -> str:
    text = _fmt(row[col], digits)
    std = row.get(f"{col} std")
    if std is not None and not (isinstance(std, float) and math.isnan(std)):
        text += " \u00b1 " + _fmt(std, digits)
    se = row.get(f"{col} se")
    if se is not None and not (isinstance(se, float) and math.isnan(se)):
        text += f" (se {_fmt(se, digits)})"
    return text


def to_markdown(df: pd.DataFrame, lower=(), higher=(), digits: int = 4, caption: str = "") -> str:
    shown = _shown(df)
    best = _best_rows(df, lower, higher)
    lines = []
    if caption:
        lines += [caption, ""]
    lines.append("| " + " | ".join(_header(c, lower, higher) for c in shown) + " |")
    lines.append("|" + "|".join("---" for _ in shown) + "|")
    for idx, row in df.iterrows():
        cells = []
        for c in shown:
            text = _cell(row, c, digits)
            cells.append(f"**{text}**" if idx in best.get(c, ()) else text)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _latex_escape(text: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"),
                 ("$", r"\$"), ("^", r"\^{}"), ("->", r"$\to$"), ("+-", r"$\pm$"), ("\u00b1", r"$\pm$")):
        text = text.replace(a, b)
    return text


def to_latex(df: pd.DataFrame, lower=(), higher=(), digits: int = 4, caption: str = "",
             label: str = "") -> str:
    shown = _shown(df)
    best = _best_rows(df, lower, higher)
    head = []
    for c in shown:
        arrow = r"$\downarrow$" if c in lower else r"$\uparrow$" if c in higher else ""
        head.append(_latex_escape(str(c)) + arrow)
    lines = [r"\begin{table}", r"\centering"]
    if caption:
        lines.append(r"\caption{" + caption + "}")
    if label:
        lines.append(r"\label{" + label + "}")
    lines += [r"\begin{tabular}{l" + "c" * (len(shown) - 1) + "}", r"\toprule", " & ".join(head) + r" \\",
              r"\midrule"]
    for idx, row in df.iterrows():
        cells = []
        for c in shown:
            text = _latex_escape(_cell(row, c, digits))
            cells.append(r"\textbf{" + text + "}" if idx in best.get(c, ()) else text)
        lines.append(" & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def write_table(df: pd.DataFrame, out_dir: str | Path, name: str = "table", caption: str = "",
                lower_is_better=(), higher_is_better=(), digits: int = 4,
                csv_table: pd.DataFrame | None = None) -> dict[str, Path]:
    """Write `<name>.csv` (full precision), `<name>.md` and `<name>.tex`; returns their paths. `csv_table`:
    what the CSV holds when it is not `df` (a long form, or columns the printed table leaves out)."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise PermissionError(f"results directory {out_dir} is not writable ({err.strerror}); "
                              f"set results_dir=... to a writable place") from err
    df = df.reset_index(drop=True)
    paths = {"csv": out_dir / f"{name}.csv", "md": out_dir / f"{name}.md", "tex": out_dir / f"{name}.tex"}
    try:
        raw = df if csv_table is None else csv_table
        write_atomic(paths["csv"], lambda tmp: raw.drop(columns=["compete"], errors="ignore").to_csv(tmp, index=False))
        markdown = to_markdown(df, lower_is_better, higher_is_better, digits, caption)
        latex = to_latex(df, lower_is_better, higher_is_better, digits, _latex_escape(caption), f"tab:{out_dir.name}")
        write_atomic(paths["md"], lambda tmp: tmp.write_text(markdown))
        write_atomic(paths["tex"], lambda tmp: tmp.write_text(latex))
    except OSError as err:
        raise PermissionError(f"cannot write tables to {out_dir}: {err.strerror}") from err
    return paths

"""The paper's numbers in bench/paper_values.csv against the paper's LaTeX source, and the loader."""
from __future__ import annotations

import csv
import re

import pytest

from bench.paper import CSV_PATH, TABLES, paper_values
from conftest import PAPER_TEXT

# LaTeX \label{tab:...} -> experiment name, and the tasks each row spans (left to right).
LATEX_TABLES = {
    "sr_denoise": ("sr_denoise", ("SR", "Denoising")),
    "dilated": ("dilation", ("SR", "Denoising")),
    "arch_design": ("stage_order", ("SRD",)),
    "deform": ("deform", ("SRD",)),
    "sota": ("sota", ("SRD",)),
    "info_reserve": ("ipt", ("SRD",)),
    "deform_num": ("deform_num", ("SRD",)),
}
METRICS = ("relMSE", "PSNR", "SSIM")


def _clean(cell: str) -> str:
    cell = re.sub(r"~?\\cite\{[^}]*\}", "", cell)
    cell = re.sub(r"\\textbf\{([^}]*)\}", r"\1", cell)
    cell = cell.strip()
    return "" if cell == "-" else cell


def _parse_seed(text: str) -> dict[tuple[str, str, str], dict[str, str]]:
    """(table, row, task) -> {column: number as printed} for every row of the seed's seven tables."""
    out: dict[tuple[str, str, str], dict[str, str]] = {}
    for label, (table, tasks) in LATEX_TABLES.items():
        m = re.search(r"\\label\{tab:" + re.escape(label) + r"\}(.*?)\\end\{table\}", text, re.S)
        assert m, f"tab:{label} not found in the seed"
        body = m.group(1)
        body = body[body.rindex(r"\hline") + len(r"\hline"):body.index(r"\bottomrule")]
        rows = [r.strip() for r in body.split(r"\\") if r.strip()]
        assert rows, f"no rows in tab:{label}"
        for r in rows:
            cells = [_clean(c) for c in r.split("&")]
            name, rest = cells[0], cells[1:]
            extra = {"GMac": "", "RF": ""}
            if table == "sota":
                extra["GMac"], rest = rest[0], rest[1:]
            elif table == "dilation":
                extra["RF"], rest = rest[0], rest[1:]
            assert len(rest) == 3 * len(tasks), f"tab:{label} row {r!r}: unexpected column count"
            for i, task in enumerate(tasks):
                key = (table, name, task)
                assert key not in out, f"duplicate row {key}"
                out[key] = {**dict(zip(METRICS, rest[3 * i:3 * i + 3])), **extra}
    return out


def _csv_rows() -> list[dict[str, str]]:
    with open(CSV_PATH, newline="") as f:
        return list(csv.DictReader(f))


def test_csv_matches_the_papers_latex_tables():
    if not PAPER_TEXT.is_file():
        pytest.skip(f"the paper's text is not at {PAPER_TEXT} (set SRD_PAPER_TEXT to its path)")
    expected = _parse_seed(PAPER_TEXT.read_text(encoding="utf-8"))
    rows = _csv_rows()
    assert len(rows) == len(expected)
    got = {}
    for r in rows:
        key = (r["table"], r["row"], r["task"])
        assert key not in got, f"duplicate CSV row {key}"
        got[key] = {c: r[c] for c in (*METRICS, "GMac", "RF")}
    assert set(got) == set(expected)
    for key, values in expected.items():
        assert got[key] == values, f"{key}: CSV {got[key]} != paper {values}"


def test_loader_filters_by_table_and_rejects_unknown_names():
    everything = paper_values()
    assert list(everything.columns) == ["table", "row", "task", "relMSE", "PSNR", "SSIM", "GMac", "RF"]
    assert set(everything["table"]) == set(TABLES)
    for name in TABLES:
        part = paper_values(name)
        assert len(part) > 0 and (part["table"] == name).all()
    assert sum(len(paper_values(n)) for n in TABLES) == len(everything)

    sota = paper_values("sota").set_index("row")
    assert sota.loc["Ours", "GMac"] == 258.29 and sota.loc["Ours", "PSNR"] == 32.1106
    assert sota["GMac"].isna().sum() == 1  # Input Bilinear, printed "-"
    dil = paper_values("dilation")
    assert dil["row"].tolist()[:2] == ["1", "1"] and set(dil["task"]) == {"SR", "Denoising"}
    assert dil.set_index(["row", "task"]).loc[("5", "Denoising"), "RF"] == 57
    assert paper_values("deform_num")["row"].iloc[0] == "0"
    assert paper_values("stage_order")["GMac"].isna().all()

    with pytest.raises(ValueError, match="known tables: sr_denoise, dilation"):
        paper_values("tab:sota")

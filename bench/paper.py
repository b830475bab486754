"""The paper's published numbers, as one tidy table.

`bench/paper_values.csv` holds every number of Tables 1-7 of Wei et al., "End-to-End Adaptive Monte
Carlo Denoising and Super-Resolution": one row per (table, row label, task). `table` is the suite's
experiment name (Table 1 sr_denoise, 2 dilation, 3 stage_order, 4 deform, 5 sota, 6 ipt, 7 deform_num);
`row` is the paper's row label (citations dropped, e.g. "EDSR"); `task` is "SR" or "Denoising" for
Tables 1-2 and "SRD" otherwise. relMSE, PSNR and SSIM are as printed in the paper (not recomputed);
GMac is filled only for Table 5 (its FLOPS/GMac column; empty for Input Bilinear, printed "-"), RF (the
receptive field) only for Table 2.
"""
from __future__ import annotations

from pathlib import Path

import pandas as pd

CSV_PATH = Path(__file__).with_name("paper_values.csv")
TABLES = ("sr_denoise", "dilation", "stage_order", "deform", "sota", "ipt", "deform_num")
NUMERIC = ("relMSE", "PSNR", "SSIM", "GMac", "RF")
# Table 5's GMac column: its methods matched at this budget, counted per 960x540 input frame
BUDGET_GMAC, GMAC_INPUT_HW = 260, (540, 960)


def paper_values(table: str | None = None) -> pd.DataFrame:
    """All published numbers, or only those of one experiment `table` (one of TABLES)."""
    if table is not None and table not in TABLES:
        raise ValueError(f"unknown paper table {table!r}; known tables: {', '.join(TABLES)}")
    df = pd.read_csv(CSV_PATH, dtype={"table": str, "row": str, "task": str,
                                      **{c: "float64" for c in NUMERIC}})
    if table is not None:
        df = df[df["table"] == table].reset_index(drop=True)
    return df

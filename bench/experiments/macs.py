"""Compute audit of the learned models at the paper's budget (Table 5: ~260 GMac per 960x540 LR frame).

For each model: fit its width argument to the budget when asked (the paper matches compute by "adjusting
the channel number without changing the topologies"), then count MACs analytically and with
torch's FlopCounterMode on the meta device (exact shapes at full size, no compute), and write
`table.{csv,md,tex}` plus a per-stage breakdown `stages.csv` to `<out_dir>`.

Two entry points: `build_table(models, budget_gmac, input_hw, out_dir)` with plain arguments, and
`run(ctx, **params)`, the experiment protocol the CLI calls (bench/experiments/__init__.py).
"""
from __future__ import annotations

import copy
import logging
from pathlib import Path

import pandas as pd
import torch

from bench.errors import UserError
from bench.experiments.context import model_config
from bench.macs import audit, closest_width, count_macs, count_params, on_meta
from bench.models.factory import build_model, is_learned
from bench.paper import BUDGET_GMAC, GMAC_INPUT_HW, paper_values
from bench.table_writer import write_table

log = logging.getLogger("bench")

# The paper's Table 5 rows and the argument that sets each one's width (None: checked at its default).
SOTA_ROWS = [
    {"label": "EDSR", "model": "edsr", "width_arg": "channels"},
    {"label": "RAE", "model": "rae", "width_arg": "width"},
    {"label": "KPCN", "model": "kpcn", "width_arg": "channels"},
    {"label": "CFM", "model": "cfm", "width_arg": "channels"},
    {"label": "Ours", "model": "srd", "width_arg": None},
]


def paper_gmac() -> dict[str, float]:
    """The paper's Table 5 "FLOPS/GMac" column (960x540 input) by row label, from paper_values.csv."""
    sota = paper_values("sota").dropna(subset=["GMac"])
    return dict(zip(sota["row"], sota["GMac"]))


def frame_inputs(cfg: dict, input_hw: tuple[int, int]):
    """inputs_fn(device) for one LR frame of the model's input and gBuffer channel counts."""
    h, w = input_hw
    in_ch, g_ch = cfg.get("in_channels", 3), cfg.get("gbuffer_channels", 7)
    return lambda device: (torch.zeros(1, 1, in_ch, h, w, device=device),
                           torch.zeros(1, 1, g_ch, h, w, device=device))


def frame_macs(cfg: dict, input_hw: tuple[int, int], scale: int = 2) -> pd.DataFrame | None:
    """bench.macs rows (layer, macs, ...) of one LR frame through `cfg`'s model at `scale`, counted on
    the meta device: what the audit counts, for the tables that report MACs beside a score or a time
    (table's GMac column, speed). None for a model with nothing to train (interpolation, OIDN): the
    budget leaves those out."""
    model, inputs = on_meta(lambda: build_model(cfg, scale), frame_inputs(cfg, input_hw))
    return count_macs(model, inputs) if is_learned(model) else None


def audit_row(name: str, cfg: dict, budget_macs: float, input_hw, tolerance: float = 0.05
              ) -> tuple[dict, dict]:
    """One table row (and its per-stage MACs) for a model's instantiate dict, fitting its width first
    when the dict names a `width_arg`. When no width lands within +-tolerance (small budgets, where one
    channel is a big step) the closest is used and a warning logged; the deviation column shows it."""
    cfg = copy.deepcopy(cfg)
    width_arg = cfg.pop("width_arg", None)
    cfg.setdefault("scale", 2)
    inputs_fn = frame_inputs(cfg, input_hw)
    if width_arg:
        cfg[width_arg], macs = closest_width(lambda width: build_model({**cfg, width_arg: width}, 2),
                                             budget_macs, inputs_fn, lo=1)
        if abs(macs / budget_macs - 1) > tolerance:
            log.warning("macs: %s: no %s gives MACs within %.0f%% of the budget; closest %d is %+.1f%%",
                        name, width_arg, 100 * tolerance, cfg[width_arg], 100 * (macs / budget_macs - 1))
    model, inputs = on_meta(lambda: build_model(cfg, 2), inputs_fn)
    row = {"method": name, "width": f"{width_arg}={cfg[width_arg]}" if width_arg else "default",
           "params": count_params(model)}
    if row["params"] == 0:  # non-learned rows (interpolation, OIDN) are not part of the budget
        return row, {}
    result = audit(model, inputs)
    row.update({
        "GMac (analytic)": result["macs"] / 1e9,
        "GMac (torch counter)": result["torch_counter_macs"] / 1e9,
        "GMac not seen by torch counter": result["macs_not_seen_by_torch"] / 1e9,
        "budget deviation %": 100 * (result["macs"] / budget_macs - 1),
    })
    return row, result["per_stage"]


def build_table(models: dict[str, dict], budget_gmac: float, input_hw=(540, 960),
                out_dir: Path = Path("results/macs"), caption: str = "") -> pd.DataFrame:
    """Audit every model (display name -> instantiate dict, optionally with `width_arg`) and write tables."""
    rows, stages = [], []
    for name, cfg in models.items():
        row, per_stage = audit_row(name, cfg, budget_gmac * 1e9, tuple(input_hw))
        log.info("macs: %s %s: %s GMac", name, row["width"], row.get("GMac (analytic)"))
        row["per stage (GMac)"] = ", ".join(f"{s} {m / 1e9:.1f}" for s, m in per_stage.items()) or "-"
        rows.append(row)
        stages += [{"method": name, "stage": s, "GMac": m / 1e9} for s, m in per_stage.items()]
    table = pd.DataFrame(rows)
    if budget_gmac == BUDGET_GMAC and tuple(input_hw) == GMAC_INPUT_HW:  # the paper's numbers: its budget and size
        published = paper_gmac()
        table["GMac (paper)"] = [published.get(name) for name in table["method"]]
    out_dir = Path(out_dir)
    h, w = input_hw
    write_table(table, out_dir, caption=caption + (" " if caption else "") + (
        f"Compute per {w}x{h} input frame (scale 2 unless a model sets it), budget {budget_gmac:g} GMac (multiply-accumulates). "
        "Analytic count from layer shapes; torch counter = FlopCounterMode FLOPs / 2, which sees only "
        "conv/matmul; 'not seen' = declared MACs it misses (the deformable convs' bilinear sampling). "
        "Widths fitted to the budget where given, else the model's default."))
    pd.DataFrame(stages, columns=["method", "stage", "GMac"]).to_csv(out_dir / "stages.csv", index=False)
    return table


def run(ctx, name: str = "macs", rows: list[dict] | None = None, input_hw=(540, 960), caption: str = ""):
    """CLI entry: rows are {label, model (a name in ctx.models), width_arg (optional), overrides
    (optional)}; defaults to the paper's Table 5 models. Writes to <results_dir>/<name>/."""
    models = {}
    for r in rows or SOTA_ROWS:
        if not isinstance(r, dict) or "label" not in r or "model" not in r:
            raise UserError(f"experiment.rows: {r!r}: each row is {{label: ..., model: ...}} (optional width_arg, "
                            "overrides)")
        cfg = model_config(ctx, r["model"], r.get("overrides"))
        if r.get("width_arg"):
            cfg["width_arg"] = r["width_arg"]
        models[r["label"]] = cfg
    return build_table(models, ctx.budget_gmac, input_hw, Path(ctx.results_dir) / name, caption)

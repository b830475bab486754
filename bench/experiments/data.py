"""`+experiment=data`: render a preset's whole dataset (every buffer) and summarise it.

Writes `<results_dir>/data/table.{csv,md,tex}` (per split: sequences, frames, render time per pass,
non-finite samples repaired, passes left out and why) and preview PNGs of a few training views.
"""
from __future__ import annotations

import json
import logging
from contextlib import closing
from pathlib import Path

import pandas as pd

from bench import runs
from bench.datagen import damaged_frames, export_examples, load_manifest, stamp_frames
from bench.errors import UserError
from bench.experiments.context import Context
from bench.experiments.datasets import ensure_data
from bench.table_writer import write_table
from bench.tasks import BUFFERS

log = logging.getLogger("bench")


def summarize(frames: list[dict]) -> pd.DataFrame:
    """One row per split from the manifest's frame records."""
    df = pd.json_normalize(frames, sep=".")
    rows = []
    for split, part in df.groupby("split", sort=False):
        row = {"split": split, "sequences": part["sequence"].nunique(), "frames": len(part)}
        for col in sorted(c for c in part.columns if c.startswith("time_s.")):
            row[f"{col.removeprefix('time_s.').removesuffix('_s')} s"] = float(part[col].fillna(0).sum())
        row["nonfinite repaired"] = int(part.get("nonfinite_repaired", pd.Series(0)).sum())
        row["ref spp"] = "/".join(str(int(v)) for v in sorted(part.get("ref_spp", pd.Series(dtype=float)).dropna().unique()))
        for res in ("lr", "hr"):  # the references' estimated relMSE (two half-sample renders; bench.metrics)
            err = part.get(f"ref_error.{res}", pd.Series(dtype=float)).dropna()
            row[f"{res} ref error median"] = float(err.median()) if len(err) else None
            row[f"{res} ref error max"] = float(err.max()) if len(err) else None
        left = [f"{k}: {v}" for rec in frames if rec["split"] == split for k, v in (rec.get("left_out") or {}).items()]
        row["left out"] = "; ".join(f"{n}x {reason}" for reason, n in pd.Series(left).value_counts().items()) or "-"
        rows.append(row)
    return pd.DataFrame(rows)


def run(ctx: Context, name: str = "data", passes: list[str] | None = None, examples: int = 4,
        verify: bool = False) -> pd.DataFrame:
    """With `verify`, every frame is decoded (truncated files, NaN/Inf pixels); damaged ones are
    deleted and rendered again, and frames rendered before file stamps existed are stamped (with
    render_data=false, your own data: damaged frames are listed and nothing is changed)."""
    ensure_data(ctx, set(passes or BUFFERS))
    root = ctx.data_dir
    manifest = load_manifest(root)
    if verify:
        damaged = damaged_frames(root, manifest["frames"], manifest.get("passes", []), decode=True,
                                 stamps=ctx.render_data)
        log.info("data: verified every frame of %s: %d damaged files", root, len(damaged))
        if damaged and not ctx.render_data:
            raise UserError(f"data: {len(damaged)} damaged frame files: "
                            + "; ".join(f"{path}: {why}" for path, why in damaged))
        for path, _ in damaged:
            Path(path).unlink(missing_ok=True)
        if damaged:
            ensure_data(ctx, set(passes or BUFFERS))
        stamped = 0
        if ctx.render_data:  # from now on an edit to a verified frame is found at every start
            with closing(runs.acquire(root / ".render.lock", f"rendering {root}")):
                stamped = stamp_frames(root)
        if stamped:
            log.info("data: stamped %d verified frames (size, mtime, CRC-32): rendered before stamps existed, "
                     "or copied without their mtimes", stamped)
        manifest = load_manifest(root)
    table = summarize(manifest["frames"])
    out = ctx.results_dir / name
    write_table(table, out, caption=(
        f"Dataset {ctx.preset} ({manifest.get('variant')}): render seconds per pass summed over frames; ref "
        f"error: a reference's estimated relMSE against the converged image, from two independent half-sample "
        f"renders (splits with their own ref_spp; blank: one render, no estimate); "
        f"spec {json.dumps({k: v for k, v in ctx.data_spec.items() if k != 'splits'})}."))
    export_examples(root, out / "examples", count=examples)
    log.info("data: %d frames in %s; summary in %s", sum(table["frames"]), root, out)
    return table

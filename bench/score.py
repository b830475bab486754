"""Score a method's outputs, computed anywhere, with the suite's metrics, beside a table's recorded rows.

    srd-bench score --outputs out/ --data data/cpu --split val --label "My method" \
                    [--table results/cpu/val/sota/table.csv] [--out-dir DIR] [--against results/cpu/runs/eval/HASH]

`--outputs` holds one EXR per frame of the split, `<sequence>/<frame:04d>_hr.exr` (the tree
`srd-bench predict --output-dir out/ data/cpu/val` writes), holding linear HDR radiance at the reference's
size: the layer `output`, or the file's only layer (plain R, G, B channels). The references are the
split's `*_hr.exr` layer `ref`, read as the evaluator reads them (bench.dataset).

The scores are bench.evaluate's own: `evaluate` runs on a stand-in model that returns the outputs read
from the files, so every frame gets relMSE, robust relMSE, PSNR, SSIM and temporal relMSE
(bench.metrics) as a recorded evaluation does, and `aggregate` gives their means over frames and
standard errors over sequences. Outputs are scored as they are: a NaN in one scores as it would in an
evaluation (the evaluator repairs a model's inputs, never its outputs); such frames are named.

Writes `per_image.csv` and `table.csv/.md/.tex` (the rows of `--table`, if given, then this one) into
`--out-dir` (default: `--outputs`) and prints the table. `--against` an evaluation run's folder (its
run.json and per-frame scores, in a run store or an archive) compares the scores with the recorded ones and exits 1 when one differs by
more than `--rtol`.

Nothing here imports bench.experiments: scoring needs no model or config; the run store is read only
for `--against`.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench import archived, exrio, runs
from bench.atomic import write_atomic
from bench.dataset import SequenceDataset
from bench.errors import UserError
from bench.evaluate import SCORES, aggregate, evaluate
from bench.metrics import HIGHER_IS_BETTER, LOWER_IS_BETTER, METRICS
from bench.table_writer import read_table, to_markdown, write_table
from bench.tasks import Task

# evaluate() reads an item's task.x, task.g and task.y; the stand-in model ignores x and g
TASK = Task("score", x="outputs", g="gbuffer", y="hr_ref", scale=1)


class RecordedOutputs:
    """A stand-in model for `evaluate`: the outputs of the sequence `OutputFolder` loaded last, as
    they are (linear radiance, whole sequences: no network domain, no repair, no state)."""
    linear_hdr = True
    recurrent = True

    def __init__(self):
        self.frames = None     # (1, T, 3, H, W)

    def __call__(self, x, g):
        return {"final": self.frames[:, :x.shape[1]]}


def read_output(path: Path, shape: tuple) -> np.ndarray:
    """The HxWx3 output in `path`: its layer `output`, or its only layer; its size must be `shape`."""
    if not path.is_file():
        raise UserError(f"{path}: missing")
    layers = exrio.exr_layers(path)
    layer = "output" if "output" in layers else layers[0] if len(layers) == 1 else None
    if layer is None:
        raise UserError(f"{path}: no layer `output` among its layers {layers}; store the RGB output as the "
                        "layer `output` (channels output.R, output.G, output.B) or as the file's only layer")
    try:
        image = exrio.read_exr(path, [layer])[layer]
    except KeyError as err:  # channels `.R`, `.G`, `.B`: a layer with an empty name, which exrio does not read
        if layer:
            raise
        raise UserError(f"{path}: its channels are named like .{err.args[0]} (a layer with an empty name); "
                        "name them R, G, B or output.R, output.G, output.B") from err
    if image.shape != shape:
        raise UserError(f"{path}: {image.shape[1]}x{image.shape[0]}x{image.shape[2]}, the reference is "
                        f"{shape[1]}x{shape[0]} RGB")
    return image


class OutputFolder(torch.utils.data.Dataset):
    """The references of a split (bench.dataset) with, per sequence, the outputs from `outputs`; loading
    an item hands its outputs to `model` (the order `evaluate` uses)."""

    def __init__(self, outputs: Path, references: SequenceDataset, model: RecordedOutputs):
        self.outputs, self.references, self.model = outputs, references, model
        self.nonfinite: list[Path] = []

    def paths(self, index: int) -> list[Path]:
        name, start, n = self.references.items[index]
        frames = self.references.sequences[name][start:start + n]
        return [self.outputs / name / f"{rec['frame']:04d}_hr.exr" for rec in frames]

    def __len__(self):
        return len(self.references)

    def __getitem__(self, index):
        item = self.references[index]
        ref = item["hr_ref"]
        frames = [read_output(path, (ref.shape[2], ref.shape[3], 3)) for path in self.paths(index)]
        self.nonfinite += [path for path, image in zip(self.paths(index), frames) if not np.isfinite(image).all()]
        self.model.frames = torch.from_numpy(np.stack(frames).transpose(0, 3, 1, 2).copy())[None]
        blank = torch.zeros(len(frames), 1, 1, 1)
        return {"outputs": blank, "gbuffer": blank, "hr_ref": ref, "meta": item["meta"]}


def score(outputs: str | Path, data: str | Path, split: str = "val") -> tuple[pd.DataFrame, dict, list[Path]]:
    """(per-frame scores, their aggregate, output files holding non-finite values) of the outputs in
    `outputs` against split `split` of the dataset `data`: bench.evaluate's rows and aggregate."""
    outputs, data = Path(outputs), Path(data)
    if not outputs.is_dir():
        raise UserError(f"--outputs {outputs} is not a folder")
    if runs.read_json_or_none(data / "manifest.json") is None:
        raise UserError(f"--data {data} has no readable manifest.json: give a dataset folder in the documented layout")
    try:
        references = SequenceDataset(data, split, ["hr_ref"])
    except (KeyError, TypeError, ValueError) as err:
        raise UserError(f"--data {data}: {err}") from err
    model = RecordedOutputs()
    folder = OutputFolder(outputs, references, model)
    missing = [p for i in range(len(folder)) for p in folder.paths(i) if not p.is_file()]
    if missing:
        raise UserError(f"{len(missing)} of the split's outputs are missing under {outputs}, e.g. "
                        f"{', '.join(str(p) for p in missing[:3])}: one <sequence>/<frame:04d>_hr.exr per frame")
    per_image, _ = evaluate(model, folder, TASK)
    per_image = per_image.drop(columns="time_ms")
    return per_image, aggregate(per_image), folder.nonfinite


def table_with(label: str, scores: dict, table: str | Path | None = None) -> pd.DataFrame:
    """The rows of the table CSV `table` (none: an empty table of the scores' columns) and, last, the
    row `label` with `scores` in the columns the table has."""
    if table is None:
        columns = ["method", *(c for s in SCORES for c in (s, f"{s} se") if c in scores)]
        rows = pd.DataFrame(columns=columns)
    else:
        rows = runs.read_or_none(Path(table), read_table)
        if rows is None or "method" not in rows:
            raise UserError(f"--table {table}: not a readable results table (a CSV with a `method` column)")
        if not set(SCORES) & set(rows.columns):
            raise UserError(f"--table {table}: none of the score columns {', '.join(SCORES)}: the new row "
                            "would show nothing; give a metrics table (results/<preset>/<name>/table.csv)")
    rows = rows.astype({c: object for c in rows.columns if pd.api.types.is_integer_dtype(rows[c])})  # ints stay ints
    row = {c: scores.get(c, math.nan) for c in rows.columns if c != "method"}
    new = pd.DataFrame([{"method": label, **row}], columns=rows.columns)
    return new if rows.empty else pd.concat([rows, new], ignore_index=True)


def compare(per_image: pd.DataFrame, scores: dict, run_dir: str | Path, rtol: float) -> tuple[list[str], bool]:
    """Lines comparing `scores` (and each frame's) with the evaluation run recorded in `run_dir`, and
    whether all agree within `rtol` (relative)."""
    run_dir = Path(run_dir)
    run_dir = run_dir if run_dir.is_dir() else run_dir.parent     # the folder, or its run.json
    record = runs.read_record(run_dir / runs.RECORD)
    if record is None:
        raise UserError(f"--against {run_dir}: no readable run record (an evaluation run's folder, e.g. "
                        "results/cpu/runs/eval/<hash>)")
    recorded = record.get("metrics", {})

    def rel(a, b):
        if a == b or (math.isnan(a) and math.isnan(b)):
            return 0.0
        return abs(a - b) / max(abs(b), 1e-300)

    lines, worst = [], 0.0
    for name in (c for s in SCORES for c in (s, f"{s} se")):
        if name in scores and isinstance(recorded.get(name), (int, float)):
            d = rel(scores[name], float(recorded[name]))
            worst = max(worst, d)
            lines.append(f"{name}: {scores[name]:.10g} scored, {recorded[name]:.10g} recorded, relative difference {d:.2e}")
    frames = archived.read_per_image(run_dir)
    if frames is not None:
        merged = per_image.merge(frames, on=["sequence", "frame"], suffixes=("", " recorded"))
        if len(merged) != len(per_image):
            lines.append(f"per frame: {len(per_image)} frames scored, {len(merged)} of them recorded")
            worst = math.inf
        for name in SCORES:
            if name in per_image and f"{name} recorded" in merged:
                d = max((rel(a, b) for a, b in zip(merged[name], merged[f"{name} recorded"])), default=0.0)
                worst = max(worst, d)
                lines.append(f"{name} per frame: largest relative difference {d:.2e} over {len(merged)} frames")
    if not lines:
        raise UserError(f"--against {run_dir}: its record holds none of the scores {list(SCORES)}")
    if frames is None:
        lines.append(f"per frame: not compared ({run_dir} holds no per-frame scores that read: missing, or "
                     "damaged and named above); the aggregates only")
    ok = worst <= rtol
    lines.append(f"{'matches' if ok else 'DIFFERS from'} {run_dir} within rtol {rtol:g} (largest relative difference {worst:.2e})")
    return lines, ok


def add_parser(commands) -> None:
    """The `score` subcommand of the srd-bench entry point (bench.predict.main)."""
    sc = commands.add_parser("score", help="score a folder of output EXRs against a dataset's references")
    sc.add_argument("--outputs", required=True, help="<sequence>/<frame:04d>_hr.exr per frame of the split")
    sc.add_argument("--data", required=True, help="the dataset (manifest.json, <split>/<sequence>/*_hr.exr)")
    sc.add_argument("--split", default="val")
    sc.add_argument("--label", required=True, help="the row's name in the table")
    sc.add_argument("--table", help="a results table CSV whose rows are shown above the new one")
    sc.add_argument("--out-dir", help="where per_image.csv and table.csv/.md/.tex go (default: --outputs)")
    sc.add_argument("--against", help="an evaluation run's folder: compare the scores with its recorded ones")
    sc.add_argument("--rtol", type=float, default=1e-6, help="relative tolerance of --against (default 1e-6)")
    sc.add_argument("--accept-nonfinite", action="store_true",
                    help="score outputs holding NaN or Inf as they are (a frame whose scores are then NaN is left "
                         "out of the row's means, and the caption says how many)")


def unscored_frames(per_image) -> list[str]:
    """'<sequence> frame <n>' of each frame with a NaN per-frame score (a non-finite output or reference;
    PSNR's +inf, identical images, is a score, and the temporal relMSE is not a per-frame score)."""
    scores = [name for name in METRICS if name in per_image]
    if not scores:
        return []
    bad = per_image[per_image[scores].isna().any(axis=1)]
    return [f"{row.sequence} frame {row.frame}" for row in bad.itertuples()]


def run(args) -> int:
    """`srd-bench score`: 0, or 1 when `--against` finds a difference over `--rtol`."""
    per_image, scores, nonfinite = score(args.outputs, args.data, args.split)
    if nonfinite and not args.accept_nonfinite:
        raise UserError(f"{len(nonfinite)} of the outputs hold NaN or Inf values, e.g. {nonfinite[0]}: their "
                        "scores are undefined; repair the method's outputs, or --accept-nonfinite scores them as "
                        "they are")
    for path in nonfinite:
        print(f"{path}: holds non-finite values; scored as they are", file=sys.stderr)
    unscored = unscored_frames(per_image)
    caption = f"{args.label}: {args.outputs} on {args.data} {args.split}"
    if unscored:  # a mean skips NaN: the row's means are over the other frames, and say so
        left_out = (f"{len(unscored)} of {len(per_image)} frames have NaN scores and are left out of the "
                    f"row's means ({', '.join(unscored[:3])}{', ...' if len(unscored) > 3 else ''})")
        print(left_out, file=sys.stderr)
        caption += f"; {left_out}"
    table = table_with(args.label, scores, args.table)
    compared = compare(per_image, scores, args.against, args.rtol) if args.against else None  # before writing
    out_dir = Path(args.out_dir or args.outputs)
    if out_dir.resolve().is_relative_to(runs.COMMITTED_RESULTS):  # the committed tables are written by the suite
        raise UserError(f"--out-dir {out_dir}: under the committed results/, where this table would replace the "
                        "suite's; choose another --out-dir (--table reads a committed table without writing it)")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_atomic(out_dir / "per_image.csv", lambda tmp: per_image.to_csv(tmp, index=False))
        written = write_table(table, out_dir, "table", caption, LOWER_IS_BETTER, HIGHER_IS_BETTER)
    except OSError as err:
        raise UserError(f"cannot write the scores to {out_dir} ({err}); choose another --out-dir") from err
    print(to_markdown(table, LOWER_IS_BETTER, HIGHER_IS_BETTER))
    print(f"{scores['images']} frames, {scores['sequences']} sequences; wrote {out_dir / 'per_image.csv'}, "
          f"{', '.join(str(p) for p in written.values())}", file=sys.stderr)
    if compared:
        lines, ok = compared
        print("\n".join(lines))
        return 0 if ok else 1
    return 0

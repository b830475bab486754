"""What a table experiment costs at a preset on one GPU, projected from the committed GPU records: a lead
for sizing the preset to the speedrun (issue #62: Table 5 from a bare machine in 13 minutes, two calls),
not a run. Each phase names where its rate comes from:

- rendering: the splits the table renders (every training's frames and the working split its learning
  curve reads, bench.experiments.context.training_splits, and the scored split), from the render probe's
  seconds per buffer (`results/gpu/data/<machine>-render-probe.md`: the later frames' noisy passes scaled
  by spp over the probe's, the references by each split's reference spp, both by the frames' pixels) plus
  each sequence's first-frame set-up, in one process; divided by the probe's gain of N processes over
  one where the preset renders with N (`workers`; the job's sota step takes it from SOTA_ARGS) and the
  record says both passes started without a kernel cache, as a fresh machine's render does (else the
  gains over pass 1 and pass 2 are printed, not used);
- training: the speed table's training step (`results/gpu/speed/<machine>/table.csv`: the trainer's step,
  at the preset's widths, batch, frames and crop) on the path the preset trains (fp32, eager or
  `train.compile=reduce-overhead` with its first call's compile once per training: Inductor's cache on
  disk is not counted on), times steps and seeds; and the learning curve's scoring at its points. A model
  configured unlike the one timed (another width or scale: one frame's MACs against the table's
  inference row) has no rate;
- scoring: the metrics of one output frame (`bench.metrics.all_metrics`, on the host's CPU), timed here
  on random frames of the preset's HR size (median of 3 calls). Run on the GPU machine (the job's `plan`
  step), it times that host; elsewhere it is an estimate that names the CPU it ran on. Inference on the
  GPU is left out (the speed table: about 1 ms a frame at this size);
- the power of the claims' paired test at a difference (default 0.1 dB) with the preset's seeds and scored
  sequences (`bench.stats.power`: compare() on simulated designs), from each claim pair's PSNR variance
  components in `results/cpu/claims/table.csv` (docs/claims_statistics.md). At the gpu preset's size the
  components are not known: the cpu preset's stand in.

Rows whose model does not import here are left out, as the GPU job's sota step leaves them (OIDN without
pyoidn). Not in the projection: installing the wheels and starting Python (the job's log), decoding the
training frames into GPU memory, checkpoints.

    python scripts/gpu_speedrun_plan.py                      # Table 5 at preset gpu on cuda-nvidia-h200
    python scripts/gpu_speedrun_plan.py --set train.steps=400 data.splits.train.sequences=30
"""
from __future__ import annotations

import argparse
import math
import re
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from gpu_render_probe import split_seconds  # noqa: E402   the probe's own projection of a split
from gpu_step_concurrency import composed  # noqa: E402   the config as the entry point resolves it

PATHS = {None: "fp32", "reduce-overhead": "fp32, compiled (reduce-overhead)"}   # train.compile -> speed table path


def render_rates(record: Path) -> dict:
    """The render probe's measured rates: its frame size and spp, seconds per buffer of a later frame,
    the first frame's extra seconds per sequence, and its passes' wall seconds."""
    text = record.read_text()
    size = re.search(r"(\d+)x(\d+) LR x(\d+), (\d+) spp, reference (\d+) spp", text)
    per_frame = re.search(r"per frame \(median[^)]*\): (.*); per sequence, the first frame's extra seconds "
                          r"in the first pass: ([\d.]+)", text)
    if not size or not per_frame:
        raise ValueError(f"{record}: no probe settings or per-buffer seconds (a PARTIAL record?)")
    walls = {k: float(v) for k, v in re.findall(r"(pass \d): \d+ frames in ([\d.]+) s wall", text)}
    workers = re.search(r"pass 3: the same \d+ frames by (\d+) processes at once[^:]*: ([\d.]+) s wall", text)
    cold = bool(re.search(r"pass 3: [^\n]* from an empty kernel cache", text)
                and re.search(r"pass 1: [^\n]* from an empty kernel cache", text))
    return {"lr": (int(size.group(1)), int(size.group(2))), "spp": int(size.group(4)),
            "ref_spp": int(size.group(5)),
            "buffers": {k: float(v) for k, v in re.findall(r"(\w+_s) ([\d.]+)", per_frame.group(1))},
            "setup_s": float(per_frame.group(2)), "walls": walls,
            "workers": (int(workers.group(1)), float(workers.group(2))) if workers else None,
            "workers_cold": cold}   # pass 3 and pass 1 both without a kernel cache: their walls compare


def step_rates(table_dir: Path, preset: str, size: str, path: str) -> dict[str, dict]:
    """Per model label, its training step (ms) on `path` at `size`, for a compiled path the seconds its
    first call compiled (from the row's note), and what one frame through the model the table timed
    costs (`frame`: {"gmac", "lr_hw": (height, width)}, from its inference rows; None without one), as the
    speed table timed them at `preset`'s widths."""
    if f"preset {preset} widths" not in (table_dir / "table.md").read_text().split("\n\n")[0]:
        raise ValueError(f"{table_dir}: not timed at preset {preset}'s widths")
    table = pd.read_csv(table_dir / "table.csv")
    rows = table[(table["section"] == "training step") & (table["size"] == size) & (table["fast path"] == path)]
    frames = {}
    for _, row in table[(table["section"] == "inference") & table["GMac"].notna()].iterrows():
        width, height = map(int, row["size"].split(" ")[0].split("x"))   # size: "960x540 -> 1920x1080"
        frames.setdefault(row["method"], {"gmac": float(row["GMac"]), "lr_hw": (height, width)})
    rates = {}
    for _, row in rows.iterrows():
        compiled = re.search(r"first call \(compile\) ([\d.]+) s", str(row["note"]))
        rates[row["method"]] = {"ms": float(row["ms"]), "compile_s": float(compiled.group(1)) if compiled else 0.0,
                                "frame": frames.get(row["method"])}
    return rates


def models_not_timed(cfg: dict, steps: dict[str, dict], learned: list[str], rtol: float = 1e-4) -> dict[str, str]:
    """{label: why} of the learned models whose configuration is not the model the speed table timed:
    one frame's MACs, counted here on the meta device at the table's inference size and the data's scale,
    differ from the table's inference row (a width set with --set models.srd.channels=..., another
    scale, a changed model), or the table has no such row to check against. Both counts are the same
    analytic count, so they agree to the CSV's rounding when the model is the same. Models are taken as
    `table_rows` takes them: a row's own `overrides` are not read (the sota table's rows have none)."""
    from bench.experiments.macs import frame_macs
    from bench.experiments.speed import LABELS
    why = {}
    for model in learned:
        label = LABELS.get(model, model)
        if label not in steps:
            continue   # no step to use: plan() says so
        timed = steps[label]["frame"]
        if timed is None:
            why[label] = "no inference row in the speed table to check the configured model against"
            continue
        height, width = timed["lr_hw"]
        gmac = frame_macs(cfg["models"][model], timed["lr_hw"], cfg["data"]["scale"])["macs"].sum() / 1e9
        if abs(gmac - timed["gmac"]) > rtol * timed["gmac"]:
            why[label] = (f"its step was timed on a model of {timed['gmac']:.1f} GMac a {width}x{height} frame; "
                          f"this configuration's is {gmac:.1f}")
    return why


def scoring_ms(hr_hw: tuple[int, int], names=None, frames: int = 7, calls: int = 3) -> float:
    """Milliseconds to score one output frame of `hr_hw` with `bench.metrics.all_metrics` (`names`: only
    these) on this host's CPU: the median of `calls` calls after one, on a random sequence of `frames`."""
    import torch
    from bench.metrics import all_metrics
    generator = torch.Generator().manual_seed(0)
    pred, ref = (2 * torch.rand(frames, 3, *hr_hw, generator=generator) for _ in range(2))
    all_metrics(pred, ref, names)
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        all_metrics(pred, ref, names)
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times) / frames


def table_rows(cfg: dict) -> tuple[list[str], list[str], dict[str, str]]:
    """The experiment's learned and deterministic row models (less `experiment.leave_out`'s), and {model:
    why} of those left out because their model does not import here (as the GPU job's sota step leaves
    them out)."""
    from bench.errors import UserError
    from bench.experiments.table import missing_package
    from bench.measure import error_summary
    from bench.models.factory import build_model, is_learned
    learned, fixed, left_out = [], [], {}
    for row in (r for r in cfg["experiment"]["rows"] if r["label"] not in (cfg["experiment"].get("leave_out") or [])):
        try:
            model = build_model(cfg["models"][row["model"]], cfg["data"]["scale"])
        except UserError as err:
            missing = missing_package(err)
            if missing is None:
                raise
            left_out[row["model"]] = error_summary(missing)
            continue
        (learned if is_learned(model) else fixed).append(row["model"])
    return learned, fixed, left_out


def render_gain(render: dict, workers: int) -> tuple[int, float, str]:
    """(processes, gain, why not) of rendering with `workers` processes: the probe's N-process pass over its
    pass 1 where both started without a kernel cache and N is `workers`; else one process, no gain, and why."""
    if not render["workers"]:
        return 1, 1.0, "the probe ran no several-process pass"
    n, wall = render["workers"]
    if not render["workers_cold"]:
        return 1, 1.0, "run the probe again for a cold one"
    if n != workers:
        return 1, 1.0, f"this preset renders with workers={workers}"
    return n, render["walls"]["pass 1"] / wall, ""


def plan(cfg: dict, render: dict, steps: dict[str, dict], score_ms: float, curve_ms: float,
         learned: list[str], fixed: list[str], not_timed: dict[str, str] | None = None) -> list[dict]:
    """The phases' projected seconds (NaN where a rate was not measured, or `not_timed` {label: why} says
    the measured one is not this model's): rows of phase, label (a split, a model, scoring), what,
    seconds, source."""
    from bench.experiments.context import training_splits, working_split
    from bench.experiments.speed import LABELS
    not_timed = not_timed or {}
    data, train, seeds = cfg["data"], cfg["train"], len(cfg["seeds"])
    scored = cfg["eval"]["split"]
    ctx = SimpleNamespace(eval=SimpleNamespace(split=scored), data_spec=data)   # what the two rules read
    processes, gain, _ = render_gain(render, cfg["workers"])
    rows = [{"phase": "render", "label": name,
             "what": f"{name}: {data['splits'][name]['sequences']} sequences at ref "
             f"{data['splits'][name].get('ref_spp') or data['ref_spp']} spp"
             + (f", / {gain:.2f} ({processes} processes)" if processes > 1 else ""),
             "seconds": split_seconds(data, name, render) / gain,
             "source": "render probe, " + (f"{processes} processes" if processes > 1 else "one process")}
            for name in sorted(training_splits(ctx) | {scored}, key=list(data["splits"]).index)]
    curve_split = working_split(ctx)
    curve_frames = min(train["val_sequences"], data["splits"].get(curve_split, {}).get("sequences", 0)) * data["seq_len"]
    # the trainer scores its curve at step 0, every val_every steps and at the last (bench/train.py)
    points = 1 + (-(-train["steps"] // train["val_every"]) if train["val_every"] else 1) if curve_frames else 0
    for model in learned:
        label = LABELS.get(model, model)
        rate = steps.get(label)
        if rate is None or label in not_timed:
            why = not_timed.get(label, "no speed row for this path and batch")
            rows.append({"phase": "train", "label": label, "what": f"{label}: {why}", "seconds": math.nan,
                         "source": "speed table"})
            continue
        curve = f" + {points} curve points x {curve_frames} frames x {curve_ms:.0f} ms" if points else ""
        rows.append({"phase": "train", "label": label,
                     "what": f"{label}: {seeds} x ({train['steps']} steps x {rate['ms']:.1f} ms"
                     + (f" + compile {rate['compile_s']:.0f} s" if rate["compile_s"] else "") + curve + ")",
                     "seconds": seeds * (train["steps"] * rate["ms"] / 1000 + rate["compile_s"]
                                         + points * curve_frames * curve_ms / 1000),
                     "source": "speed table" + (", scoring timed here" if points else "")})
    frames = data["splits"][scored]["sequences"] * data["seq_len"]
    hr = f"{data['lr_width'] * data['scale']}x{data['lr_height'] * data['scale']}"
    evaluations = len(learned) * seeds + len(fixed)
    rows.append({"phase": "evaluate", "label": "scoring",
                 "what": f"{evaluations} evaluations x {frames} {scored} frames of {hr} x {score_ms:.0f} ms",
                 "seconds": evaluations * frames * score_ms / 1000,
                 "source": "scoring timed here"})
    return rows


def seconds_cell(seconds: float) -> str:
    return "-" if math.isnan(seconds) else f"{seconds:.0f}"


def claims_power(claims: Path, diff: float, seeds: int, sequences: int) -> list[float]:
    """Each claim pair's power at `diff` (PSNR) in the design, from its recorded variance components."""
    from bench.stats import power
    parts = pd.read_csv(claims)[["PSNR sd seed", "PSNR sd sequence", "PSNR sd residual"]].dropna()
    return [power(diff, *row, seeds, sequences) for row in parts.itertuples(index=False)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="gpu")
    parser.add_argument("--experiment", default="sota")
    parser.add_argument("--machine", default="cuda-nvidia-h200", help="the GPU records' device tag")
    parser.add_argument("--records", type=Path, default=ROOT / "results/gpu")
    parser.add_argument("--claims", type=Path, default=ROOT / "results/cpu/claims/table.csv",
                        help="variance components for the power (the cpu preset's claims)")
    parser.add_argument("--diff", type=float, default=0.1, help="PSNR difference (dB) the power is stated at")
    parser.add_argument("--budget", type=float, default=780.0, help="seconds of commands the speedrun has")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="Hydra overrides")
    parser.add_argument("--out", type=Path, help="also write the record here")
    args = parser.parse_args(argv)
    cfg = composed(args.preset, [f"+experiment={args.experiment}", *args.set])
    train, data = cfg["train"], cfg["data"]
    if train["precision"] != "fp32" or train["channels_last"] or train["compile"] not in PATHS:
        parser.error(f"no speed rows for train.precision={train['precision']}, channels_last={train['channels_last']}, "
                     f"compile={train['compile']}: the plan projects fp32, eager or reduce-overhead")
    import torch
    from bench.experiments.speed import _step_size   # the speed table's own label of a step's batch
    from bench.experiments.training import CURVE_SCORES
    from bench.machine import device_tag
    from bench.train import Recipe
    size = _step_size(Recipe.from_config(train))
    steps = step_rates(args.records / "speed" / args.machine, args.preset, size, PATHS[train["compile"]])
    render = render_rates(args.records / "data" / f"{args.machine}-render-probe.md")
    hr_hw = (data["lr_height"] * data["scale"], data["lr_width"] * data["scale"])
    learned, fixed, left_out = table_rows(cfg)
    rows = plan(cfg, render, steps, scoring_ms(hr_hw), scoring_ms(hr_hw, CURVE_SCORES), learned, fixed,
                models_not_timed(cfg, steps, learned))
    command = " ".join(["python scripts/gpu_speedrun_plan.py", *(argv if argv is not None else sys.argv[1:])])
    lines = [f"# {args.experiment} at preset {args.preset} on {args.machine}, projected", "",
             f"`{command}` (a lead, not a run: how each phase is projected is in the script's docstring); "
             f"training steps of {size}; scoring timed on {device_tag('cpu')} with {torch.get_num_threads()} threads"
             + (f"; left out, not importable here: {', '.join(f'{m} ({why})' for m, why in left_out.items())}"
                if left_out else "") + ".", "",
             "| phase | what | seconds | from |", "|---|---|---|---|"]
    lines += [f"| {row['phase']} | {row['what']} | {seconds_cell(row['seconds'])} | {row['source']} |" for row in rows]
    unmeasured = [row["label"] for row in rows if math.isnan(row["seconds"])]
    total = sum(row["seconds"] for row in rows if not math.isnan(row["seconds"]))
    lines += ["", f"total: {total:.0f} s ({total / 60:.1f} min) against a budget of {args.budget:.0f} s: "
              + ("fits" if total <= args.budget else f"over by {total - args.budget:.0f} s")
              + (f"; without {', '.join(unmeasured)}: not rated (the rows say why)" if unmeasured else "")]
    if render["workers"] and {"pass 1", "pass 2"} <= set(render["walls"]):
        n, wall = render["workers"]
        why_not = render_gain(render, cfg["workers"])[2]
        lines.append(f"rendering with {n} processes: the probe's {n}-process pass "
                     + ("(no kernel cache) " if render["workers_cold"] else "(Dr.Jit's kernel cache warm on disk) ")
                     + f"took {wall:.1f} s against one process's {render['walls']['pass 1']:.1f} s cold and "
                     f"{render['walls']['pass 2']:.1f} s warm (x{render['walls']['pass 1'] / wall:.2f} and "
                     f"x{render['walls']['pass 2'] / wall:.2f})" + (f"; not used: {why_not}" if why_not else ""))
    sequences, seeds = data["splits"][cfg["eval"]["split"]]["sequences"], len(cfg["seeds"])
    powers = sorted(claims_power(args.claims, args.diff, seeds, sequences))
    if powers:
        source = args.claims.relative_to(ROOT) if args.claims.is_relative_to(ROOT) else args.claims
        lines.append(f"power at {args.diff} dB, {seeds} seeds x {sequences} {cfg['eval']['split']} sequences, with the "
                     f"variance components of the {len(powers)} claim pairs in {source}: median "
                     f"{statistics.median(powers):.2f}, lowest {powers[0]:.2f}, highest {powers[-1]:.2f}")
    print("\n".join(lines))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

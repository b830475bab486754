"""What a table experiment costs at a preset on one GPU, projected from the committed GPU records: a lead
for sizing the preset to the speedrun (issue #62: Table 5 from a bare machine in 13 minutes, two calls),
not a run. Each phase names where its rate comes from:

- rendering: the render probe's seconds per buffer (`results/gpu/data/<machine>-render-probe.md`: the
  later frames' noisy passes as measured, the references scaled by each split's spp over the probe's, the
  frames by their pixels over the probe's) plus each sequence's first-frame set-up; divided by the probe's
  measured gain of `workers` processes at once when the preset renders with that many (else none);
- training: the speed table's training step (`results/gpu/speed/<machine>/table.csv`: the trainer's step
  at the preset's batch, frames and crop) on the path the preset trains (eager, or `train.compile`'s with
  its first call's compile, once per training: the Inductor cache on disk is not counted on), times steps
  and seeds; the learning curve's scoring every `val_every` steps;
- scoring: the metrics of one output frame (`bench.metrics.all_metrics`, on the host's CPU), timed here
  on random frames of the preset's HR size. Run on the GPU machine, it times that host; elsewhere it is
  an estimate that names the CPU it ran on. Inference on the GPU is left out (the speed table: about
  1 ms a frame at this size);
- the power of the claims' paired test at a difference (default 0.1 dB) with the preset's seeds and
  scored sequences, from each claim pair's PSNR variance components in `results/cpu/claims/table.csv`
  (seed, sequence, residual: docs/claims_statistics.md), Satterthwaite's df, two-sided 5%, before Holm.
  At the gpu preset's size the components are not known: the cpu preset's stand in.

Not in the projection: installing the wheels and starting Python (the job's log), decoding the training
frames into GPU memory, checkpoints, and OIDN (left out on the GPU image).

    python scripts/gpu_speedrun_plan.py                      # Table 5 at preset gpu on cuda-nvidia-h200
    python scripts/gpu_speedrun_plan.py --set train.steps=400 data.splits.test.sequences=30
"""
from __future__ import annotations

import argparse
import math
import re
import sys
import time
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from gpu_step_concurrency import composed  # noqa: E402

COMPILED = "fp32, compiled (reduce-overhead)"


def render_rates(record: Path) -> dict:
    """The render probe's measured rates: its frame size and spp, seconds per buffer of a later frame,
    the first frame's extra seconds per sequence, and its N-process pass's gain over one process."""
    text = record.read_text()
    size = re.search(r"(\d+)x(\d+) LR x(\d+), (\d+) spp, reference (\d+) spp", text)
    per_frame = re.search(r"per frame \(median[^)]*\): (.*); per sequence, the first frame's extra seconds "
                          r"in the first pass: ([\d.]+)", text)
    if not size or not per_frame:
        raise ValueError(f"{record}: no probe settings or per-buffer seconds (a PARTIAL record?)")
    buffers = {k: float(v) for k, v in re.findall(r"(\w+_s) ([\d.]+)", per_frame.group(1))}
    workers = re.search(r"by (\d+) processes at once.*?([\d.]+) frames/s against pass 1's ([\d.]+) in one", text)
    return {"lr": (int(size.group(1)), int(size.group(2))), "scale": int(size.group(3)), "spp": int(size.group(4)),
            "ref_spp": int(size.group(5)), "buffers": buffers, "setup_s": float(per_frame.group(2)),
            "workers": int(workers.group(1)) if workers else 1,
            "workers_gain": float(workers.group(2)) / float(workers.group(3)) if workers else 1.0}


def step_rates(table: Path) -> dict[str, dict]:
    """Per model label: its eager fp32 training step (ms), its graphed one and the seconds its first call
    compiled (from the row's note), as the speed table timed them."""
    rows = pd.read_csv(table)
    rows = rows[rows["section"] == "training step"]
    rates: dict[str, dict] = {}
    for _, row in rows.iterrows():
        rate = rates.setdefault(row["method"], {})
        if row["fast path"] == "fp32":
            rate["eager_ms"] = float(row["ms"])
        elif row["fast path"] == COMPILED:
            rate["compiled_ms"] = float(row["ms"])
            found = re.search(r"first call \(compile\) ([\d.]+) s", str(row["note"]))
            rate["compile_s"] = float(found.group(1)) if found else math.nan
    return rates


def scoring_ms(hr_hw: tuple[int, int], names=None, frames: int = 7) -> float:
    """Milliseconds to score one output frame of `hr_hw` with `bench.metrics.all_metrics` on this host's
    CPU (the second of two calls on a random sequence of `frames` frames)."""
    import torch
    from bench.metrics import all_metrics
    generator = torch.Generator().manual_seed(0)
    pred, ref = (2 * torch.rand(frames, 3, *hr_hw, generator=generator) for _ in range(2))
    all_metrics(pred, ref, names)
    start = time.perf_counter()
    all_metrics(pred, ref, names)
    return 1000 * (time.perf_counter() - start) / frames


def split_seconds(spec: dict, name: str, rates: dict, workers: int) -> tuple[float, str]:
    """A split's projected render seconds, and how they were projected."""
    part = spec["splits"][name]
    sequences, frames = int(part["sequences"]), int(part["sequences"]) * int(spec["seq_len"])
    ref_spp = int(part.get("ref_spp") or spec["ref_spp"])
    pixels = spec["lr_width"] * spec["lr_height"] / (rates["lr"][0] * rates["lr"][1])
    b = rates["buffers"]
    noisy = (b.get("lr_noisy_s", 0) + b.get("hr_noisy_s", 0)) * spec["spp"] / rates["spp"]
    ref = (b.get("lr_ref_s", 0) + b.get("hr_ref_s", 0)) * ref_spp / rates["ref_spp"]
    seconds = frames * pixels * (noisy + ref) + sequences * rates["setup_s"]
    gain = rates["workers_gain"] if workers == rates["workers"] else 1.0
    how = f"{sequences} sequences, {frames} frames, ref {ref_spp} spp" + (f", / {gain:.2f} ({workers} processes)"
                                                                           if gain != 1.0 else "")
    return seconds / gain, how


def power(diff: float, sd_seed: float, sd_sequence: float, sd_residual: float, seeds: int, sequences: int,
          alpha: float = 0.05) -> float:
    """Two-sided power of the paired test at `diff` for `seeds` x `sequences`, from variance components;
    df by Satterthwaite over the three terms (the claims' test caps it at the largest term's)."""
    from scipy import stats
    terms = [(sd_sequence ** 2 / sequences, sequences - 1), (sd_seed ** 2 / seeds, seeds - 1),
             (sd_residual ** 2 / (seeds * sequences), (seeds - 1) * (sequences - 1))]
    terms = [(v, df) for v, df in terms if v > 0 and df > 0]
    if not terms:
        return math.nan
    variance = sum(v for v, _ in terms)
    df = min(variance ** 2 / sum(v ** 2 / df for v, df in terms), max(terms)[1])
    critical = stats.t.ppf(1 - alpha / 2, df)
    shift = diff / math.sqrt(variance)
    return float(stats.nct.sf(critical, df, shift) + stats.nct.cdf(-critical, df, shift))


def plan(cfg: dict, render: dict, steps: dict[str, dict], score_ms: float, curve_ms: float) -> list[dict]:
    """The phases' projected seconds: rows of phase, what, seconds, source."""
    from bench.experiments.speed import LABELS
    from bench.models.factory import build_model, is_learned
    spec, train, experiment = cfg["data"], cfg["train"], cfg["experiment"]
    seeds = len(cfg["seeds"])
    eval_split = cfg["eval"]["split"] or ("test" if "test" in spec["splits"] else "val")
    curve = train["val_sequences"] > 0 and train["val_every"] > 0
    splits = ["train"] + (["val"] if curve and eval_split != "val" else []) + [eval_split]
    rows = []
    for name in splits:
        seconds, how = split_seconds(spec, name, render, cfg["workers"])
        rows.append({"phase": "render", "what": f"{name}: {how}", "seconds": seconds, "source": "render probe"})
    compiled = train.get("compile") == "reduce-overhead"
    hr = (spec["lr_height"] * spec["scale"], spec["lr_width"] * spec["scale"])
    curve_points = -(-train["steps"] // train["val_every"]) if curve else 0   # every val_every steps and the last
    curve_frames = min(train["val_sequences"], spec["splits"]["val"]["sequences"]) * spec["seq_len"]
    rows_models = [row["model"] for row in experiment["rows"]]
    learned = [m for m in rows_models if learned_model(build_model, is_learned, cfg["models"][m], spec["scale"])]
    for model in learned:
        label = LABELS.get(model, model)
        rate = steps.get(label, {})
        step_ms = rate.get("compiled_ms" if compiled else "eager_ms", math.nan)
        first = rate.get("compile_s", math.nan) if compiled else 0.0
        seconds = seeds * (train["steps"] * step_ms / 1000 + first + curve_points * curve_frames * curve_ms / 1000)
        rows.append({"phase": "train", "what": f"{label}: {seeds} x ({train['steps']} steps x {step_ms:.1f} ms"
                     + (f" + compile {first:.0f} s" if compiled else "")
                     + (f" + {curve_points} curve points x {curve_frames} frames" if curve else "") + ")",
                     "seconds": seconds, "source": "speed table" + (", this host's scoring" if curve else "")})
    frames = spec["splits"][eval_split]["sequences"] * spec["seq_len"]
    evaluations = len(learned) * seeds + len(rows_models) - len(learned)
    rows.append({"phase": "evaluate", "what": f"{evaluations} evaluations x {frames} frames of {hr[1]}x{hr[0]} "
                 f"x {score_ms:.0f} ms", "seconds": evaluations * frames * score_ms / 1000,
                 "source": "scoring timed on this host"})
    return rows


def learned_model(build_model, is_learned, model_cfg: dict, scale: int) -> bool:
    """Whether a row's model trains; one that cannot be built here (OIDN without pyoidn) does not."""
    try:
        return is_learned(build_model(model_cfg, scale))
    except Exception:
        return False


def claims_power(claims: Path, diff: float, seeds: int, sequences: int) -> list[float]:
    """Each claim pair's power at `diff` (PSNR) in the design, from its recorded variance components."""
    table = pd.read_csv(claims)
    parts = table[["PSNR sd seed", "PSNR sd sequence", "PSNR sd residual"]].dropna()
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
    render = render_rates(args.records / "data" / f"{args.machine}-render-probe.md")
    steps = step_rates(args.records / "speed" / args.machine / "table.csv")
    spec = cfg["data"]
    hr = (spec["lr_height"] * spec["scale"], spec["lr_width"] * spec["scale"])
    from bench.experiments.training import CURVE_SCORES
    from bench.machine import device_tag
    rows = plan(cfg, render, steps, scoring_ms(hr), scoring_ms(hr, CURVE_SCORES))
    total = sum(row["seconds"] for row in rows)
    import torch
    lines = [f"# {args.experiment} at preset {args.preset} on {args.machine}, projected", "",
             f"`python scripts/gpu_speedrun_plan.py {' '.join(argv if argv is not None else sys.argv[1:])}` "
             f"(a lead, not a run: how each phase is projected is in the script's docstring); scoring timed on "
             f"{device_tag('cpu')} with {torch.get_num_threads()} threads.", "",
             "| phase | what | seconds | from |", "|---|---|---|---|"]
    lines += [f"| {row['phase']} | {row['what']} | {row['seconds']:.0f} | {row['source']} |" for row in rows]
    lines += ["", f"total: {total:.0f} s ({total / 60:.1f} min) against a budget of {args.budget:.0f} s: "
              + ("fits" if total <= args.budget else f"over by {total - args.budget:.0f} s")]
    eval_split = cfg["eval"]["split"] or ("test" if "test" in spec["splits"] else "val")
    sequences, seeds = spec["splits"][eval_split]["sequences"], len(cfg["seeds"])
    powers = sorted(claims_power(args.claims, args.diff, seeds, sequences))
    if powers:
        source = args.claims.relative_to(ROOT) if args.claims.is_relative_to(ROOT) else args.claims
        lines.append(f"power at {args.diff} dB, {seeds} seeds x {sequences} {eval_split} sequences, with the variance "
                     f"components of the {len(powers)} claim pairs in {source}: median {powers[len(powers) // 2]:.2f}, "
                     f"lowest {powers[0]:.2f}, highest {powers[-1]:.2f}")
    print("\n".join(lines))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

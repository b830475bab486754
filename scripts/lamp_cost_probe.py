"""Where the lamps' cost lies (docs/studies.md, emitters_causes), and what exposure_pass passes: four probes.

    PYTHONPATH=$PWD .venv/bin/python scripts/lamp_cost_probe.py bins library,living_room RUN...
    PYTHONPATH=$PWD .venv/bin/python scripts/lamp_cost_probe.py gradients RUN [ITEMS]
    PYTHONPATH=$PWD .venv/bin/python scripts/lamp_cost_probe.py passed [SPLIT]
    PYTHONPATH=$PWD .venv/bin/python scripts/lamp_cost_probe.py knee [VALUE] [ITEMS] [FRAMES]

`bins`: each training's outputs on the val sequences whose names start with one of the given prefixes,
binned by the HR reference's luminance (linear radiance): per bin its share of the pixels, the mean
signed error and the mean squared error on images clamped to [0, 1] (PSNR's domain), and the outputs'
sum over the reference's. A bias shows as a signed error comparable to the root of the squared one;
noise left in shows as a squared error far above the signed error's square.

`gradients`: the norm of the loss's gradient (the cpu preset's recipe) for ITEMS training items, each as
drawn and with a lamp pasted (bench.emitters.with_emitter), per loss term; the medians and the median
ratio. A lamp item whose gradient is several times an item's without would take over the clipped step.

`passed`: the share of a split's LR pixels (default val) that exposure_pass passes through in part
(bench.exposure.highlights above 0) and whole (1): what the network does not see trained or scored.

`knee`: what the two candidate causes of emitters_causes act on. The radiance, as a multiple of the
exposure, at network-domain VALUE (default 2, `train.loss_knee=2`) in the exposure domain; the values a
lamp encodes to (bench.emitters.LOG10_LEVEL, 10x to 3e4x the exposure); the share of the HR reference's
values and pixels above VALUE on the first FRAMES frames of the training split, each at its own
exposure; and how much a pasted lamp raises a training crop's exposure (ITEMS items, median and range).

RUN: a training's hash, from the run store (runs/) or the committed archive (bench.weights.export).
Both need the cpu dataset (`python -m bench +experiment=data preset=cpu`).
"""
from __future__ import annotations

import argparse
import random
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

import bench.losses
from bench.cli import CONF_DIR, make_context
from bench.emitters import LOG10_LEVEL, first_frame_exposure, with_emitter
from bench.errors import UserError
from bench.evaluate import predict
from bench.exposure import decode, encode, frame_exposure, highlights
from bench.experiments.datasets import dataset
from bench.sanitize import sanitize_radiance
from bench.tasks import get_task
from bench.train import batch_loss
from bench.weights import export, load_exported

EDGES = [0, 0.003, 0.01, 0.03, 0.1, 0.3, 0.6, 1.0, np.inf]   # HR reference luminance
TERMS = ("spatial", "edge", "temporal", "ssim")


def _context():
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        return make_context(compose("config", overrides=["preset=cpu", "render_data=false", "device=cpu"]))


def _model(run: str, runs_dir: Path):
    model, meta = load_exported(export(run, Path(tempfile.mkdtemp()) / f"{run}.pt", runs_dir))
    return model, meta["hdr"]


def _with_lamps(data, task, items: int):
    """`items` training items, each as drawn and with a lamp pasted (the same draws in every probe)."""
    for i in range(items):
        item = data.item(random.Random(i).randrange(len(data)), i)
        yield item, with_emitter(item, task, random.Random(f"lamp {i}"))


def bins(prefixes: str, run_hashes: list[str]) -> None:
    ctx, task = _context(), get_task("srd")
    data = dataset(ctx, "val", task, training=False)
    chosen = [i for i, item in enumerate(data.items) if item[0].startswith(tuple(prefixes.split(",")))]
    for run in run_hashes:
        model, hdr = _model(run, ctx.runs_dir)
        model.eval()
        sums = {}   # sequence -> (bins, [pixels, signed, squared, output, reference])
        for i in chosen:
            item = data[i]
            with torch.no_grad():
                out = predict(model, item[task.x][None], item[task.g][None], hdr)[0].double().numpy()
            ref = item[task.y].double().numpy()
            luminance = np.repeat(ref.mean(1, keepdims=True), 3, 1)
            diff = np.clip(out, 0, 1) - np.clip(ref, 0, 1)
            acc = sums.setdefault(data.items[i][0], np.zeros((len(EDGES) - 1, 5)))
            for b in range(len(EDGES) - 1):
                m = (luminance >= EDGES[b]) & (luminance < EDGES[b + 1])
                acc[b] += [m.sum(), diff[m].sum(), (diff[m] ** 2).sum(), out[m].sum(), ref[m].sum()]
        for sequence, acc in sums.items():
            print(f"{run} {sequence}: PSNR of the pooled pixels {10 * np.log10(acc[:, 0].sum() / acc[:, 2].sum()):.2f}")
            for b, (n, signed, squared, out_sum, ref_sum) in enumerate(acc):
                if n:
                    print(f"  [{EDGES[b]:g}, {EDGES[b + 1]:g}) share {n / acc[:, 0].sum():.3f} signed {signed / n:+.5f} "
                          f"squared {squared / n:.2e} output/reference {out_sum / max(ref_sum, 1e-12):.3f}")


def gradients(run: str, items: int = 16) -> None:
    ctx, task = _context(), get_task("srd")
    data = dataset(ctx, "train", task, training=True)
    model, hdr = _model(run, ctx.runs_dir)
    model.train()
    keys, weights = task.buffers(with_mid=True), ctx.train.loss
    norm = sum(weights["final"].get(t, 0) for t in ("edge", "temporal", "spatial"))
    # one term at a time, at its weight in the whole loss (absolute_weights would renormalise the term alone)
    bench.losses.absolute_weights = lambda w: {k: v / norm for k, v in w.items()}

    def grad_norm(item, only=None):
        chosen = {stage: {k: v for k, v in w.items() if only is None or k == only} for stage, w in weights.items()}
        model.zero_grad()
        batch_loss(model, {k: item[k][None] for k in keys}, task, chosen, hdr)[0].backward()
        return float(torch.sqrt(sum((p.grad.double() ** 2).sum() for p in model.parameters() if p.grad is not None)))

    rows = {t: [] for t in (*TERMS, "all")}
    for item, lamp in _with_lamps(data, task, items):
        for term in rows:
            only = None if term == "all" else term
            rows[term].append((grad_norm(item, only), grad_norm(lamp, only)))
    print(f"{run} ({hdr}), {items} items, gradient norm as drawn / with a lamp:")
    for term, pairs in rows.items():
        plain, lamp = zip(*pairs)
        print(f"  {term:9s} median {statistics.median(plain):.3f} / {statistics.median(lamp):.3f}, "
              f"median ratio {statistics.median(b / a for a, b in pairs):.2f}")


def passed(split: str = "val") -> None:
    ctx, task = _context(), get_task("srd")
    data = dataset(ctx, split, task, training=False)
    pixels = part = whole = 0
    for i in range(len(data)):
        x = sanitize_radiance(data[i][task.x][:, :3])  # as predict sanitizes its input
        w = highlights(encode(x, "exposure_pass", frame_exposure(x, "exposure_pass")))
        pixels, part, whole = pixels + w.numel(), part + int((w > 0).sum()), whole + int((w == 1).sum())
    print(f"{split}: {pixels} LR pixels, passed in part {part / pixels:.4%}, whole {whole / pixels:.4%}")


def knee(value: float = 2.0, items: int = 64, frames: int = 60) -> None:
    ctx, task = _context(), get_task("srd")
    unit = torch.ones(1, 1, 1, 1)
    multiple = float(decode(torch.full((1, 1, 1, 1), value), "exposure", unit))
    lamps = [float(encode(torch.full((1, 1, 1, 1), 10.0 ** e), "exposure", unit)) for e in LOG10_LEVEL]
    print(f"network-domain value {value:g} (exposure domain) = radiance {multiple:.2f}x the frame's exposure; "
          f"a lamp of {10 ** LOG10_LEVEL[0]:g}x to {10 ** LOG10_LEVEL[1]:.3g}x encodes to {lamps[0]:.2f}-{lamps[1]:.2f}")
    whole = dataset(ctx, "train", task, training=False)
    seen = values_above = pixels_above = values = pixels = 0
    for i in range(len(whole)):
        item = whole[i]
        x, y = item[task.x][:, :3], item[task.y][:, :3]
        encoded = encode(y, "exposure", frame_exposure(x, "exposure"))[:frames - seen]
        values_above, values = values_above + int((encoded > value).sum()), values + encoded.numel()
        pixels_above = pixels_above + int((encoded > value).any(-3).sum())
        pixels, seen = pixels + encoded[:, 0].numel(), seen + len(encoded)
        if seen >= frames:
            break
    print(f"train, first {seen} frames at their own exposure: HR reference above {value:g}: "
          f"{values_above / values:.2%} of the values, {pixels_above / pixels:.2%} of the pixels (any channel)")
    data = dataset(ctx, "train", task, training=True)
    raises = [first_frame_exposure(lamp[task.x]) / first_frame_exposure(item[task.x])
              for item, lamp in _with_lamps(data, task, items)]
    print(f"{items} training crops ({ctx.train.crop} LR px) with a lamp pasted: exposure raised "
          f"{statistics.median(raises):.2f}x (median), {min(raises):.2f}-{max(raises):.2f}x")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    by_bin = commands.add_parser("bins", help="outputs' error by the reference's radiance")
    by_bin.add_argument("prefixes", help="val sequence name prefixes, comma-separated (library,living_room)")
    by_bin.add_argument("runs", nargs="+", help="training hashes")
    grads = commands.add_parser("gradients", help="gradient norms of items with and without a lamp")
    grads.add_argument("run", help="a training hash")
    grads.add_argument("items", nargs="?", type=int, default=16)
    share = commands.add_parser("passed", help="share of LR pixels exposure_pass passes through")
    share.add_argument("split", nargs="?", default="val")
    at_knee = commands.add_parser("knee", help="what the loss knee and the lamp's exposure act on")
    at_knee.add_argument("value", nargs="?", type=float, default=2.0)
    at_knee.add_argument("items", nargs="?", type=int, default=64)
    at_knee.add_argument("frames", nargs="?", type=int, default=60)
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        if args.command == "bins":
            bins(args.prefixes, args.runs)
        elif args.command == "gradients":
            gradients(args.run, args.items)
        elif args.command == "knee":
            knee(args.value, args.items, args.frames)
        else:
            passed(args.split)
    except UserError as err:  # a mistyped hash, data not rendered: one line, as `python -m bench` says it
        sys.exit(f"error: {err}")

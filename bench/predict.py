"""A trained model outside the benchmark: export a recorded run's weights, apply them to your EXR frames.

    srd-bench export RUN_HASH --out results/cpu/weights/ours.pt      (or python -m bench.predict export ...)
    srd-bench predict --weights results/cpu/weights/ours.pt --output-dir out/ frame0_lr.exr frame1_lr.exr

`export` writes the exported weights file (`bench.weights`, which says what it holds); `predict` checks
its sha256 against the JSON beside it.

`predict` reads each input EXR's layers `noisy` (LR radiance), `albedo`, `normal` and `roughness` (the
dataset layout's `*_lr.exr`; roughness may be left out: 1.0), treats the inputs as one sequence in the
order given (a recurrent model keeps its state from frame to frame) and writes `<name>_hr.exr` with the
layer `output` (linear HDR radiance at the model's scale). Non-finite input values are repaired as in
every evaluation (bench.sanitize) and counted in the output's header (`srd_nonfinite_repaired`).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

from bench import exrio
from bench.dataset import DEFAULT_ROUGHNESS, GBUF_SIZES
from bench.errors import UserError
from bench.evaluate import predict as predict_batch
from bench.evaluate import runner
from bench.infer import REFERENCE
from bench.measure import AUTO, choose_fast_path
from bench.tasks import GBUF_LAYERS
from bench.weights import export, from_run, load_exported


def fast_path_cache() -> Path:
    """Where predict remembers the fast path it measured ($XDG_CACHE_HOME, else ~/.cache)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "srd-bench" / "fast_paths.json"


# ---------------------------------------------------------------- predict

def read_frame(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """(radiance (3, h, w), gBuffer (7, h, w)) of one LR frame in the dataset layout's `*_lr.exr`."""
    path = Path(path)
    layers = exrio.exr_layers(path)
    missing = [name for name in ("noisy", "albedo", "normal") if name not in layers]
    if missing:
        raise UserError(f"{path}: missing layers {missing} (has {layers}); an input frame needs `noisy` "
                        "(LR radiance), `albedo`, `normal` and optionally `roughness`")
    wanted = ["noisy", "albedo", "normal"] + (["roughness"] if "roughness" in layers else [])
    images = exrio.read_exr(path, wanted)
    h, w = images["noisy"].shape[:2]
    planes = []
    for name in GBUF_LAYERS:
        image = images.get(name, np.full((h, w, 1), DEFAULT_ROUGHNESS, np.float32))
        if image.shape[:2] != (h, w) or image.shape[2] != GBUF_SIZES[name]:
            raise UserError(f"{path}: layer {name} is {image.shape[1]}x{image.shape[0]}x{image.shape[2]}, "
                            f"expected {w}x{h}x{GBUF_SIZES[name]} (the gBuffer is at the radiance's resolution)")
        planes.append(image)
    if images["noisy"].shape[2] != 3:
        raise UserError(f"{path}: layer noisy has {images['noisy'].shape[2]} channels, expected RGB")
    to_tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))
    return to_tensor(images["noisy"]), to_tensor(np.concatenate(planes, -1))


def apply(model, meta: dict, inputs: list, output_dir: str | Path, tile: int | None = None,
          fast_path: str = REFERENCE) -> list[Path]:
    """Run `model` on the frames `inputs` (one sequence, in order) and write one HR EXR per frame.
    `fast_path`: a path of bench.infer, or "auto" (the fastest correct one here, bench.measure, its
    choice cached in `fast_path_cache()`)."""
    if not inputs:
        raise UserError("no input frames given")
    frames = [read_frame(p) for p in inputs]
    sizes = {tuple(x.shape[1:]) for x, _ in frames}
    if len(sizes) > 1:
        raise UserError(f"the input frames are one sequence and must share one size; got {sorted(sizes)}")
    x = torch.stack([f[0] for f in frames])[None]     # (1, T, 3, h, w)
    g = torch.stack([f[1] for f in frames])[None]
    repaired = [int((~torch.isfinite(f[0])).sum() + (~torch.isfinite(f[1])).sum()) for f in frames]
    if fast_path == AUTO:
        first = (x, g) if getattr(model, "recurrent", False) else (x[:, :1], g[:, :1])
        fast_path, times = choose_fast_path(model, *first, "cpu", fast_path_cache(), {"model": meta["model"]})
        print(f"fast path: {fast_path} " + " ".join(f"({k} {v:.0f} ms)" if isinstance(v, float) else f"({k}: {v})"
                                                    for k, v in times.items()), file=sys.stderr)
    forward = runner(model, path=fast_path, tile=tile)
    with torch.no_grad():
        if getattr(model, "recurrent", False):
            out = predict_batch(model, x, g, meta["hdr"], forward=forward)
        else:  # frame by frame: bounded memory, same result
            out = torch.cat([predict_batch(model, x[:, t:t + 1], g[:, t:t + 1], meta["hdr"], forward=forward)
                             for t in range(x.shape[1])], 1)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for t, source in enumerate(inputs):
        target = output_dir / (Path(source).name.removesuffix(".exr").removesuffix("_lr") + "_hr.exr")
        exrio.write_exr(target, {"output": out[0, t].permute(1, 2, 0).numpy().astype(np.float32)},
                        attributes={"srd_weights": str(meta.get("run")), "srd_nonfinite_repaired": str(repaired[t]),
                                    "srd_model": meta["model"]["_target_"]})
        written.append(target)
    return written


# ---------------------------------------------------------------- command line

def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="srd-bench", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    ex = commands.add_parser("export", help="write a recorded training run's weights to a file")
    ex.add_argument("run", help="training run hash (runs/train/<hash>)")
    ex.add_argument("--out", required=True, help="weights file to write (.pt); a .json lands beside it")
    ex.add_argument("--runs-dir", default="runs")
    pr = commands.add_parser("predict", help="apply trained weights to LR EXR frames")
    source = pr.add_mutually_exclusive_group(required=True)
    source.add_argument("--weights", help="an exported weights file")
    source.add_argument("--run", help="a recorded training run hash")
    pr.add_argument("--runs-dir", default="runs")
    pr.add_argument("--output-dir", required=True)
    pr.add_argument("--tile", type=int, default=None, help="LR pixels per tile (bounded memory on large frames)")
    pr.add_argument("--fast-path", default=AUTO, help="fp32, a bench.infer path (channels_last, bf16, ...) or auto "
                                                      "(default: the fastest correct one on this machine, measured once)")
    pr.add_argument("inputs", nargs="+", help="LR frames (*_lr.exr), one sequence in order")
    args = parser.parse_args(argv)
    try:
        if args.command == "export":
            print(export(args.run, args.out, args.runs_dir))
            return 0
        model, meta = load_exported(args.weights) if args.weights else from_run(args.run, args.runs_dir)
        for path in apply(model, meta, args.inputs, args.output_dir, args.tile, args.fast_path):
            print(path)
        return 0
    except (UserError, exrio.ExrError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

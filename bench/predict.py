"""A trained model outside the benchmark: export a recorded run's weights, apply them to your EXR frames.

    srd-bench export RUN_HASH --out results/cpu/weights/ours.pt      (or python -m bench.predict export ...)
    srd-bench predict --weights results/cpu/weights/ours.pt --output-dir out/ frame0_lr.exr frame1_lr.exr
    srd-bench predict --weights results/cpu/weights/ours.pt --output-dir out/ data/cpu/val    (folders)
    srd-bench score --outputs out/ --data data/cpu --split val --label NAME                (bench.score)

`export` writes the exported weights file (`bench.weights`, which says what it holds); `predict` checks
its sha256 against the JSON beside it.

`predict` reads each input EXR's layers `noisy` (LR radiance), `albedo`, `normal` and `roughness` (the
dataset layout's `*_lr.exr`; roughness may be left out: 1.0). An input is a file or a folder: each folder
holding `*_lr.exr` files (the folder given or any folder below it) is one sequence, its frames in name
order; files given one by one form one sequence per folder they lie in, in the order given. A recurrent
model keeps its state from frame to frame within a sequence and starts afresh at the next one. Each
frame gives `<name>_hr.exr` with the layer `output` (linear HDR radiance at the model's scale), under
--output-dir at the frame's place in the input tree (relative to the folder given; files given one by
one, relative to the folder their folders share). Two frames that would write one file, or an output that
would replace a file that is not a predict output (a dataset's `*_hr.exr` references), stop the command
before anything runs. Non-finite input values are repaired as in every evaluation (bench.sanitize): each
repair is printed and counted in the output's header (`srd_nonfinite_repaired`); a frame with more than
`--max-nonfinite` of its pixels non-finite is refused unless `--accept-nonfinite`. Outputs get the
file mode the umask gives.

`srd-bench score` (bench.score) scores a folder of outputs, these or any method's, against a dataset.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

from bench import exrio, score
from bench.runs import PATH_ERRORS, error_line
from bench.datagen import MAX_NONFINITE  # the share the table's eval.data_dir check allows too
from bench.dataset import DEFAULT_ROUGHNESS, GBUF_SIZES
from bench.errors import UserError
from bench.evaluate import predict as predict_batch
from bench.evaluate import runner
from bench.infer import REFERENCE, parse_path
from bench.measure import AUTO, choose_fast_path, fused_kernels_on_cuda
from bench.tasks import GBUF_LAYERS, get_task
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




def output_name(frame: Path) -> str:
    """`0000_lr.exr` -> `0000_hr.exr` (any other name: `<stem>_hr.exr`)."""
    return frame.name.removesuffix(".exr").removesuffix("_lr") + "_hr.exr"


def _lr_frames(folder: Path) -> dict[Path, list[Path]]:
    """Each folder at or below `folder` that holds `*_lr.exr` files -> those files in name order."""
    found: dict[Path, list[Path]] = {}
    for frame in sorted(folder.rglob("*_lr.exr")):
        if frame.is_file():
            found.setdefault(frame.parent, []).append(frame)
    if not found:
        raise UserError(f"{folder}: no *_lr.exr frames in it or below it")
    return dict(sorted(found.items()))


def plan(inputs: list, output_dir: str | Path) -> list[tuple[list[Path], list[Path]]]:
    """The sequences to run, [(frames, output files)], in order (see the module docstring). Raises a
    UserError, before anything runs, for a missing input, two frames writing one file, or an output
    that would replace a file other than an earlier output of predict."""
    if not inputs:
        raise UserError("no input frames given")
    output_dir = Path(output_dir)
    sequences, files = [], {}
    for given in map(Path, inputs):
        if given.is_dir():
            sequences += [(frames, [output_dir / folder.relative_to(given) / output_name(f) for f in frames])
                          for folder, frames in _lr_frames(given).items()]
        elif given.is_file():
            files.setdefault(given.parent, []).append(given)
        else:
            raise UserError(f"input {given} does not exist (give *_lr.exr files or folders of them)")
    if files:
        root = Path(os.path.commonpath([str(folder.resolve()) for folder in files]))
        sequences += [(frames, [output_dir / folder.resolve().relative_to(root) / output_name(f) for f in frames])
                      for folder, frames in files.items()]
    writers: dict[Path, Path] = {}
    inputs_resolved = {f.resolve() for frames, _ in sequences for f in frames}
    for frames, targets in sequences:
        for frame, target in zip(frames, targets):
            key = target.resolve()
            if key in writers:
                raise UserError(f"{writers[key]} and {frame} would both write {target}: give their folders "
                                "(each folder one sequence, its outputs in its own folder) or rename one")
            if key in inputs_resolved:
                raise UserError(f"{frame} would write its output over the input {target}: choose another --output-dir")
            if target.exists() and exrio.exr_layers(target) != ["output"]:
                raise UserError(f"{frame} would write {target}, which exists and is not an output of predict "
                                f"(its layers: {exrio.exr_layers(target)}): choose another --output-dir")
            writers[key] = frame
    return sequences


def nonfinite(x: torch.Tensor, g: torch.Tensor) -> tuple[int, float]:
    """(non-finite values, share of pixels with at least one) of one frame's radiance and gBuffer."""
    bad = torch.cat([~torch.isfinite(x), ~torch.isfinite(g)])
    return int(bad.sum()), float(bad.any(0).float().mean())


def read_sequence(frames: list[Path], max_nonfinite: float | None) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The frames of one sequence; one size for all, and no frame with more than `max_nonfinite` of its
    pixels non-finite (None: any share is repaired)."""
    read = [read_frame(f) for f in frames]
    sizes = {tuple(x.shape[1:]) for x, _ in read}
    if len(sizes) > 1:
        raise UserError(f"the frames of one sequence must share one size; {frames[0].parent} has {sorted(sizes)}")
    for frame, (x, g) in zip(frames, read):
        share = nonfinite(x, g)[1]
        if max_nonfinite is not None and share > max_nonfinite:
            raise UserError(f"{frame}: {share:.1%} of its pixels are non-finite (NaN or Inf), over the "
                            f"{max_nonfinite:.1%} predict repairs; fix the frame, or repair them anyway with "
                            "--accept-nonfinite")
    return read


def task_notice(task_name: str) -> str | None:
    """What outputs mean when the weights were not trained for predict's task (noisy LR in, clean HR out)."""
    if task_name == "srd":
        return None
    try:
        task = get_task(task_name)
    except KeyError:  # a newer suite's task, or an edited file
        return (f"note: these weights were trained for the task {task_name!r}, which this version does not know; "
                "predict gives them each frame's `noisy` layer as for srd")
    size = f"at {task.scale}x the input's size" if task.scale > 1 else "at the input's size, not super-resolved"
    trained_on = "noise-free" if task.x.endswith("_ref") else "noisy"
    target = "noisy" if task.y.endswith("_noisy") else "clean"
    return (f"note: these weights were trained for the task {task_name!r} ({trained_on} {task.x} in, {target} "
            f"output {size}), not srd; predict gives them each frame's `noisy` layer as it is")


def file_mode() -> int:
    """The mode a new file gets under this process's umask (0666 minus it)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def apply(model, meta: dict, inputs: list, output_dir: str | Path, tile: int | None = None,
          fast_path: str = REFERENCE, max_nonfinite: float | None = MAX_NONFINITE) -> list[Path]:
    """Run `model` on the frames and folders `inputs` (see the module docstring: sequences, output
    names) and write one HR EXR per frame. Every input is read and checked before the first output is
    written. `fast_path`: a path of bench.infer, or "auto" (the fastest correct one here, bench.measure,
    its choice cached in `fast_path_cache()`)."""
    sequences = plan(inputs, output_dir)
    for frames, _ in sequences:
        read_sequence(frames, max_nonfinite)
    recurrent, mode, written, forward = getattr(model, "recurrent", False), file_mode(), [], None
    for frames, targets in sequences:
        read = read_sequence(frames, max_nonfinite)
        x = torch.stack([f[0] for f in read])[None]     # (1, T, 3, h, w)
        g = torch.stack([f[1] for f in read])[None]
        if forward is None:
            if fast_path == AUTO:
                first = (x, g) if recurrent else (x[:, :1], g[:, :1])
                fast_path, times = choose_fast_path(model, *first, "cpu", fast_path_cache(), {"model": meta["model"]})
                print(f"fast path: {fast_path} " + " ".join(f"({k} {v:.0f} ms)" if isinstance(v, float) else f"({k}: {v})"
                                                            for k, v in times.items()), file=sys.stderr)
            forward = runner(model, path=fast_path, tile=tile) or model
        with torch.no_grad():  # one call per sequence: a recurrent model's state starts afresh
            if recurrent:
                out = predict_batch(model, x, g, meta["hdr"], forward=forward)
            else:  # frame by frame: bounded memory, same result
                out = torch.cat([predict_batch(model, x[:, t:t + 1], g[:, t:t + 1], meta["hdr"], forward=forward)
                                 for t in range(x.shape[1])], 1)
        for t, (source, target) in enumerate(zip(frames, targets)):
            repaired, share = nonfinite(*read[t])
            if repaired:
                print(f"{source}: repaired {repaired} non-finite input values ({share:.2%} of its pixels) "
                      "as every evaluation does (bench.sanitize)", file=sys.stderr)
            exrio.write_exr(target, {"output": out[0, t].permute(1, 2, 0).numpy().astype(np.float32)},
                            attributes={"srd_weights": str(meta.get("run")), "srd_nonfinite_repaired": str(repaired),
                                        "srd_model": meta["model"]["_target_"]})
            os.chmod(target, mode)   # exrio writes through a private temporary file (0600)
            written.append(target)
    return written


# ---------------------------------------------------------------- command line

class _Parser(argparse.ArgumentParser):
    """A bad argument is one line (and exit 2), like every other mistake predict reports."""

    def error(self, message):
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")


def positive_int(text: str) -> int:
    value = int(text) if text.lstrip("+").isdigit() else 0
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of pixels")
    return value


def share(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a share between 0 and 1")
    return value


def check_fast_path(fast_path: str, tile: int | None) -> None:
    if fast_path == AUTO:
        return
    try:
        path = parse_path(fast_path)
    except ValueError as err:
        raise UserError(f"--fast-path: {err}") from err
    if tile and path.compile:
        raise UserError(f"--fast-path {fast_path} compiles the model, which --tile does not support "
                        "(border tiles change shape); leave one out")


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog="srd-bench", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    ex = commands.add_parser("export", help="write a recorded training run's weights to a file")
    ex.add_argument("run", help="training run hash (runs/train/<hash>)")
    ex.add_argument("--out", required=True, help="weights file to write (.pt); a .json lands beside it")
    ex.add_argument("--runs-dir", default="runs")
    ex.add_argument("--force", action="store_true", help="replace --out (and its .json) if they exist")
    pr = commands.add_parser("predict", help="apply trained weights to LR EXR frames and folders of them")
    source = pr.add_mutually_exclusive_group(required=True)
    source.add_argument("--weights", help="an exported weights file")
    source.add_argument("--run", help="a recorded training run hash")
    pr.add_argument("--runs-dir", default="runs")
    pr.add_argument("--output-dir", required=True, help="outputs go here, at their frames' places in the input tree")
    pr.add_argument("--tile", type=positive_int, default=None,
                    help="LR pixels per tile (bounded memory on large frames)")
    pr.add_argument("--fast-path", default=AUTO, help="fp32, a bench.infer path (channels_last, bf16, ...) or auto "
                                                      "(default: the fastest correct one on this machine, measured once)")
    pr.add_argument("--max-nonfinite", type=share, default=MAX_NONFINITE,
                    help=f"largest share of a frame's pixels that may be NaN/Inf and be repaired (default {MAX_NONFINITE})")
    pr.add_argument("--accept-nonfinite", action="store_true", help="repair any share of non-finite pixels")
    pr.add_argument("inputs", nargs="+", help="LR frames (*_lr.exr) and folders of them: each folder one sequence")
    score.add_parser(commands)
    args = parser.parse_args(argv)
    try:
        if args.command == "export":
            print(export(args.run, args.out, args.runs_dir, args.force))
            return 0
        if args.command == "score":
            return score.run(args)
        check_fast_path(args.fast_path, args.tile)
        model, meta = load_exported(args.weights) if args.weights else from_run(args.run, args.runs_dir)
        limit = None if args.accept_nonfinite else args.max_nonfinite
        notice = task_notice(meta.get("task", "srd"))
        if notice:
            print(notice, file=sys.stderr)
        with fused_kernels_on_cuda():
            for path in apply(model, meta, args.inputs, args.output_dir, args.tile, args.fast_path, limit):
                print(path)
        return 0
    except (UserError, exrio.ExrError, *PATH_ERRORS) as err:
        print(f"error: {error_line(err)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

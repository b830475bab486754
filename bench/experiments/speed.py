"""`+experiment=speed`: how fast every learned model runs on THIS machine, against reference points
measured in the same run (issue #8).

Per model (the configured widths of ctx.models), one LR frame at `input_hw` (default 960x540 in,
1920x1080 out), each fast path of bench.infer (fp32 reference, inference_mode, channels_last, bf16,
compile): warm ms per frame (median, min, max of `repeats` calls after `warmup`), achieved GMac/s
(analytic MACs of bench.macs counted on the meta device, divided by the median time), peak memory of
one call, and the largest difference from the fp32 output (every fast path is checked in the run that
times it). Then one step of the trainer (bench.train: HDR encode, forward, loss, backward, gradient
clip, Adam, EMA) at the training crop.

Reference points, same run, same threads: Intel OIDN (pyoidn, albedo + normal) denoising one frame at
the OUTPUT size; a plain stack of 3x3 convs + ReLU with the proposed model's MACs at the same input
size, per fast path (what the hardware gives a dense conv net of that cost); a plain nn.Conv2d next to
the deformable conv at realistic layer shapes. The headline ratios are model time / OIDN time and model
GMac/s / conv-stack GMac/s. Tiled inference (bench.infer.tiled_predict) is checked against untiled
inference at the input size and timed at a 4K output (3840x2160) with its peak memory.

Times are wall clock (CUDA synchronised); peak memory on CPU is the rise of the process's peak
resident set (VmHWM, reset through /proc/self/clear_refs after malloc_trim) during one call, on CUDA
torch.cuda.max_memory_allocated above what was allocated before. Weights are the untrained init plus
N(0, `perturb`) noise on every parameter: timings do not depend on trained values, and the noise makes
the zero-initialised branches (CFM, deformable offsets, residual output convs) compute, which the
tiling check needs. The differences from fp32 do depend on them, and so does the path auto picks (it
refuses a path whose output strays, which a path may do on untrained weights and not on trained ones):
`weights` gives a model its exported trained weights (`srd-bench export`) for every row.

Writes `<results_dir>/speed/<device tag>/table.{csv,md,tex}`: keyed by preset (the widths) and by
machine and its ISA (e.g. `results/cpu/speed/cpu-amd-epyc-avx2/`), since a speed table describes one machine.
Each model's inference rows say which path `fast_path=auto` (bench.measure.choose_fast_path) picks
here, and whether that is the fastest of the paths this table measured: a benchmark check of the chooser.
"""
from __future__ import annotations

import copy
import functools
import hashlib
import itertools
import json
import logging
import os
import re
import statistics
import time
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import pandas as pd
import torch
import torch.nn as nn

from bench import runs
from bench.atomic import write_atomic
from bench.errors import UserError
from bench.evaluate import sync
from bench.infer import (REFERENCE, frames_channels_last, freed_memory_kept, max_abs_diff, parse_path, prepare, release_free_memory,
                         tiled_predict)
from bench.experiments.macs import frame_inputs, frame_macs
from bench.macs import macs_at
from bench.machine import cpu_identity, cpu_isa, cpu_model, device_tag, gpu_model, isa_tag
from bench.measure import FUSED_GPU, candidate_paths, choose_fast_path, error_summary, time_call
from bench.models.factory import build_model, is_learned
from bench.nn import DeformConv2d, eager_gather, fused, grid_sample_training, inference_sampler, training_sampler
from bench.table_writer import PARTIAL_CAPTION, write_table
from bench.tasks import get_task
from bench.train import Recipe, batch_loss, compiled_as, step_loss, training_start, update_weights
from bench.weights import load_exported

log = logging.getLogger("bench")

LABELS = {"srd": "Ours", "edsr": "EDSR", "rae": "RAE", "kpcn": "KPCN", "cfm": "CFM"}
PATHS = ["fp32", "inference_mode", "channels_last", "bf16"]
COLUMNS = ["section", "method", "fast path", "size", "per", "ms", "ms min", "ms max", "GMac", "GMac/s",
           "peak MiB", "time / OIDN", "GMac/s / conv stack", "step / conv stack step", "time / plain conv",
           "max abs diff",
           "max rel diff", "note"]
# beside a PARTIAL table: the rows of its finished sections and the settings they were timed with, read by
# the next run of the same settings, which times only the rest (kept_sections); removed once it is whole
PARTIAL_SECTIONS = "partial_sections.json"


# ------------------------------------------------------------------------------ machine

def machine_caption(device: str) -> str:
    """Device, ISA, library and thread settings of this run, for the caption."""
    if str(device).startswith("cuda"):
        # the host CPU runs the Python and the launches (and OIDN's row): its ISA belongs to the figures too
        where = (f"{gpu_model(device)} (CUDA {torch.version.cuda}), host CPU "
                 f"{cpu_model().strip()}{_identified()}, {cpu_isa()}")
    else:
        where = (f"{device_tag(device)[4:].removesuffix('-' + isa_tag())} CPU{_identified()}, {cpu_isa()}, {torch.get_num_threads()} torch threads, glibc malloc "
                 f"{'keeping freed memory' if freed_memory_kept() else 'default (mmap per big tensor)'}")
    return f"{where}, torch {torch.__version__}"


def _identified() -> str:
    identity = cpu_identity()
    return f" ({identity})" if identity else ""


def _status_kib(field: str) -> int:
    found = re.search(rf"^{field}:\s+(\d+) kB", Path("/proc/self/status").read_text(), re.MULTILINE)
    return int(found.group(1)) if found else 0


def peak_memory_mib(fn, device: str) -> float:
    """Peak memory one call of fn() adds to what is allocated before it, in MiB (module docstring).
    NaN on a CPU system without /proc (the resident-set peak cannot be reset there)."""
    if str(device).startswith("cuda"):
        sync(device)
        before = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        fn()
        sync(device)
        return (torch.cuda.max_memory_allocated(device) - before) / 2 ** 20
    try:
        release_free_memory()
        before = _status_kib("VmRSS")
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current resident set
    except OSError:
        return float("nan")
    fn()
    return max(0, _status_kib("VmHWM") - before) / 1024


# ------------------------------------------------------------------------------ models and inputs

def random_frames(batch: int, frames: int, hw, device: str, in_channels=3, gbuffer_channels=7, seed=0):
    """Random radiance in [0, 1) and gBuffer (B, T, C, h, w), reproducible."""
    gen = torch.Generator().manual_seed(seed)
    h, w = hw
    x = torch.rand(batch, frames, in_channels, h, w, generator=gen)
    g = torch.rand(batch, frames, gbuffer_channels, h, w, generator=gen)
    return x.to(device), g.to(device)


def build(cfg: dict, device: str, perturb: float, seed: int = 0) -> nn.Module:
    """The model of `cfg` (scale 2) with N(0, perturb) noise on every parameter (module docstring)."""
    torch.manual_seed(seed)
    model = build_model(cfg, 2)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * perturb)
    return model.to(device).eval()


def trained_models(weights, models: Sequence[str], configs) -> dict[str, tuple[nn.Module, str]]:
    """{model name: (its exported trained weights, loaded; what the caption says of them)}, each checked
    to be a model this table times, at the preset's configuration (widths) and the table's scale (2),
    before anything is timed. None: none (the YAML's default)."""
    if weights is None:
        return {}
    if not isinstance(weights, Mapping):
        raise UserError(f"experiment.weights={weights!r}: expected {{model: weights file}}, e.g. "
                        "'experiment.weights={srd:results/cpu/weights/ours.pt}'")
    trained = {}
    for name, path in weights.items():
        if name not in models:
            raise UserError(f"experiment.weights.{name}: {name!r} is not one of experiment.models {list(models)}")
        if not isinstance(path, str) or not path:
            raise UserError(f"experiment.weights.{name}={path!r}: expected the path of a weights file")
        model, meta = load_exported(path)
        if meta["scale"] != 2:
            raise UserError(f"experiment.weights.{name}: {path} holds a model of scale {meta['scale']} (task "
                            f"{meta.get('task')}); this table times scale 2 (960x540 -> 1920x1080)")
        if meta["model"] != configs[name]:
            differ = sorted(k for k in set(meta["model"]) | set(configs[name])
                            if meta["model"].get(k) != configs[name].get(k))
            raise UserError(f"experiment.weights.{name}: {path} holds another configuration than this preset's "
                            f"{name} (" + ", ".join(f"{k} {meta['model'].get(k)!r}, here {configs[name].get(k)!r}"
                                                   for k in differ[:3]) + ")")
        trained[name] = (model, f"{path}, training run {meta.get('run')}, {meta['hdr']} domain")
    return trained


class ConvStack(nn.Module):
    """`depth` 3x3 convs + ReLU at `channels` channels, applied to a (B, T, channels, h, w) input: the
    dense-conv reference. Takes (x, g) like a model and ignores g."""

    def __init__(self, channels: int, depth: int):
        super().__init__()
        layers = []
        for _ in range(depth):
            layers += [nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(inplace=True)]
        self.body = nn.Sequential(*layers)

    def forward(self, x, g=None):
        b, t = x.shape[:2]
        return {"final": self.body(x.reshape(b * t, *x.shape[2:])).reshape(b, t, x.shape[2], *x.shape[-2:])}


def conv_stack_depth(target_macs: float, hw, channels: int) -> int:
    """Depth whose MACs (h*w*channels^2*9 per conv) are closest to `target_macs`."""
    per_conv = hw[0] * hw[1] * channels * channels * 9
    return max(1, round(target_macs / per_conv))


# ------------------------------------------------------------------------------ sections

def _row(section, method, path, size, per, timing=None, **extra) -> dict:
    row = {"section": section, "method": method, "fast path": path, "size": size, "per": per}
    if timing is not None:
        row.update({k: timing[k] for k in ("ms", "ms min", "ms max")})
    row.update(extra)
    return row


def _size(hw, scale=2) -> str:
    h, w = hw
    return f"{w}x{h} -> {scale * w}x{scale * h}" if scale > 1 else f"{w}x{h}"


def inference_rows(label: str, model, macs: int, x, g, paths, device, repeats, warmup) -> list[dict]:
    """One row per fast path: time, GMac/s, peak memory and the difference from the fp32 output."""
    rows, reference = [], None
    for path in paths:
        row = _row("inference", label, path, _size(x.shape[-2:]), "frame", GMac=macs / 1e9)
        try:
            t0 = time.perf_counter()
            run = prepare(model, path)
            first = run(x, g)  # compile happens here
            first_s = time.perf_counter() - t0
            timing = time_call(lambda: run(x, g), device, repeats, max(0, warmup - 1))
            row.update({k: timing[k] for k in ("ms", "ms min", "ms max")})
            row["GMac/s"] = macs / 1e9 / (timing["ms"] / 1000)
            row["peak MiB"] = peak_memory_mib(lambda: run(x, g), device)
            out = timing["result"]
            if reference is None and parse_path(path).name == "fp32":
                reference = out
            if reference is not None:
                row["max abs diff"] = max_abs_diff(out, reference)
                row["max rel diff"] = row["max abs diff"] / max(float(reference["final"].abs().max()), 1e-12)
            if parse_path(path).compile:
                row["note"] = f"first call (compile) {first_s:.1f} s"
            del first, out
        except Exception as err:  # a path the machine cannot run (no compiler, no bf16) is a row saying so
            log.warning("speed: %s %s failed: %s", label, path, err)
            row["note"] = f"failed: {error_summary(err, 120)}"
        rows.append(row)
        log.info("speed: %s %s: %s ms/frame", label, path, row.get("ms"))
    return rows


def note_auto_choice(rows: list[dict], model, x, g, device, repeats, untrained: bool = False) -> str | None:
    """Which path `fast_path=auto` picks for `model` on this machine (bench.measure.choose_fast_path,
    measured afresh), noted on that path's row of `rows` (the model's inference rows) with a check:
    whether this table measured it as the fastest of the candidates auto accepted, or which one beat
    it, and which faster paths auto refused and why (bf16 off by more than measure.TOLERANCE with these
    weights, say; on `untrained` weights the note says the refusal was on them: trained ones may pass).
    None, and a warning, when no path runs the model."""
    try:
        chosen, measured = choose_fast_path(model, x, g, device, cache=None, key={}, repeats=repeats)
    except RuntimeError as err:
        log.warning("speed: fast_path=auto has nothing to pick for %s: %s", type(model).__name__, err)
        return None
    candidates = candidate_paths(device)
    refused = {path: why for path, why in measured.items() if isinstance(why, str)}  # "off by ...", "failed: ..."
    timed = {r["fast path"]: r["ms"] for r in rows if r["fast path"] in candidates and pd.notna(r.get("ms"))}
    if chosen not in timed:
        check = "not timed in this table"
    else:
        # the fastest path auto could have taken: a path its accuracy check refused is no rival
        fastest = min((p for p in timed if p not in refused), key=timed.get, default=chosen)
        check = ("the fastest in this table of those its accuracy check accepted" if fastest == chosen else
                 f"but {fastest} was {timed[chosen] / timed[fastest]:.2f}x faster in this table")
        faster_refused = [p for p in timed if p in refused and timed[p] < timed[chosen]]
        def on_what(why):  # an output that strayed depends on the weights; a path that failed does not
            return " on these untrained weights" if untrained and why.startswith("off by") else ""
        check += "".join(f"; {p} ran {timed[chosen] / timed[p]:.2f}x faster here, refused{on_what(refused[p])}: "
                         f"{refused[p]}" for p in faster_refused)
    on_its_row = [row for row in rows if row["fast path"] == chosen]
    # a path the table has no row for (channels_last+bf16 where only the default paths were timed):
    # said on the model's first row
    targets = on_its_row or rows[:1]
    said = (f"fast_path=auto picks this of {candidates}, {check}" if on_its_row else
            f"fast_path=auto picks {chosen} of {candidates}, {check}")
    for row in targets:
        row["note"] = "; ".join(n for n in (row.get("note"), said) if isinstance(n, str) and n)
    log.info("speed: fast_path=auto picks %s for %s", chosen, type(model).__name__)
    return chosen


def training_steps(label: str, model, recipe: Recipe, compiled: str | None, device, repeats, warmup):
    """(path, compute) of each training step the table times, compute() giving its row: the step with the
    deformable convs' default training sampler (compiled on CPU; on CUDA the fused kernels, the entry
    points' default), also compiled in mode `compiled` (the trainer's train.compile) where given; for models
    that have deformable convs, with the grid_sample sampler and, on CUDA, the fused Triton kernels
    (deformable conv and CFM). `recipe`: the trainer's, at the table's batch, frames and crop."""
    step = functools.partial(training_row, label, model, recipe, device, repeats, warmup)
    yield "fp32", step
    if compiled:
        yield f"fp32, compiled ({compiled})", functools.partial(step, path=f"fp32, compiled ({compiled})",
                                                                compile=compiled)
    deform = next((m for m in model.modules() if isinstance(m, DeformConv2d)), None)
    if deform is None:
        return
    probe = torch.empty(1, device=device)
    default = training_sampler(probe, deform.weight)
    if default != "grid_sample":
        def grid_sample_step():
            with grid_sample_training(), fused.forced(False):
                return step(path="fp32, grid_sample sampler")
        yield "fp32, grid_sample sampler", grid_sample_step
    if probe.is_cuda and fused.available():
        def fused_step(path, **options):
            with fused.on_cuda():
                return step(path=path, **options)
        if default != "fused":
            yield "fp32, fused sampler", functools.partial(fused_step, "fp32, fused sampler")
        # the trainer's train.precision=bf16 and train.channels_last=true, eager and, where asked, compiled:
        # eager, that step is host-bound; graphed, its convolutions are what is left to gain on
        path = "bf16+channels_last, fused sampler"
        yield path, functools.partial(fused_step, path, bf16=True, channels_last=True)
        if compiled:
            yield f"{path}, compiled ({compiled})", functools.partial(
                fused_step, f"{path}, compiled ({compiled})", bf16=True, channels_last=True, compile=compiled)


def training_row(label: str, model, recipe: Recipe, device, repeats, warmup, path: str = "fp32",
                 **options) -> dict:
    """`timed_training_row`, or a row saying why the step failed on this machine (a compiled step that
    does not trace, no memory): the sections after it still run."""
    try:
        return timed_training_row(label, model, recipe, device, repeats, warmup, path=path, **options)
    except Exception as err:  # noqa: BLE001 - as inference_rows: any failure of a path is that path's row
        log.warning("speed: %s training step %s failed: %s", label, path, err)
        return _row("training step", label, path, _step_size(recipe), "step",
                    note=f"failed: {error_summary(err, 120)}")


def _step_size(recipe: Recipe) -> str:
    return f"{recipe.batch_size}x{recipe.seq_len} frames of {recipe.crop}x{recipe.crop} LR"


def timed_training_row(label: str, model, recipe: Recipe, device, repeats, warmup, stack_channels: int | None = None,
                       path: str = "fp32", bf16: bool = False, channels_last: bool = False,
                       compile: str | None = None) -> dict:
    """Time of one training step (`training_step`), fp32 or as the trainer's options ask; a compiled
    step's first call, the compilation, is timed apart."""
    recipe = replace(recipe, precision="bf16" if bf16 else "fp32", channels_last=channels_last, compile=compile)
    if compile is not None:  # a compilation of its own: Dynamo stops compiling a function after 8 settings
        torch._dynamo.reset()
    step = training_step(copy.deepcopy(model), recipe, device, stack_channels)  # the table's model untouched
    note = step_note(recipe, stack_channels)
    if compile is not None:
        compile_s = time_call(step, device, 1, 0)["ms"] / 1000  # the first call compiles
        note += f"; first call (compile) {compile_s:.0f} s"
        if compile == "reduce-overhead" and torch.device(device).type == "cuda":
            note += "; peak MiB leaves out the CUDA graphs' memory pool, taken when they were captured"
    timing = time_call(step, device, repeats, warmup)
    return _row("training step", label, path, _step_size(recipe), "step", timing,
                **{"peak MiB": peak_memory_mib(step, device), "note": note})


def step_note(recipe: Recipe, stack_channels: int | None = None) -> str:
    """What a training row's step does (its note): the trainer's, or the conv stack's, whose channels in
    and out are not radiance, so an L1 loss stands in for the trainer's."""
    update = ", ".join(part for part, on in (("clip", recipe.clip_grad_norm), ("Adam", True), ("EMA", recipe.ema))
                       if on)
    if stack_channels:
        return f"L1 loss, then the trainer's {update}"
    return f"the trainer's step: HDR encode, loss without perceptual, {update}"


def training_step(model, recipe: Recipe, device, stack_channels: int | None = None):
    """The trainer's step of `model` (trained in place), as a call returning its loss, on a random batch of
    `recipe`'s batch, frames and crop: bench.train's training_start (memory format, EMA, Adam), step_loss
    (HDR encode and the weighted loss, bf16 and compiled as the recipe says; no perceptual term: no VGG
    here) and update_weights (backward, gradient clip, Adam, EMA). With `stack_channels`, the conv
    stack's step instead: `stack_channels` channels in and out at scale 1, an L1 loss, the same update.
    The exposure each frame is encoded at is computed in the step, as the trainer does for every item but
    the lamp items of train.emitters_exposure=without."""
    ema_model, optimizer = training_start(model, recipe, device)
    recipe = replace(recipe, loss={head: {**w, "perceptual": 0} for head, w in recipe.loss.items()})
    task = None if stack_channels else get_task("srd")
    channels, scale = (stack_channels, 1) if stack_channels else (3, task.scale)
    sequences, crop = (recipe.batch_size, recipe.seq_len), recipe.crop
    x, g = random_frames(*sequences, (crop, crop), device, seed=1, in_channels=channels)
    target = torch.rand(*sequences, channels, scale * crop, scale * crop,
                        generator=torch.Generator().manual_seed(2)).to(device)
    if task is None:
        batch, loss_fn = {"x": x, "y": target}, compiled_as(recipe, _stack_loss)
    else:
        batch = {task.x: x, task.g: g, task.y: target, **({task.mid: target} if task.mid else {})}
        loss_fn = compiled_as(recipe, batch_loss)
    if recipe.channels_last:  # as the trainer lays out every buffer of a batch
        batch = {k: frames_channels_last(v) for k, v in batch.items()}
    steps = itertools.count()

    def step():
        loss, _ = step_loss(loss_fn, model, batch, task, recipe)
        update_weights(model, optimizer, ema_model, loss, recipe, next(steps))
        return loss
    return step


def _stack_loss(net, batch, *_):
    """The conv stack's loss, in batch_loss's form (total, parts)."""
    return (net(batch["x"])["final"] - batch["y"]).abs().mean(), {}


def oidn_row(out_hw, device, repeats, warmup) -> dict | None:
    """Intel OIDN (quality high, albedo + normal) on one frame at the OUTPUT size; None without pyoidn."""
    try:
        from baselines.oidn import OIDN
    except ImportError as err:
        log.warning("speed: no OIDN reference (%s)", err)
        return None
    oidn = OIDN(scale=1, variant="lr_then_up", quality="high")
    x, g = random_frames(1, 1, out_hw, "cpu", seed=3)
    timing = time_call(lambda: oidn(x, g), "cpu", repeats, warmup)
    return _row("reference", "OIDN (albedo + normal)", "its own (fp32)", _size(out_hw, 1), "frame", timing,
                **{"peak MiB": peak_memory_mib(lambda: oidn(x, g), "cpu"), "time / OIDN": 1.0,
                   "note": "pyoidn on the CPU, its own threads"})


def conv_stack_rows(target_macs: int, hw, channels: int, paths, device, repeats, warmup,
                    recipe: Recipe | None, compiled: str | None) -> list[dict]:
    """The dense-conv reference at the proposed model's MACs, per fast path; with `recipe` (the trainer's,
    at the table's batch, frames and crop), also its training step (`training_step`: L1 loss, then the
    trainer's update) at that crop, the same MACs per LR pixel as the proposed model's forward, and
    compiled in mode `compiled` where given."""
    depth = conv_stack_depth(target_macs, hw, channels)
    torch.manual_seed(0)
    stack = ConvStack(channels, depth).to(device).eval()
    x = torch.rand(1, 1, channels, *hw, generator=torch.Generator().manual_seed(4)).to(device)
    macs = macs_at(lambda: ConvStack(channels, depth), frame_inputs({"in_channels": channels}, hw))
    label = f"3x3 conv stack ({depth} x {channels} ch)"
    rows = inference_rows(label, stack, macs, x, None, paths, device, repeats, warmup)
    for row in rows:
        row["section"], row["size"] = "reference", _size(hw, 1)
    if recipe is not None:
        rows.append(training_row(label, stack, recipe, device, repeats, warmup, stack_channels=channels))
        if compiled:  # the same path as Ours' compiled row, for their ratio
            rows.append(training_row(label, stack, recipe, device, repeats, warmup, stack_channels=channels,
                                     path=f"fp32, compiled ({compiled})", compile=compiled))
    return rows


def deform_rows(channels: int, sizes, device, repeats, warmup) -> list[dict]:
    """bench.nn.DeformConv2d vs nn.Conv2d of the same shape (channels -> channels, 3x3), forward only, on
    three paths (fp32, channels_last, channels_last+bf16), each ratio against the conv on the same path:
    the inference sampler this machine takes (the compiled columns one on CPU where it builds), the eager
    gather sampler (its fallback, and the one before it), and the training sampler (grid_sample, taken
    whenever autograd needs a gradient; forward time only, fp32)."""
    rows = []
    for hw in sizes:
        torch.manual_seed(0)
        conv = nn.Conv2d(channels, channels, 3, padding=1).to(device)
        deform = DeformConv2d(channels, channels).to(device)
        nn.init.normal_(deform.offset_conv.weight, std=0.1)  # real offsets, not the zero init
        x = torch.randn(1, channels, *hw, generator=torch.Generator().manual_seed(5)).to(device)
        x_cl = x.contiguous(memory_format=torch.channels_last)
        macs = hw[0] * hw[1] * channels * channels * 9
        sampler = inference_sampler(x, deform.weight)

        def row(method, path, fn, conv_ms=None, mode=torch.no_grad):
            with mode():
                timing = time_call(fn, device, repeats, warmup)
            rows.append(_row("deformable conv", f"{method} {channels}->{channels} 3x3", path, _size(hw, 1),
                             "layer call", timing, GMac=macs / 1e9, **{
                                 "GMac/s": macs / 1e9 / (timing["ms"] / 1000),
                                 "time / plain conv": timing["ms"] / (conv_ms or timing["ms"])}))
            return timing["ms"]

        fused_too = x.is_cuda and sampler != "fused" and fused.available()
        for path, inputs, bf16 in (("fp32", x, False), ("channels_last", x_cl, False),
                                   ("channels_last+bf16", x_cl, True)):
            with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=bf16):
                conv_ms = row("nn.Conv2d", path, lambda: conv(inputs))
                row(f"DeformConv2d ({sampler} sampler)", path, lambda: deform(inputs), conv_ms)
                if fused_too:
                    with fused.on_cuda():
                        row("DeformConv2d (fused sampler)", path, lambda: deform(inputs), conv_ms)
                if sampler != "gather":
                    with eager_gather(), fused.forced(False):
                        row("DeformConv2d (eager gather sampler)", path, lambda: deform(inputs), conv_ms)
                if path == "fp32":
                    x_grad = inputs.clone().requires_grad_(True)
                    row(f"DeformConv2d ({training_sampler(x_grad, deform.weight)} sampler, autograd on)", path,
                        lambda: deform(x_grad), conv_ms, torch.enable_grad)
                    if fused_too:
                        with fused.on_cuda():
                            row("DeformConv2d (fused sampler, forward + backward)", path,
                                lambda: deform(x_grad).sum().backward(), conv_ms, torch.enable_grad)
    return rows


def tiled_rows(label: str, model, x, g, tile: int, overlap: int, device, repeats, warmup,
               untiled=None, uhd_hw=None) -> list[dict]:
    """Tiled inference at the input size (max difference from `untiled`, the fp32 output) and,
    with uhd_hw, at that LR size (a 4K output): time and peak memory (fp32)."""
    note = f"tile {tile}, overlap {overlap} LR px"
    run = lambda: tiled_predict(model, x, g, tile=tile, overlap=overlap)
    timing = time_call(run, device, repeats, warmup)
    row = _row("tiled", label, "fp32", _size(x.shape[-2:]), "frame", timing, note=note,
               **{"peak MiB": peak_memory_mib(run, device)})
    if untiled is not None:
        row["max abs diff"] = max_abs_diff(timing["result"], untiled)
        row["max rel diff"] = row["max abs diff"] / max(float(untiled["final"].abs().max()), 1e-12)
    rows = [row]
    if uhd_hw:
        x4, g4 = random_frames(1, 1, uhd_hw, device, seed=6)
        run4 = lambda: tiled_predict(model, x4, g4, tile=tile, overlap=overlap)
        timing4 = time_call(run4, device, repeats=1, warmup=0)
        rows.append(_row("tiled", label, "fp32", _size(uhd_hw), "frame", timing4, note=note,
                         **{"peak MiB": peak_memory_mib(run4, device)}))
        del x4, g4
    return rows


def profile_rows(label: str, model, macs_table: pd.DataFrame, x, g, path: str, device, repeats, warmup) -> list[dict]:
    """Where one frame's time goes: per module class, the wall time of its calls in one frame (median
    of `repeats` frames after `warmup`), inclusive of the modules nested in them (a DecoderBlock's time
    includes its DeformConv2d's), next to the MACs of those modules (from `macs_table`, bench.macs
    rows named by module path), so a class whose share of time exceeds its share of MACs stands out.
    Hooks synchronise CUDA; their own cost is a few microseconds per call."""
    if parse_path(path).compile:
        raise ValueError("profile: hooks do not see inside a compiled module; choose a path without compile")
    run = prepare(model, path)
    names = defaultdict(list)
    for module_name, module in run.net.named_modules():
        if module is not run.net:
            names[type(module).__name__].append(module_name)
    frame, starts = defaultdict(float), {}
    calls = defaultdict(int)

    def before(module, args):
        sync(device)
        starts[id(module)] = time.perf_counter()

    def after(module, args, out):
        sync(device)
        frame[type(module).__name__] += time.perf_counter() - starts.pop(id(module))
        calls[type(module).__name__] += 1

    modules = [m for m in run.net.modules() if m is not run.net]
    handles = [m.register_forward_pre_hook(before) for m in modules] + [m.register_forward_hook(after) for m in modules]
    per_frame, totals = [], defaultdict(list)
    try:
        for i in range(warmup + max(1, repeats)):
            frame.clear()
            calls.clear()
            t0 = time.perf_counter()
            run(x, g)
            sync(device)
            if i >= warmup:
                per_frame.append(time.perf_counter() - t0)
                for cls, seconds in frame.items():
                    totals[cls].append(seconds)
    finally:
        for handle in handles:
            handle.remove()
    whole_ms = 1000 * statistics.median(per_frame)
    macs_of = {cls: sum(int(macs_table.loc[(macs_table["layer"] == n) | macs_table["layer"].str.startswith(n + "."),
                                           "macs"].sum()) for n in module_names)
               for cls, module_names in names.items()}
    size = _size(x.shape[-2:])
    rows = [_row("profile", f"{label}: whole frame", path, size, "frame", GMac=sum(macs_table["macs"]) / 1e9,
                 ms=whole_ms, note=f"median of {len(per_frame)} frames with hooks on every module")]
    for cls in sorted(totals, key=lambda c: -statistics.median(totals[c])):
        ms = 1000 * statistics.median(totals[cls])
        gmac = macs_of.get(cls, 0) / 1e9
        rows.append(_row("profile", f"{label}: {cls}", path, size, "frame", GMac=gmac, ms=ms,
                         **{"GMac/s": gmac / (ms / 1000) if gmac else float("nan"),
                            "note": f"{calls[cls]} calls; {100 * ms / whole_ms:.0f}% of the time, "
                                    f"{100 * gmac * 1e9 / max(1, sum(macs_table['macs'])):.0f}% of the MACs; inclusive"}))
    return rows


# ------------------------------------------------------------------------------ the experiment

def _ratios(table: pd.DataFrame) -> pd.DataFrame:
    """time / OIDN for every per-frame inference row of OIDN's output size (not the 4K tiles: OIDN is timed
    at 1080p only); GMac/s / conv stack per fast path; a training step against the conv stack's step on
    the same path, else (a compiled step on another path: bf16) its fp32 one compiled the same way, else
    its eager fp32 one."""
    oidn = table[table["method"].str.startswith("OIDN")]
    if len(oidn):
        output_size = table["size"].astype(str).str.split("-> ").str[-1]
        frames = table["section"].isin(["inference", "tiled"]) & (output_size == str(oidn["size"].iloc[0]))
        table.loc[frames, "time / OIDN"] = table.loc[frames, "ms"] / float(oidn["ms"].iloc[0])
    stack = table[table["method"].str.startswith("3x3 conv stack") & (table["section"] == "reference")]
    stack = stack.set_index("fast path")["GMac/s"]
    inference = table["section"] == "inference"
    table.loc[inference, "GMac/s / conv stack"] = [
        gmacs / stack.get(path, float("nan")) for gmacs, path in table.loc[inference, ["GMac/s", "fast path"]].to_numpy()]
    steps = table["section"] == "training step"
    stack_steps = table[steps & table["method"].str.startswith("3x3 conv stack")].set_index("fast path")["ms"]
    if len(stack_steps):
        def stack_step(path: str) -> float:
            compiled = re.search(r"compiled \(.*\)$", path)
            fp32 = f"fp32, {compiled.group(0)}" if compiled else "fp32"
            return stack_steps.get(path, stack_steps.get(fp32, float("nan")))
        table.loc[steps, "step / conv stack step"] = [
            ms / stack_step(str(path)) for ms, path in table.loc[steps, ["ms", "fast path"]].to_numpy()]
    return table


def run(ctx, name: str = "speed", models: list[str] = (), input_hw=(540, 960),
        fast_paths: list[str] | None = None, repeats: int = 5, warmup: int = 1, threads: int | None = None,
        train: dict | None = None, oidn: bool = True, conv_stack_channels: int = 32,
        deform: dict | None = None, tiled: dict | None = None, perturb: float = 0.02,
        profile: dict | None = None, weights: dict | None = None, caption: str = "") -> pd.DataFrame:
    """CLI entry (conf/experiment/speed.yaml documents every parameter). Returns the table, which is
    rewritten after every section, so an interrupted run leaves what it measured."""
    unknown = [m for m in models if m not in ctx.models]
    if unknown:  # before the first section is timed
        raise UserError(f"experiment.models: no model {unknown[0]!r}; models: {', '.join(ctx.models)}")
    twice = [m for i, m in enumerate(models) if m in models[:i]]
    if twice:  # a model's section is named by it
        raise UserError(f"experiment.models: {twice[0]!r} is listed twice")
    for m in models:
        with torch.device("meta"):   # no memory: only whether it has parameters
            if not is_learned(build_model(ctx.models[m], 2)):
                raise UserError(f"experiment.models: {m!r} has nothing to train; the speed table times learned "
                                f"models (OIDN has its own row: experiment.oidn)")
    if not (len(input_hw) == 2 and all(isinstance(n, int) and n >= 8 for n in input_hw)):
        raise UserError(f"experiment.input_hw={list(input_hw)}: expected [height, width], each an integer >= 8")
    for key, count, least in (("repeats", repeats, 1), ("warmup", warmup, 0)):
        if not (isinstance(count, int) and count >= least):
            raise UserError(f"experiment.{key}={count!r}: expected an integer >= {least}")
    for path in fast_paths or ():
        try:
            parse_path(path)
        except ValueError as err:
            raise UserError(f"experiment.fast_paths: {path!r}: {err}") from None
    _check_sections(conv_stack_channels, perturb, deform or {}, tiled or {})
    profile = {**(profile or {}), "fast_path": profiled_path(profile or {}, fast_paths or PATHS)}  # checked now
    trained = trained_models(weights, models, ctx.models)
    device = str(ctx.device)
    previous_threads = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    out_dir = Path(ctx.results_dir) / name / device_tag(device)
    caption = (caption + " " if caption else "") + (
        f"Speed on {machine_caption(device)}; preset {ctx.preset} widths, {weights_caption(trained, models)}. ms: wall clock, median "
        f"(min, max) of {repeats} warm calls; GMac: analytic multiply-accumulates per frame; path: fp32 reference "
        "or bench.infer fast path (bf16 = autocast bfloat16); diffs vs the fp32 output (tiled: vs untiled); peak MiB: "
        "memory one call adds; note: the path fast_path=auto picks on this machine. Ratios: model time / OIDN at the output size; model GMac/s / a 3x3 conv stack of "
        "the proposed model's GMac on the same path; deformable conv time / nn.Conv2d of the same shape.")
    settings = settings_key(ctx, caption, trained, models=list(models), input_hw=list(input_hw),
                            fast_paths=fast_paths, repeats=repeats, warmup=warmup, threads=threads, train=train,
                            oidn=oidn, conv_stack_channels=conv_stack_channels, deform=deform, tiled=tiled,
                            perturb=perturb, profile=profile, weights=weights)
    kept = kept_sections(out_dir, settings)
    done, table = {}, None
    try:
        for key, compute in _sections(ctx, models, tuple(input_hw), fast_paths or PATHS, repeats, warmup,
                                      train or {}, oidn, conv_stack_channels, deform or {}, tiled or {}, perturb,
                                      profile, trained, device):
            if key in kept:
                log.info("speed: %s as the interrupted run with these settings timed it", key)
            done[key] = kept[key] if key in kept else compute()
            table = _ratios(pd.DataFrame([r for rows in done.values() for r in rows], columns=COLUMNS))
            write_table(table, out_dir, digits=3, caption=f"{PARTIAL_CAPTION} {caption}")
            write_atomic(out_dir / PARTIAL_SECTIONS, lambda tmp: tmp.write_text(
                json.dumps({"settings": settings, "sections": done}, default=float) + "\n"))
        if table is not None:  # every section is in: the caption loses its PARTIAL
            reused = [key for key in done if key in kept]
            write_table(table, out_dir, digits=3, caption=caption + (
                f" Resumed: {'; '.join(reused)} timed by an earlier run of these settings and code, which was "
                "interrupted." if reused else ""))
        (out_dir / PARTIAL_SECTIONS).unlink(missing_ok=True)
    finally:
        torch.set_num_threads(previous_threads)
    log.info("speed: table in %s", out_dir)
    return table


def settings_key(ctx, caption: str, trained: dict, **arguments) -> str:
    """What a section's rows depend on: the experiment's arguments; the caption (machine, threads, preset,
    weights) without the clock, which /proc gives as the current one where the CPU scales it; the
    trained weights' values; the models' configurations and the training recipe; the code they run
    (bench.experiments.speed's imports, the models' modules and the fused kernels, which are loaded by
    name); and the switches of the CPU and GPU kernels (the GPU job turns the fused ones on once its
    kernel tests pass)."""
    names = list(dict.fromkeys(arguments["models"] + ["srd"]))
    configs = {m: ctx.models[m] for m in names if m in ctx.models}
    weights = {m: hashlib.sha256(b"".join(t.detach().cpu().double().numpy().tobytes()  # any dtype, bf16 too
                                          for t in model.state_dict().values())).hexdigest()
               for m, (model, _) in trained.items()}
    code = runs.code_fingerprint(["bench.experiments.speed", "bench.nn.triton_kernels",
                                  *(cfg["_target_"] for cfg in configs.values())])
    described = {"arguments": arguments, "caption": re.sub(r"\d+ MHz", "MHz", caption), "device": str(ctx.device),
                 "switches": {k: os.environ.get(k) for k in (FUSED_GPU, "SRD_BENCH_NATIVE")},
                 "weights": weights, "models": configs, "recipe": ctx.train, "code": code}
    return hashlib.sha256(json.dumps(described, sort_keys=True, default=repr).encode()).hexdigest()[:16]


def kept_sections(out_dir: Path, settings: str) -> dict[str, list[dict]]:
    """{section: rows} an interrupted run of the same settings left (PARTIAL_SECTIONS), else {}: a speed
    table too long for one call (a GPU machine's) is finished by the next instead of started again."""
    try:
        recorded = json.loads((out_dir / PARTIAL_SECTIONS).read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(recorded, dict) or recorded.get("settings") != settings:
        log.info("speed: %s is of other settings or code: every section is timed again", out_dir / PARTIAL_SECTIONS)
        return {}
    return recorded.get("sections") or {}


def weights_caption(trained: dict, models: Sequence[str]) -> str:
    """What the caption says of the weights: untrained, or which models ran which trained weights."""
    if not trained:
        return "untrained weights"
    named = "; ".join(f"{LABELS.get(name, name)} {said}" for name, (_, said) in trained.items())
    others = [LABELS.get(m, m) for m in models if m not in trained]
    return f"trained weights ({named})" + (f", untrained for {', '.join(others)}" if others else "")


def profiled_path(profile: dict, paths: Sequence[str]) -> str:
    """The path the profile section runs: `profile.fast_path`, else the last of `paths` that hooks can see
    into (not compiled). Checked before the first section is timed: a compiled or misspelt one ended in a
    traceback after every other section had run."""
    chosen = profile.get("fast_path")
    if not profile.get("models"):  # nothing profiled: nothing to check
        return chosen or REFERENCE
    if chosen is None:
        hookable = [p for p in paths if not parse_path(p).compile]
        return hookable[-1] if hookable else REFERENCE
    try:
        compiled = parse_path(chosen).compile
    except ValueError as err:
        raise UserError(f"experiment.profile.fast_path: {chosen!r}: {err}") from None
    if compiled:
        raise UserError(f"experiment.profile.fast_path={chosen}: hooks do not see inside a compiled module; "
                        "choose a path without compile")
    return chosen


def _check_sections(conv_stack_channels, perturb, deform: dict, tiled: dict) -> None:
    """The sections' own values, before the first is timed (a tile of 0 ended in a traceback after the
    inference and training sections; a negative one timed an empty output). A key left out takes
    `_sections`' default, which is valid: only the given ones are checked."""
    def integer(key, value, least):
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= least):
            raise UserError(f"experiment.{key}={value!r}: expected an integer >= {least}")
    integer("conv_stack_channels", conv_stack_channels, 0)
    if not (isinstance(perturb, (int, float)) and not isinstance(perturb, bool) and perturb >= 0):
        raise UserError(f"experiment.perturb={perturb!r}: expected a number >= 0")
    for name, section, key, least in (("deform", deform, "channels", 1), ("tiled", tiled, "tile", 1),
                                      ("tiled", tiled, "overlap", 0)):
        if key in section:
            integer(f"{name}.{key}", section[key], least)
    def size(key, hw):
        if not (isinstance(hw, Sequence) and len(hw) == 2 and all(isinstance(n, int) and n >= 8 for n in hw)):
            raise UserError(f"experiment.{key}: {hw!r}: expected [height, width], each an integer >= 8")
    sizes = deform.get("sizes", [])
    if not isinstance(sizes, Sequence) or isinstance(sizes, str):
        raise UserError(f"experiment.deform.sizes={sizes!r}: expected a list of [height, width]")
    for hw in sizes:
        size("deform.sizes", hw)
    if "uhd_input_hw" in tiled:
        size("tiled.uhd_input_hw", tiled["uhd_input_hw"])


def table_recipe(recipe: Recipe, train: dict) -> Recipe:
    """The trainer's `recipe` at the batch, frames and crop that `train` (experiment.train, its nulls left
    out by `_sections`: null is the recipe's) gives."""
    named = {"batch": "batch_size", "frames": "seq_len", "crop": "crop"}
    return replace(recipe, **{field: train[key] for key, field in named.items() if key in train})


def _sections(ctx, models, input_hw, paths, repeats, warmup, train, oidn, stack_channels, deform, tiled,
              perturb, profile, trained, device):
    """(name, compute) of each section, in order: the reference points first (quick, and every ratio
    needs them), then one model at a time, in sections small enough that a run stopped part way keeps
    most of what it timed; compute() times the section and returns its rows."""
    if oidn:
        yield "OIDN", lambda: [row for row in [oidn_row((2 * input_hw[0], 2 * input_hw[1]), device, repeats, warmup)]
                               if row]
    train = {k: v for k, v in train.items() if v is not None}   # null: the default
    recipe = table_recipe(ctx.train, train) if train.get("enabled", True) else None
    compiled = train.get("compile")
    layers_of = functools.cache(lambda name: frame_macs(ctx.models[name], input_hw))  # srd's counted once
    if stack_channels and "srd" in ctx.models:
        yield "conv stack", lambda: conv_stack_rows(int(layers_of("srd")["macs"].sum()), input_hw, stack_channels,
                                                    paths, device, repeats, warmup, recipe, compiled)
    if deform.get("enabled", True):
        yield "deformable conv", lambda: deform_rows(
            deform.get("channels", 32), [tuple(s) for s in deform.get("sizes", [[270, 480], [540, 960]])],
            device, repeats, warmup)
    tile_models = (tiled.get("models") or models) if tiled.get("enabled", True) else []
    x, g = random_frames(1, 1, input_hw, device)
    for name in models:   # each model's inference, each training step, profile and tiles: sections of their own
        label = LABELS.get(name, name)
        model = trained[name][0].to(device) if name in trained else build(ctx.models[name], device, perturb)
        yield f"{label} inference", functools.partial(_inference_section, label, model, layers_of(name), x, g, paths,
                                                      device, repeats, warmup, untrained=name not in trained)
        if recipe is not None:
            mode = compiled if label in train.get("compiled", ()) else None
            for path, step in training_steps(label, model, recipe, mode, device, repeats, warmup):
                yield f"{label} training step ({path})", lambda step=step: [step()]
        if name in (profile.get("models") or []):
            yield f"{label} profile", functools.partial(profile_rows, label, model, layers_of(name), x, g,
                                                        profile["fast_path"], device, repeats, warmup)
        if name in tile_models:
            yield f"{label} tiles", functools.partial(_tiles_section, label, model, x, g, tiled, device, repeats,
                                                      warmup)


def _inference_section(label, model, layers, x, g, paths, device, repeats, warmup, untrained: bool) -> list[dict]:
    """A model's inference rows, each fast path, and the path fast_path=auto picks noted on them."""
    rows = inference_rows(label, model, int(layers["macs"].sum()), x, g, paths, device, repeats, warmup)
    note_auto_choice(rows, model, x, g, device, repeats, untrained=untrained)
    return rows


def _tiles_section(label, model, x, g, tiled: dict, device, repeats, warmup) -> list[dict]:
    """Tiled inference against untiled, at the table's size and, where asked, at a 3840x2160 output."""
    untiled = prepare(model)(x, g)
    uhd = tuple(tiled.get("uhd_input_hw", (1080, 1920))) if tiled.get("uhd", True) else None
    return tiled_rows(label, model, x, g, tiled.get("tile", 512), tiled.get("overlap", 128), device, repeats, warmup,
                      untiled, uhd)

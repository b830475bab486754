"""Inference fast paths and tiled inference (floor 2: models, evaluator and experiments may use it).

A *fast path* is a named way to run a model's forward pass; `fp32` is the reference (float32, eager,
contiguous tensors, under torch.no_grad, exactly what bench.evaluate.predict does). The others are
switches, combinable with "+" (e.g. "channels_last+bf16"); every one of them also runs under
torch.inference_mode (no autograd bookkeeping at all, slightly cheaper than no_grad):

  inference_mode  fp32 under torch.inference_mode: the same kernels, so the same numbers.
  channels_last   model weights and every input frame in channels-last (NHWC) memory format; oneDNN
                  convs skip their layout reorders, and the deformable conv writes its output in NHWC.
                  Equal to fp32 up to summation order (~1e-6).
  bf16            torch.autocast(bfloat16): convs and matmuls in bfloat16, accumulation in float32;
                  the output is cast back to float32. About 3 significant digits: equal to fp32 only
                  within a loose tolerance (tests use 5% of the output's range).
  compile         torch.compile(model) (Inductor); the first call compiles (tens of seconds to
                  minutes on a small CPU), later calls reuse it while shapes stay the same. Equal to
                  fp32 up to fusion rounding.

`prepare(model, path)` returns a function (x, g) -> output dict that runs `model` that way, without
modifying `model`. `tiled_predict` runs a model on overlapping LR tiles and stitches the HR output, so
memory is bounded by the tile size (4K frames on a laptop).
"""
from __future__ import annotations

import contextlib
import copy
import ctypes
from dataclasses import dataclass
from typing import Callable

import torch

from bench.nn.blocks import run_sequence

SWITCHES = ("inference_mode", "channels_last", "bf16", "compile")
REFERENCE = "fp32"

# The U-Nets here pool five times (RAE at LR, SRDNet at HR = 2x LR): a tile whose LR origin is a
# multiple of 32 sees the same pooling grid as the whole frame. Harmless for conv-only models.
POOLING_ALIGN = 32


@dataclass(frozen=True)
class FastPath:
    """Which switches a path turns on (see the module docstring)."""
    name: str
    inference_mode: bool = False
    channels_last: bool = False
    bf16: bool = False
    compile: bool = False


def parse_path(name: str | FastPath) -> FastPath:
    """"fp32" (the reference) or switches joined by "+", e.g. "channels_last+bf16"."""
    if isinstance(name, FastPath):
        return name
    if name == REFERENCE:
        return FastPath(name)
    switches = name.split("+")
    unknown = [s for s in switches if s not in SWITCHES]
    if unknown:
        raise ValueError(f"unknown fast path switch {unknown[0]!r} in {name!r}; "
                         f"use {REFERENCE!r} or switches from {SWITCHES} joined by '+'")
    return FastPath(name, **{**{s: True for s in switches}, "inference_mode": True})


def frames_channels_last(t: torch.Tensor | None) -> torch.Tensor | None:
    """A (B, T, C, H, W) or (N, C, H, W) tensor with each frame in channels-last memory format (same
    values and shape): slicing a frame or folding T into the batch then gives NHWC frames."""
    if t is None:
        return None
    if t.dim() == 4:
        return t.contiguous(memory_format=torch.channels_last)
    if t.dim() == 5:
        return t.permute(0, 1, 3, 4, 2).contiguous().permute(0, 1, 4, 2, 3)
    raise ValueError(f"expected a 4-D or 5-D tensor, got shape {tuple(t.shape)}")


@contextlib.contextmanager
def inference_context(path: str | FastPath, device_type: str = "cpu"):
    """Grad mode and autocast of a path: no_grad for fp32, inference_mode for the others, plus
    autocast(bfloat16) for bf16."""
    path = parse_path(path)
    with contextlib.ExitStack() as stack:
        stack.enter_context(torch.inference_mode() if path.inference_mode else torch.no_grad())
        if path.bf16:
            stack.enter_context(torch.autocast(device_type, dtype=torch.bfloat16))
        yield


def prepare_model(model, path: str | FastPath):
    """The module a path runs: `model` itself, a channels-last copy, and/or its torch.compile wrapper.
    `model` is never modified."""
    path = parse_path(path)
    net = model
    if path.channels_last:
        net = copy.deepcopy(model).to(memory_format=torch.channels_last)
    if path.compile:
        net = torch.compile(net)
    return net


def prepare(model, path: str | FastPath = REFERENCE) -> Callable:
    """A function (x, g) -> {"final": ..., ...} running `model` the `path` way; outputs are float32
    (x's dtype) and contiguous whatever the path computed in. Build it once and call it per batch:
    the channels-last copy and the compiled graph are made here, not per call. Outputs of the
    non-fp32 paths are inference tensors: fine for metrics and saving, clone() one before editing
    it in place outside inference_mode."""
    path = parse_path(path)
    net = prepare_model(model, path)

    def run(x, g):
        with inference_context(path, x.device.type):
            if path.channels_last:
                x_in, g_in = frames_channels_last(x), frames_channels_last(g)
            else:
                x_in, g_in = x, g
            out = net(x_in, g_in)
            return {k: v.to(x.dtype).contiguous() for k, v in out.items()}

    run.path, run.net = path, net
    return run


# ---------------------------------------------------------------------------------- process memory

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
_KEPT = []


def keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for reuse: no mmap for big blocks (M_MMAP_MAX=0) and no
    return of the heap top to the OS (M_TRIM_THRESHOLD at its maximum). Returns whether it applied
    (False off glibc). Applies to the whole process, from the next allocation on.

    Why: by default every tensor over 32 MB is a fresh mmap, and its first write page-faults every
    4 KiB page. At 1920x1080 with 32 channels every activation is such a tensor; on the 2-core
    machine this repository is measured on that made a 3x3 conv 1.4-1.8x slower and the proposed
    model about 1.5x slower (6.4 s -> 4.3 s per frame, bf16, same code). The price: the process
    keeps its peak heap (explicit malloc_trim still returns free pages) and may fragment it: 4K
    tiled fp32 peaked at 6.0 GB with it against 3.4 GB without (tiled_predict trims between tiles).
    The CLI calls this (config key keep_freed_memory); a library user can call it too."""
    if _KEPT:
        return _KEPT[0]
    try:
        libc = ctypes.CDLL("libc.so.6")
        applied = bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2 ** 31 - 1))
    except (OSError, AttributeError):
        applied = False
    _KEPT.append(applied)
    return applied


def freed_memory_kept() -> bool:
    """Whether keep_freed_memory() applied in this process."""
    return bool(_KEPT and _KEPT[0])


def release_free_memory() -> None:
    """Return the heap's free memory to the OS now (glibc malloc_trim; a no-op elsewhere)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


# ---------------------------------------------------------------------------------- tiled inference

def _spans(size: int, tile: int, overlap: int) -> list[tuple[int, int, int, int]]:
    """(crop start, core start, core end, crop end) along one axis: cores of `tile` pixels partition
    [0, size); each crop adds `overlap` pixels of context on both sides, clipped to the frame."""
    return [(max(0, c0 - overlap), c0, min(size, c0 + tile), min(size, c0 + tile + overlap))
            for c0 in range(0, size, tile)]


def _round_up(value: int, multiple: int) -> int:
    return -(-value // multiple) * multiple


def _run_tile(net, x, g, fmt):
    """(B, T, 3, s*h, s*w) for one LR crop: a recurrent model streams its frames from a fresh state of
    the crop's own size (init_state / step); any other model runs frame by frame."""
    frames = x.shape[1]
    if getattr(net, "recurrent", False) and hasattr(net, "step"):
        def step(x_t, g_t, state):
            out, state = net.step(fmt(x_t), None if g_t is None else fmt(g_t), state)
            return {"final": out["final"]}, state
        return run_sequence(net.init_state, step, x, g)["final"]
    g_seq = (lambda t: None) if g is None else (lambda t: fmt(g[:, t:t + 1]))
    return torch.cat([net(fmt(x[:, t:t + 1]), g_seq(t))["final"] for t in range(frames)], dim=1)


def tiled_predict(model, x: torch.Tensor, g: torch.Tensor | None, tile: int | tuple[int, int] = 512,
                  overlap: int = 128, path: str | FastPath = REFERENCE, align: int = POOLING_ALIGN,
                  scale: int | None = None) -> torch.Tensor:
    """The model's "final" output (B, T, 3, s*h, s*w) computed on overlapping LR tiles.

    The LR frame is cut into cores of `tile` pixels (int or (rows, cols)); each core is run with
    `overlap` LR pixels of context on every side (clipped at the frame border) and only its core's HR
    pixels are kept, so every output pixel comes from exactly one tile: no blending and no seams. A
    conv-only model gives the untiled output (up to float rounding) once `overlap` >= its receptive
    radius (see `receptive_radius`): at the frame border the crop border is the frame border, and
    padding is the same. U-Nets (RAE, SRDNet) see the whole frame through their bottleneck and
    recurrence, so they match only approximately; tile, overlap and crop origins are rounded up to
    multiples of `align` LR pixels so their pooling grid at least stays the frame's.
    Recurrent models are streamed tile by tile: each tile carries its own state through the T frames,
    and only one tile's activations and state are alive at a time. Peak memory is that of one crop
    plus the output. `path` is a fast path as in `prepare` (compile is not supported: border tiles
    change shape and would recompile).
    """
    path = parse_path(path)
    if path.compile:
        raise ValueError("tiled_predict does not support the compile path (border tiles change shape)")
    net = prepare_model(model, path)
    scale = scale or getattr(model, "scale", 2)
    tile_h, tile_w = (tile, tile) if isinstance(tile, int) else tile
    tile_h, tile_w = _round_up(tile_h, align), _round_up(tile_w, align)
    overlap = _round_up(overlap, align) if overlap > 0 else 0
    b, frames, _, h, w = x.shape
    fmt = frames_channels_last if path.channels_last else (lambda t: t)
    # allocated outside inference_mode: the caller gets an ordinary tensor it may edit in place
    out = torch.empty(b, frames, 3, scale * h, scale * w, dtype=x.dtype, device=x.device)
    with inference_context(path, x.device.type):
        for y0, cy0, cy1, y1 in _spans(h, tile_h, overlap):
            for x0, cx0, cx1, x1 in _spans(w, tile_w, overlap):
                crop_g = g[..., y0:y1, x0:x1] if g is not None else None
                part = _run_tile(net, x[..., y0:y1, x0:x1], crop_g, fmt)
                out[..., scale * cy0:scale * cy1, scale * cx0:scale * cx1] = \
                    part[..., scale * (cy0 - y0):scale * (cy1 - y0), scale * (cx0 - x0):scale * (cx1 - x0)]
                del part
                if freed_memory_kept():  # tiles differ in size: a kept heap fragments and grows
                    release_free_memory()
    return out


def receptive_radius(model, x: torch.Tensor, g: torch.Tensor | None) -> int:
    """LR pixels (Chebyshev distance) from the centre pixel within which the input can change the
    centre output pixel of the LAST frame, measured: the support of the gradient of that output
    w.r.t. every input frame (radiance and gBuffer). Use it on a model with nonzero weights
    (zero-initialised layers hide paths) and an input larger than twice the radius."""
    scale = getattr(model, "scale", 2)
    x, g = x.detach().clone().requires_grad_(True), None if g is None else g.detach().clone().requires_grad_(True)
    h, w = x.shape[-2:]
    cy, cx = h // 2, w // 2
    with torch.enable_grad():
        out = model(x, g)["final"]
        out[:, -1, :, scale * cy, scale * cx].sum().backward()
    support = x.grad.abs().sum(dim=(0, 1, 2))
    if g is not None:
        support = support + g.grad.abs().sum(dim=(0, 1, 2))
    ys, xs = torch.nonzero(support, as_tuple=True)
    if len(ys) == 0:
        return 0
    return int(torch.maximum((ys - cy).abs().max(), (xs - cx).abs().max()))


def max_abs_diff(a: dict | torch.Tensor, b: dict | torch.Tensor) -> float:
    """Largest absolute difference between two outputs (dicts compare their "final")."""
    a = a["final"] if isinstance(a, dict) else a
    b = b["final"] if isinstance(b, dict) else b
    return float((a.float() - b.float()).abs().max())


__all__ = ["FastPath", "POOLING_ALIGN", "REFERENCE", "SWITCHES", "frames_channels_last", "inference_context",
           "freed_memory_kept", "keep_freed_memory", "max_abs_diff", "parse_path", "prepare", "prepare_model",
           "receptive_radius", "release_free_memory", "tiled_predict"]

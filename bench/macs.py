"""Multiply-accumulate (MAC) counting, cross-checked against torch's own counter, and a width solver.

The paper compares methods at a fixed compute budget (about 260 GMac per 960x540 LR frame, Table 5) by
"adjusting the channel number without changing the topologies". That takes three tools, all here: an
analytic per-layer count, a cross-check with `torch.utils.flop_counter.FlopCounterMode`, and a bisection
on the width argument of a model builder.

We count multiply-accumulates (MACs). FlopCounterMode reports FLOPs = 2 x MACs and only sees
matmul / conv / bmm-like ops; grid_sample, interpolation, gathers and elementwise products count zero
there. We convert at the boundary (divide by 2) and report everything in MACs.

Analytic rules (forward hooks; a module called several times, e.g. a recurrent block over T, is summed):
  - nn.Conv1d/2d/3d: out_elements * (in_channels / groups) * prod(kernel_size)
  - nn.ConvTranspose*: in_elements * (out_channels / groups) * prod(kernel_size)
  - nn.Linear: out_elements * in_features
  - any other module with its own 4-D `weight` Parameter (O, I, kh, kw) and no `macs` method is taken
    to be a conv-like layer applied at every output pixel (e.g. a deformable conv doing im2col +
    matmul): out_elements * I * kh * kw. The audit below catches a module for which that is wrong.
  - Hook protocol for layers that are not torch modules of those types (all methods optional):
      `macs(inputs: tuple, output) -> int`: MACs the module computes itself (not in child layers)
          with ops that FlopCounterMode *does* count (conv, matmul, bmm, einsum), e.g. the main
          product of a deformable convolution done as im2col + matmul.
      `extra_macs(inputs: tuple, output) -> int`: MACs FlopCounterMode does *not* see, e.g. the
          bilinear sampling of a deformable convolution (~4 MACs per sampled value: per output pixel,
          per input channel, per kernel tap), or a kernel-predicting filter applied with elementwise
          products. Reported in the row labelled counted_by_torch=False.
    `inputs` is the tuple of positional arguments of the module's forward call.

All counts are exact for the given input shape. Convolutions are linear in the pixel count, so a model
without internal padding scales exactly with H*W; models that pad to a multiple (pooling encoders) do
not, which is why `macs_at` counts at the real target size on the meta device (shapes only, no compute)
instead of extrapolating from a small real forward.

This file is floor 1: no project imports.
"""

from typing import Callable

import pandas as pd
import torch
import torch.nn as nn

_CONV = (nn.Conv1d, nn.Conv2d, nn.Conv3d)
_CONV_T = (nn.ConvTranspose1d, nn.ConvTranspose2d, nn.ConvTranspose3d)
COLUMNS = ["layer", "type", "stage", "macs", "counted_by_torch"]


def _first_tensor(x):
    """The first tensor in a (possibly nested) module output; dict outputs use their first value."""
    if torch.is_tensor(x):
        return x
    if isinstance(x, dict):
        x = list(x.values())
    if isinstance(x, (tuple, list)):
        for item in x:
            found = _first_tensor(item)
            if found is not None:
                return found
    return None


def _builtin_macs(module: nn.Module, inputs: tuple, output) -> int:
    """MACs of a torch conv / linear layer for one call (0 for any other module)."""
    if isinstance(module, _CONV):
        kernel = 1
        for k in module.kernel_size:
            kernel *= k
        return _first_tensor(output).numel() * (module.in_channels // module.groups) * kernel
    if isinstance(module, _CONV_T):
        kernel = 1
        for k in module.kernel_size:
            kernel *= k
        return inputs[0].numel() * (module.out_channels // module.groups) * kernel
    if isinstance(module, nn.Linear):
        return _first_tensor(output).numel() * module.in_features
    if _is_conv_like(module):
        out_ch, in_ch, kh, kw = module.weight.shape
        return _first_tensor(output).numel() * in_ch * kh * kw
    return 0


def _is_conv_like(module: nn.Module) -> bool:
    """A non-torch layer owning a 4-D weight and not declaring its own `macs` (see module docstring)."""
    weight = module._parameters.get("weight")
    return (weight is not None and weight.dim() == 4 and not callable(getattr(module, "macs", None))
            and not isinstance(module, _CONV + _CONV_T))


def _count(model: nn.Module, inputs: tuple, with_torch_counter: bool) -> tuple[pd.DataFrame, int | None]:
    """One no_grad forward with the analytic hooks and, optionally, FlopCounterMode at the same time."""
    totals: dict[tuple[str, bool], int] = {}
    types: dict[str, str] = {}
    handles = []

    def add(name, module, macs, seen):
        if macs:
            totals[(name, seen)] = totals.get((name, seen), 0) + int(macs)
            types[name] = type(module).__name__

    def make_hook(name):
        def hook(module, args, output):
            add(name, module, _builtin_macs(module, args, output), True)
            if callable(getattr(module, "macs", None)):
                add(name, module, module.macs(args, output), True)
            if callable(getattr(module, "extra_macs", None)):
                add(name, module, module.extra_macs(args, output), False)
        return hook

    for name, module in model.named_modules():
        counted = isinstance(module, _CONV + _CONV_T + (nn.Linear,)) or _is_conv_like(module)
        declared = callable(getattr(module, "macs", None)) or callable(getattr(module, "extra_macs", None))
        if counted or declared:
            handles.append(module.register_forward_hook(make_hook(name)))
    from torch.utils.flop_counter import FlopCounterMode  # imports triton where installed: 0.3 s of every process
    counter = FlopCounterMode(display=False) if with_torch_counter else None
    try:
        with torch.no_grad():
            if counter is None:
                model(*inputs)
            else:
                with counter:
                    model(*inputs)
    finally:
        for h in handles:
            h.remove()

    rows = [
        {"layer": name or "(root)", "type": types[name], "stage": name.split(".")[0] or "(root)",
         "macs": macs, "counted_by_torch": seen}
        for (name, seen), macs in totals.items()
    ]
    by_torch = None if counter is None else counter.get_total_flops() // 2
    return pd.DataFrame(rows, columns=COLUMNS), by_torch


def count_macs(model: nn.Module, inputs: tuple) -> pd.DataFrame:
    """Analytic MACs per layer for one forward call `model(*inputs)` (run under no_grad).

    Returns one row per (layer, counted_by_torch) with columns layer (dotted module name), type
    (class name), stage (top-level child name, '(root)' for the model itself), macs (int),
    counted_by_torch (bool: whether FlopCounterMode sees these MACs). Layers with zero MACs are omitted.
    """
    return _count(model, inputs, with_torch_counter=False)[0]


def torch_counter_macs(model: nn.Module, inputs: tuple) -> int:
    """MACs as seen by torch.utils.flop_counter.FlopCounterMode (its FLOPs / 2), forward only.

    It counts matmul/conv/bmm-like ops only: grid_sample, interpolation, gathers and elementwise
    products count zero.
    """
    from torch.utils.flop_counter import FlopCounterMode
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(*inputs)
    return counter.get_total_flops() // 2


def count_params(model: nn.Module) -> int:
    """Number of parameters (works on the meta device)."""
    return sum(p.numel() for p in model.parameters())


def audit(model: nn.Module, inputs: tuple, tolerance: float = 0.01) -> dict:
    """Count MACs both ways and raise if the conv/matmul parts disagree by more than `tolerance`.

    A disagreement means some layer's compute is invisible to the analytic hooks (a functional conv
    or matmul inside a module that does not declare `macs`) or declared wrongly.
    Returns params, macs (analytic total), macs_torch_visible, macs_not_seen_by_torch,
    torch_counter_macs, rel_diff, per_stage ({stage: macs}) and the per-layer table.
    """
    table, by_torch = _count(model, inputs, with_torch_counter=True)  # one forward for both counts
    seen = int(table.loc[table.counted_by_torch, "macs"].sum())
    unseen = int(table.loc[~table.counted_by_torch, "macs"].sum())
    rel_diff = abs(seen - by_torch) / max(by_torch, 1)
    if rel_diff > tolerance:
        raise ValueError(
            f"MAC audit failed for {type(model).__name__}: analytic conv/matmul MACs {seen:,} vs "
            f"FlopCounterMode {by_torch:,} ({100 * rel_diff:.2f}% > {100 * tolerance:.2f}%). "
            "A module probably runs a functional conv/matmul without declaring `macs(inputs, output)`."
        )
    return {
        "params": count_params(model),
        "macs": seen + unseen,
        "macs_torch_visible": seen,
        "macs_not_seen_by_torch": unseen,
        "torch_counter_macs": by_torch,
        "rel_diff": rel_diff,
        "per_stage": table.groupby("stage")["macs"].sum().astype(int).to_dict(),
        "table": table,
    }


def on_meta(build: Callable[[], nn.Module], inputs_fn: Callable[[torch.device], tuple]):
    """Build the model and its inputs on the meta device: exact shapes, no memory, no compute."""
    meta = torch.device("meta")
    with meta:
        model = build()
    return model.eval(), inputs_fn(meta)


def macs_at(build: Callable[[], nn.Module], inputs_fn: Callable[[torch.device], tuple]) -> int:
    """Total analytic MACs of `build()` on `inputs_fn(device)`, counted on the meta device.

    inputs_fn must create its tensors on the device it is given. Counting at the true target size on
    meta avoids both a slow real forward and the inexact pixel scaling of padded models.
    """
    model, inputs = on_meta(build, inputs_fn)
    return int(count_macs(model, inputs)["macs"].sum())


def closest_width(
    build: Callable[[int], nn.Module],
    budget_macs: float,
    inputs_fn: Callable[[torch.device], tuple],
    lo: int = 4,
    hi: int = 256,
) -> tuple[int, int]:
    """The integer width in [lo, hi] whose model's MACs are closest to `budget_macs`, and those MACs.

    MACs grow monotonically with width, so bisect for the largest width under the budget and then pick
    the closer of it and its successor. build(width) returns a model; inputs_fn(device) its inputs.
    """
    cache: dict[int, int] = {}

    def macs(width):
        if width not in cache:
            cache[width] = macs_at(lambda: build(width), inputs_fn)
        return cache[width]

    if macs(lo) >= budget_macs:
        return lo, macs(lo)
    if macs(hi) <= budget_macs:
        return hi, macs(hi)
    low, high = lo, hi  # invariant: macs(low) < budget < macs(high)
    while high - low > 1:
        mid = (low + high) // 2
        if macs(mid) <= budget_macs:
            low = mid
        else:
            high = mid
    width = min((low, high), key=lambda w: abs(macs(w) - budget_macs))
    return width, macs(width)


def fit_width(
    build: Callable[[int], nn.Module],
    budget_macs: float,
    inputs_fn: Callable[[torch.device], tuple],
    lo: int = 4,
    hi: int = 256,
    tolerance: float = 0.05,
) -> tuple[int, int]:
    """closest_width, raising ValueError unless its MACs are within +-tolerance of the budget."""
    width, found = closest_width(build, budget_macs, inputs_fn, lo, hi)
    if abs(found - budget_macs) > tolerance * budget_macs:
        raise ValueError(
            f"no width in [{lo}, {hi}] gives MACs within {100 * tolerance:.0f}% of {budget_macs:.4g}: "
            f"closest is width {width} with {found:.4g} ({100 * (found / budget_macs - 1):+.1f}%)"
        )
    return width, found

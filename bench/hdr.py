"""HDR transforms between linear radiance and the network domain, each with its inverse.

Only the trainer and evaluator apply them (models see network-domain values; metrics see linear ones).

- `clamp`: clip to [0, 1] (the paper normalises its images to [0, 1]); inverse is the identity on [0, 1].
- `log1p`: log(1 + x), x >= 0; inverse expm1. Keeps highlights instead of clipping them.
- `pu`: PU21 (Mantiuk et al. 2021, "banding+glare" fit) applied per channel to x * 100 cd/m^2
  (radiance 1.0 displays at 100 cd/m^2), divided by its value at radiance 1.0 so that 1.0 maps to 1.0.
  Valid for radiance in [5e-5, 100] (the fit's 0.005..10000 cd/m^2); values outside are clipped.
"""
from __future__ import annotations

import functools

import torch

_PU = (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627, 0.09150303166, 0.9099517204, 596.3148142)
_PU_SCALE = 100.0                     # cd/m^2 for radiance 1.0
_PU_RANGE = (0.005, 10000.0)          # cd/m^2


def _pu21(y: torch.Tensor) -> torch.Tensor:
    p1, p2, p3, p4, p5, p6, p7 = _PU
    yp = y ** p4
    return p7 * (((p1 + p2 * yp) / (1 + p3 * yp)) ** p5 - p6)


def _pu21_inverse(v: torch.Tensor) -> torch.Tensor:
    p1, p2, p3, p4, p5, p6, p7 = _PU
    q = (v / p7 + p6).clamp_min(0) ** (1 / p5)
    return ((q - p1).clamp_min(0) / (p2 - p3 * q)) ** (1 / p4)


_PU_ONE = float(_pu21(torch.tensor(_PU_SCALE, dtype=torch.float64)))
_PU_ZERO = float(_pu21(torch.tensor(_PU_RANGE[0], dtype=torch.float64)))
_PU_TOP = float(_pu21(torch.tensor(_PU_RANGE[1], dtype=torch.float64)))

MODES = ("clamp", "log1p", "pu")


def to_network(x: torch.Tensor, mode: str = "clamp") -> torch.Tensor:
    """Linear radiance -> network domain."""
    if mode == "clamp":
        return x.clamp(0.0, 1.0)
    if mode == "log1p":
        return torch.log1p(x.clamp_min(0.0))
    if mode == "pu":
        y = (x * _PU_SCALE).clamp(*_PU_RANGE)
        return (_pu21(y) - _PU_ZERO) / (_PU_ONE - _PU_ZERO)
    raise ValueError(f"unknown HDR transform {mode!r}; choose one of {MODES}")


def transforms(mode: str | None):
    """(to linear, from linear) callables of a network domain, for layers that must not import this
    module (bench.nn.upsampled_input); None for None."""
    if mode is None:
        return None
    # bench.exposure's domains (log1p of radiance over the frame's exposure, which is linear): that module
    # builds on this one, which imports nothing of the project, so they are known by their common prefix
    # (tests/test_hdr.py checks every one of bench.exposure.EXPOSURE_DOMAINS maps to its transfer)
    if mode.startswith("exposure"):
        mode = "log1p"
    if mode not in MODES:
        raise ValueError(f"unknown HDR transform {mode!r}; choose one of {MODES}")
    return functools.partial(from_network, mode=mode), functools.partial(to_network, mode=mode)


def from_network(y: torch.Tensor, mode: str = "clamp") -> torch.Tensor:
    """Network domain -> linear radiance (the inverse of `to_network` on its valid range)."""
    if mode == "clamp":
        return y.clamp(0.0, 1.0)
    if mode == "log1p":
        return torch.expm1(y.clamp_min(0.0))
    if mode == "pu":
        # clip to the fit's range first: far above it the inverse has a pole (NaN), not a saturation
        v = (y * (_PU_ONE - _PU_ZERO) + _PU_ZERO).clamp(_PU_ZERO, _PU_TOP)
        return _pu21_inverse(v) / _PU_SCALE
    raise ValueError(f"unknown HDR transform {mode!r}; choose one of {MODES}")

"""The one model factory: a model config (`_target_` and arguments, conf/model/) built into a plain
`nn.Module` at an upsampling factor. The only call of `hydra.utils.instantiate`; the benchmark's
experiments, `srd-bench export/predict` and the MACs audit all build their models here.
"""
from __future__ import annotations

from hydra.utils import instantiate

from bench.macs import count_params


def build_model(cfg: dict, scale: int):
    """The model of `cfg` ({"_target_": "pkg.module.Class", **arguments}) at upsampling factor `scale`."""
    return instantiate(cfg, scale=scale)


def is_learned(model) -> bool:
    """Whether `model` has parameters to train (bilinear, bicubic and OIDN have none)."""
    return count_params(model) > 0

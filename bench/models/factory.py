"""The one model factory: a model config (`_target_` and arguments, conf/model/) built into a plain
`nn.Module` at an upsampling factor. The only call of `hydra.utils.instantiate`; the benchmark's
experiments, `srd-bench export/predict` and the MACs audit all build their models here.
"""
from __future__ import annotations

from hydra.errors import InstantiationException
from hydra.utils import instantiate

from bench.errors import UserError
from bench.macs import count_params


def build_model(cfg: dict, scale: int):
    """The model of `cfg` ({"_target_": "pkg.module.Class", **arguments}) at upsampling factor `scale`; a
    bad argument is a UserError naming the model and what its constructor said."""
    try:
        return instantiate(cfg, scale=scale)
    except InstantiationException as err:
        said = err.__cause__ if err.__cause__ is not None else err
        raise UserError(f"model {cfg.get('_target_')} with {_arguments(cfg)}: {said}") from err


def _arguments(cfg: dict) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in cfg.items() if not k.startswith("_")) or "no arguments"


def is_learned(model) -> bool:
    """Whether `model` has parameters to train (bilinear, bicubic and OIDN have none)."""
    return count_params(model) > 0

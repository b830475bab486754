"""What every experiment is handed: the typed `Context` the CLI builds from the Hydra config, a row's
model config and training recipe, and the code a run's fingerprint covers.

A row is (model name, argument overrides, task, training overrides, cascade or not). Its identity hashes
only what determines its numbers, so two tables that ask for the same row (the paper reuses "ours" across
Tables 4, 5 and 7) share one run. Identities hash configuration; each run also records the fingerprint of
the code it ran (the model's module, the trainer or evaluator, and what they import:
`runs.code_fingerprint`). A recorded run whose code has changed since is recomputed, and the log names
the changed files; `reuse_stale=true` reuses it.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from bench import runs
from bench.errors import UserError
from bench.tasks import Task, get_task
from bench.train import Recipe


FROZEN_SPLIT = "test"   # scored by the paper's tables and the claims; nothing is chosen on it
TUNING_SPLIT = "val"    # what the recipes, learning rates and studies were chosen on, and learning curves read


def working_split(ctx: "Context") -> str:
    """The split looked at while working (learning curves, the stability table's sample frame): the scored
    split, unless that is the frozen test split; then val, since what is looked at may steer a choice."""
    return TUNING_SPLIT if ctx.eval.split == FROZEN_SPLIT else ctx.eval.split


def training_splits(ctx: "Context") -> set[str]:
    """The splits a training reads: its frames, and the working split its learning curve is scored on.
    An experiment that only trains renders these, never the test split's expensive references."""
    return {"train", working_split(ctx)} & set(ctx.data_spec["splits"])


def split_note(ctx: "Context", split: str) -> str:
    """A caption's sentence on what the scored `split` is for."""
    if split == FROZEN_SPLIT:
        return (f" Split {FROZEN_SPLIT} is frozen: rendered apart (its own seeds), scored only; nothing was "
                f"chosen on it (the recipes, learning rates and studies read {TUNING_SPLIT}; a tuning "
                f"experiment refuses {FROZEN_SPLIT}).")
    if split == TUNING_SPLIT and FROZEN_SPLIT in ctx.data_spec.get("splits", {}):
        return (f" Split {TUNING_SPLIT} is the one the recipe and learning rates were chosen on; the frozen "
                f"{FROZEN_SPLIT} split's table is the one to quote.")
    if split == TUNING_SPLIT:
        return f" This preset's data has no {FROZEN_SPLIT} split: its tables report {TUNING_SPLIT}, the split the recipe was chosen on."
    return ""


@dataclass(frozen=True)
class EvalSpec:
    """How tables evaluate (conf/config.yaml `eval:`, where the defaults and their meaning are)."""
    split: str
    data_dir: Path | None        # another dataset to score (see evaluation_data); None: data_dir
    save_exr: bool
    fast_path: str
    tile: int | None
    rescore_missing: bool        # score again an evaluation recorded before evaluate.LATER_SCORES (FLIP) existed


@dataclass(frozen=True)
class VggSpec:
    """The perceptual loss's features (conf/config.yaml `vgg:`)."""
    weights: str | None
    layer: str
    allow_random: bool


@dataclass
class Context:
    """Everything a table needs, as typed values built by the CLI from the Hydra config (`make_context`);
    the defaults live in conf/, not here. `data_spec` and `models` stay dicts: the data description and
    the model configs (`_target_` + arguments) are recorded and hashed as they are written."""
    preset: str                                     # the size preset's name (smoke, cpu, paper)
    runs_dir: Path
    results_dir: Path
    data_dir: Path
    data_spec: dict
    train: Recipe
    eval: EvalSpec
    vgg: VggSpec
    models: dict
    budget_gmac: float | None                       # the preset's MAC budget per 960x540 frame (GMac)
    seeds: list
    device: str
    workers: int
    force: bool
    progress: bool
    render_data: bool
    model_lr: dict                                  # model name -> peak learning rate (else train.lr)
    shard: tuple[int, int] | None                   # (i, n): a table computes its (row, seed) runs i, i+n, ... first
    reuse_stale: bool                               # reuse runs whose code changed since they were recorded
    runs_archive: Path | None                       # finished trainings and evaluations kept with the results

    @property
    def archives(self) -> tuple[Path, ...]:
        """The archives a recorded run is looked up in after the run store: runs_archive, if any."""
        return (self.runs_archive,) if self.runs_archive is not None else ()


def model_config(ctx: Context, name: str, overrides: dict | None = None) -> dict:
    if name not in ctx.models:
        raise UserError(f"unknown model {name!r}; known models: {', '.join(sorted(ctx.models))} "
                        f"(add one as conf/model/<name>.yaml, see README, 'Adding a model')")
    cfg = copy.deepcopy(ctx.models[name])
    cfg.update(overrides or {})
    return cfg


def deep_merge(base: dict, overrides: dict | None) -> dict:
    """A copy of `base` with `overrides` merged in, nested dicts key by key."""
    out = copy.deepcopy(base)
    for key, value in (overrides or {}).items():
        out[key] = deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) \
            else copy.deepcopy(value)
    return out


def with_training(ctx: Context, overrides: dict | None, model: str | None = None) -> Context:
    """`ctx` with the recipe a row trains with: the model's own learning rate (`model_lr`, from the
    range test), then the row's training overrides (e.g. the perceptual weight) merged in."""
    if model in ctx.model_lr:
        overrides = deep_merge({"lr": ctx.model_lr[model]}, overrides)
    return dataclasses.replace(ctx, train=recipe_from(deep_merge(dataclasses.asdict(ctx.train), overrides))) \
        if overrides else ctx


class RowSetting(NamedTuple):
    """What a table row's runs are computed with."""
    ctx: Context     # with the row's training recipe (`with_training`)
    cfg: dict        # its model's config (`model_config`, the row's overrides in)
    task: Task
    cascade: bool    # the stages trained separately (paper Table 3 "Cascade")


def row_setting(ctx: Context, r: dict) -> RowSetting:
    """The setting of an expanded table row (`bench.experiments.table.expand_rows`)."""
    return RowSetting(with_training(ctx, r.get("train"), r["model"]), model_config(ctx, r["model"], r.get("overrides")),
                      get_task(r["task"]), r.get("cascade", False))


def recipe_from(config: dict) -> Recipe:
    """The training recipe of a `train:` dict, a bad key or value as a UserError."""
    try:
        return Recipe.from_config(config)
    except (TypeError, ValueError) as err:
        raise UserError(f"train: {err}") from err


TRAINING_CODE = ("bench.train", "bench.dataset")

EVALUATION_CODE = ("bench.evaluate", "bench.dataset")

def code_of(cfg: dict, *modules: str) -> dict:
    """Code fingerprint of a run of the model `cfg` that also runs `modules`."""
    return runs.code_fingerprint([cfg["_target_"], *modules])

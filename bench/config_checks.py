"""Checks of a resolved config (plain dicts, no Hydra) before anything runs: every bad value is one line
naming the key, the value and what is allowed (`config_problems`). The CLI (bench/cli.py) calls it from
`make_context`; tables' rows and `+experiment=train`'s row are checked with the command line's values."""
from __future__ import annotations

import re

from bench.errors import UserError

_TRAIN_POSITIVE_INTS = ("steps", "batch_size", "seq_len", "crop", "checkpoint_every")
_TRAIN_NON_NEGATIVE_INTS = ("val_every", "val_sequences")
_TRAIN_POSITIVE_NUMBERS = ("lr", "checkpoint_every_s")
_FLAGS = ("render_data", "force", "reuse_stale", "keep_freed_memory", "progress", "vgg.allow_random", "eval.save_exr")
_TRAIN_RANGES = (  # (key, what is allowed, check)
    ("warmup", "a fraction of the steps in [0, 1)", lambda v: _is_number(v) and 0 <= v < 1),
    ("halve_every", "a fraction of the steps in (0, 1]", lambda v: _is_number(v) and 0 < v <= 1),
    ("ema", "null or a decay in [0, 1)", lambda v: v is None or (_is_number(v) and 0 <= v < 1)),
    ("clip_grad_norm", "null or a positive number", lambda v: v is None or (_is_number(v) and v > 0)),
    ("betas", "two numbers in [0, 1), e.g. [0.9,0.99]",
     lambda v: isinstance(v, list) and len(v) == 2 and all(_is_number(b) and 0 <= b < 1 for b in v)),
    ("colour_permute", "true or false", lambda v: isinstance(v, bool)),
    ("emitters", "a share of the training items in [0, 1]", lambda v: _is_number(v) and 0 <= v <= 1),
    ("fireflies", "a share of the training items in [0, 1]", lambda v: _is_number(v) and 0 <= v <= 1),
    ("emitters_exposure", "with or without", lambda v: v in ("with", "without")),
    ("loss_knee", "null or a number > 0", lambda v: v is None or (_is_number(v) and v > 0)),
    ("channels_last", "true or false", lambda v: isinstance(v, bool)))
# model arguments that are widths or counts (channels, blocks, layers, kernel sizes, ...): integers >= 1,
# or >= 0 for the optional parts (deformable blocks, gBuffer channels)
_MODEL_COUNT = re.compile(r"(channels|blocks|width|layers|size|hidden|dilation)$")
_MODEL_OPTIONAL_COUNT = re.compile(r"deform|gbuffer")


def _lookup(plain: dict, dotted: str):
    value = plain
    for part in dotted.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def train_problems(train: dict, data: dict | None, where: str = "train.") -> list[str]:
    """Bad values of a `train:` dict (`where` names it: the command line's, or a table row's), and a crop
    or sequence length the rendered data (`data`, its spec; None: your own frames) cannot give."""
    problems = [f"{where}{key}={train.get(key)!r}: expected a positive integer"
                for key in _TRAIN_POSITIVE_INTS if not (_is_int(train.get(key)) and train[key] > 0)]
    problems += [f"{where}{key}={train.get(key)!r}: expected an integer >= 0"
                 for key in _TRAIN_NON_NEGATIVE_INTS if not (_is_int(train.get(key)) and train[key] >= 0)]
    problems += [f"{where}{key}={train.get(key)!r}: expected a positive number"
                 for key in _TRAIN_POSITIVE_NUMBERS if not (_is_number(train.get(key)) and train[key] > 0)]
    problems += [f"{where}{key}={value!r}: expected {allowed}" for key, allowed, ok in _TRAIN_RANGES
                 if key in train and not ok(value := train[key])]
    problems += loss_problems(train.get("loss"), where)
    if problems or data is None:
        return problems
    width, height, frames = data.get("lr_width"), data.get("lr_height"), data.get("seq_len")
    if _is_int(width) and _is_int(height) and train["crop"] > min(width, height):
        problems.append(f"{where}crop={train['crop']}: larger than the LR frame {width}x{height} (data.lr_width, "
                        "data.lr_height); the crop must fit inside it")
    if _is_int(frames) and train["seq_len"] > frames:
        problems.append(f"{where}seq_len={train['seq_len']}: longer than the dataset's sequences "
                        f"({frames} frames, data.seq_len)")
    return problems


def loss_problems(loss, where: str) -> list[str]:
    """Bad loss weights: each stage's terms known to bench.losses, each weight a number >= 0."""
    from bench.losses import absolute_weights
    problems = []
    for stage, weights in (loss or {}).items():
        if not isinstance(weights, dict):
            problems.append(f"{where}loss.{stage}={weights!r}: expected a mapping of loss terms to weights")
            continue
        bad = [f"{where}loss.{stage}.{term}={w!r}: expected a number >= 0" for term, w in weights.items()
               if not (_is_number(w) and w >= 0)]
        if not bad and any(weights.values()):  # all zero: the stage's loss is off (bench.train)
            try:
                absolute_weights(weights)
            except ValueError as err:
                bad = [f"{where}loss.{stage}: {err}"]
        problems += bad
    return problems


def model_problems(model: dict, where: str) -> list[str]:
    """Bad widths and counts among a model's arguments (`where` names the model: models.srd, a row)."""
    problems = []
    for key, value in model.items():
        if key.startswith("_") or not _MODEL_COUNT.search(key):
            continue
        least = 0 if _MODEL_OPTIONAL_COUNT.search(key) else 1
        if not (_is_int(value) and value >= least):
            problems.append(f"{where}.{key}={value!r}: expected an integer >= {least}")
    return problems


def row_problems(plain: dict, data: dict | None) -> list[str]:
    """Bad values inside a table experiment's rows (or the one row of `+experiment=train`): their model
    arguments and training overrides."""
    from bench.experiments.context import deep_merge
    from bench.experiments.one_model import one_row
    from bench.experiments.table import expand_rows
    experiment = plain.get("experiment") or {}
    kind = experiment.get("kind", "table")
    try:
        if kind == "one_model":  # one row, written as a table's
            rows = expand_rows([one_row(**{k: experiment.get(k) for k in ("model", "overrides", "task", "train",
                                                                          "cascade", "label") if k in experiment})])
        elif kind == "table" and isinstance(experiment.get("rows"), list):
            rows = expand_rows(experiment["rows"], experiment.get("task", "srd"))
        else:
            return []
    except (ValueError, KeyError, TypeError) as err:
        return [f"experiment.rows: {err}"]
    problems = []
    shared = set(train_problems(plain["train"], data))  # said once, for train.*, not again per row
    for r in rows:
        where = "experiment" if kind == "one_model" else f"experiment.rows[{r['label']!r}]"
        problems += model_problems(r.get("overrides") or {}, f"{where}.overrides")
        if r.get("cascade") and r["model"] in (plain.get("models") or {}):  # an unknown one: model_config says
            problems += cascade_problems(deep_merge((plain.get("models") or {}).get(r["model"]) or {},
                                                   r.get("overrides")), where)
        if not isinstance(r.get("train") or {}, dict):
            problems.append(f"{where}.train={r.get('train')!r}: expected a dict of train.* overrides")
            continue
        train = deep_merge(plain["train"], r.get("train"))
        own = train_problems(train, data, f"{where}.train.")
        problems += [p for p in own if "train." + p.removeprefix(f"{where}.train.") not in shared]
        own_recipe = [p for p in recipe_problems(train) if not _said(p, own, f"{where}.train.")]
        problems += [f"{where}.{p}" for p in own_recipe if p not in recipe_problems(plain["train"])]
    return problems


def cascade_problems(model: dict, where: str) -> list[str]:
    """A Cascade row trains the proposed model's stages apart, which exchange RGB images only
    (SRDNet.forward_stage): it needs SRDNet with channel_aug and skip off."""
    if model.get("_target_") != "bench.models.srd.SRDNet":
        return [f"{where}.cascade=true: a Cascade trains the proposed model's stages apart (model srd), "
                f"not {model.get('_target_')}"]
    on = [key for key in ("channel_aug", "skip") if model.get(key, True)]
    if on:
        return [f"{where}.cascade=true: its stages exchange RGB images only, so it needs "
                + " and ".join(f"{key}=false" for key in on) + " in its overrides (conf/experiment/stage_order.yaml)"]
    return []


def _said(recipe_line: str, problems: list[str], where: str) -> bool:
    """Whether the Recipe's line is about a key `problems` already name: the Recipe checks a few values
    these checks do too (the shares of lamp and firefly items, ...), and a value is one line, not two."""
    key = re.search(r"train\.(\w+)", recipe_line)
    return bool(key) and any(p.startswith(f"{where}{key.group(1)}=") for p in problems)


def recipe_problems(train: dict) -> list[str]:
    """A `train:` dict's unknown or missing keys, or a bad schedule, domain or precision: [] or one line."""
    from bench.experiments.context import recipe_from
    try:
        recipe_from(train)
    except UserError as err:
        return [str(err)]
    return []


def config_problems(plain: dict) -> list[str]:
    """What is wrong with a resolved config, one line per bad value: the key, the value, what is allowed."""
    from bench.infer import parse_path
    data = plain["data"] if plain["render_data"] else None  # your own frames: checked at start
    problems = train_problems(plain["train"], data)
    problems += [p for p in recipe_problems(plain["train"]) if not _said(p, problems, "train.")]
    if not (_is_int(plain.get("workers")) and plain["workers"] > 0):
        problems.append(f"workers={plain.get('workers')!r}: expected a positive integer")
    if not (_is_int(plain.get("jobs")) and plain["jobs"] > 0):
        problems.append(f"jobs={plain.get('jobs')!r}: expected a positive integer")
    elif plain["jobs"] > 1 and plain.get("shard") is not None:
        problems.append(f"jobs={plain['jobs']} with shard={plain['shard']}: jobs starts the shards itself; give one of them")
    for name, model in (plain.get("models") or {}).items():
        problems += model_problems(model or {}, f"models.{name}")
    problems += row_problems(plain, data)
    seeds = plain.get("seeds")
    if not (isinstance(seeds, list) and seeds and all(_is_int(s) for s in seeds)):
        problems.append(f"seeds={seeds!r}: expected a non-empty list of integers, e.g. seeds=[0,1,2]")
    elif len(set(seeds)) < len(seeds):  # one run twice: a spread of 0 that looks like no seed noise
        problems.append(f"seeds={seeds!r}: a seed named twice; give distinct seeds, e.g. seeds=[0,1,2]")
    for name, lr in (plain.get("model_lr") or {}).items():
        if not (_is_number(lr) and lr > 0):
            problems.append(f"model_lr.{name}={lr!r}: expected a positive number")
        if name not in (plain.get("models") or {}):
            problems.append(f"model_lr.{name}: no model {name} (models: {', '.join(plain.get('models') or {})})")
    # a missing flag (None) is its reader's to name
    problems += [f"{key}={_lookup(plain, key)!r}: expected true or false" for key in _FLAGS
                 if not isinstance(_lookup(plain, key), (bool, type(None)))]
    try:
        if _lookup(plain, "eval.fast_path") != "auto":  # auto: chosen by measurement (bench.measure)
            parse_path(_lookup(plain, "eval.fast_path"))
    except (ValueError, AttributeError) as err:
        problems.append(f"eval.fast_path={_lookup(plain, 'eval.fast_path')!r}: {err}")
    if plain["tracking"] not in ("mlflow", "none"):
        problems.append(f"tracking={plain['tracking']!r}: expected mlflow or none")
    tile = _lookup(plain, "eval.tile")
    if tile is not None and not (_is_int(tile) and tile > 0):
        problems.append(f"eval.tile={tile!r}: expected null (whole frames) or a positive integer")
    return problems

"""Command line: `python -m bench +experiment=NAME [preset=smoke|cpu|gpu|paper] [key=value ...]`; a study
(conf/study/, docs/studies.md) instead of an experiment: `python -m bench +study=NAME ...`.

The only module that reads the Hydra config: it turns it into a plain `Context` and the experiment's
parameters, calls the experiment, and prints user errors as one line instead of a traceback.
"""
from __future__ import annotations

import importlib
import inspect
import logging
import os
import re
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import hydra
import yaml
from omegaconf import DictConfig, OmegaConf

from bench.config_checks import config_problems
from bench.errors import UserError
from bench.runs import (COMMITTED_RESULTS, PATH_ERRORS, ROOT, committed_archive, ensure_writable, error_line,
                        out_of_space, probe_write)
from bench.experiments import KINDS, RUNLESS_KINDS

log = logging.getLogger("bench")
CONF_DIR = str(ROOT / "conf")
DEFAULT_ARCHIVE = "${results_dir}/runs"  # conf/config.yaml's runs_archive: it follows results_dir


def hydra_output_dir(runs_dir: str) -> str:
    """Hydra's own output folder (conf/config.yaml `hydra.run.dir`): `<runs_dir>/hydra` when it can be
    written, else one under the system's temporary folder. Hydra creates it before any of our code runs,
    so an unwritable runs_dir must not fail there (a traceback) but in run_experiment (one line).
    Under torchrun each rank other than 0 gets a folder of its own (`hydra/rank<N>`) for its log."""
    path = Path(runs_dir) / "hydra"
    if int(os.environ.get("RANK", "0")) > 0:
        path = path / f"rank{os.environ['RANK']}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        if os.access(path, os.W_OK):
            return str(path)
    except OSError:
        pass
    return str(Path(tempfile.gettempdir()) / "srd-bench-hydra")


OmegaConf.register_new_resolver("hydra_output_dir", hydra_output_dir, replace=True)
# Arithmetic for configs that scale with the preset, e.g. a crop twice the preset's but inside the frame:
# ${min:${data.lr_height},${mul:2,${train.crop}}}
OmegaConf.register_new_resolver("mul", lambda a, b: a * b, replace=True)
OmegaConf.register_new_resolver("min", lambda *values: min(values), replace=True)


def available_experiments() -> list[str]:
    return sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))


def available_studies() -> list[str]:
    return sorted(p.stem for p in (Path(CONF_DIR) / "study").glob("*.yaml"))


def choice_problem(args: list[str]) -> str | None:
    """What is wrong with the command line's `+experiment=`/`+study=` choices, before Hydra composes them (its
    own message is a traceback-like block): a name that does not exist, or an experiment and a study together;
    then a plain key the config lacks (`key_problem`)."""
    available = {"experiment": available_experiments(), "study": available_studies()}
    chosen = set()  # (group, name)
    for arg in args:
        match = re.fullmatch(r"\+{0,2}(experiment|study)=([\w,]+)", arg)  # names, or a sweep's a,b,c
        if not match:
            continue
        group, names = match.groups()
        for name in names.split(","):
            if name not in available[group]:
                return f"+{group}={name}: no conf/{group}/{name}.yaml; available: {', '.join(available[group])}"
            chosen.add((group, name))
    if len({group for group, _ in chosen}) == 2:
        return "choose an experiment or a study, not both: +experiment=NAME or +study=NAME"
    return key_problem(args, chosen)


def _dotted_keys(tree, prefix: str = "") -> set[str]:
    """Every key of a YAML mapping as a dotted path (a.b.c), the mappings' own included."""
    if not isinstance(tree, dict):
        return set()
    out = set()
    for key, value in tree.items():
        path = f"{prefix}{key}"
        out |= {path} | _dotted_keys(value, path + ".")
    return out


def _config_keys(path: Path) -> set[str]:
    """The top-level keys a conf/ YAML file sets."""
    return set(yaml.safe_load(path.read_text()) or {}) - {"defaults"}


def key_problem(args: list[str], chosen: set[tuple[str, str]]) -> str | None:
    """A plain `key=value` whose key no config file has at the top (Hydra's own message is six lines): one
    line, naming where a key of that name is, e.g. `+experiment=data verify=true` means
    `experiment.verify=true`, `steps=9` means `train.steps=9`. `chosen`: the (experiment|study, name)
    pairs of the command line. The other config files are read only for a key that config.yaml and the
    groups do not name, so a command's start pays for one small file."""
    conf = Path(CONF_DIR)
    plain = [(m.group(1), arg) for arg in args if (m := re.fullmatch(r"(\w+)=.*", arg))]  # no +, ~, dots or @
    known = {p.name for p in conf.iterdir() if p.is_dir()} | _config_keys(conf / "config.yaml")  # groups: preset=...
    if all(key in known for key, _ in plain):
        return None
    near = [conf / "config.yaml", *conf.glob("preset/*.yaml")]
    trees = {path: yaml.safe_load(path.read_text()) or {}
             for path in [*near, *conf.glob("experiment/*.yaml"), *conf.glob("study/*.yaml")]}
    for tree in trees.values():
        known |= set(tree) - {"defaults"}
    for key, arg in plain:
        if key in known:
            continue
        paths = sorted({p for group, name in chosen for p in _dotted_keys(trees[conf / group / f"{name}.yaml"])
                        if p.endswith("." + key)}
                       or {p for path in near for p in _dotted_keys(trees[path]) if p.endswith("." + key)}, key=len)
        where = f"; write {paths[0]}={arg.split('=', 1)[1]}" if paths else " (a new key is +KEY=...)"
        return f"{arg}: the config has no key `{key}` at the top{where}"
    return None


PATH_KEYS = ("data_dir", "runs_dir", "results_dir")  # conf/config.yaml: relative to the working directory
# Hydra's flags that run nothing, and those that bring a config of their own (which may set the paths)
_NOTHING_RUNS = ("-h", "--help", "--hydra-help", "--info", "-i", "--version", "-c", "--cfg", "-sc",
                 "--shell-completion", "-cd", "--config-dir", "-cn", "--config-name", "-cp", "--config-path")


def working_dir_problem(args: list[str], cwd: Path | None = None) -> str | None:
    """Run from elsewhere than the project, the default data, run store and results folders would be new
    ones there: the committed tables and their recorded runs not found, so rendered and trained again
    under that folder (or missing). One line instead, unless the command line gives all three paths."""
    cwd = cwd or Path.cwd()
    if os.path.samefile(cwd, ROOT) or any(arg.split("=", 1)[0] in _NOTHING_RUNS for arg in args):
        return None
    given = {arg.split("=", 1)[0].lstrip("+") for arg in args if "=" in arg}
    missing = [key for key in PATH_KEYS if key not in given]
    if not missing:
        return None
    return (f"the working directory {cwd.resolve()} is not the project's ({ROOT}): {', '.join(missing)} would be "
            f"folders under it, where the committed tables' recorded runs are not: they would be rendered and "
            f"trained again there (or found missing); cd {ROOT}, or give " + " ".join(f"{key}=..." for key in missing))


def hydra_dir_problem(args: list[str]) -> str | None:
    """`hydra.run.dir=` (or with -m, `hydra.sweep.dir=`) where nothing can be written: Hydra would fail
    there with a traceback before any of our code runs. Checked on the nearest folder that exists;
    nothing is created."""
    sweep = any(arg in ("-m", "--multirun", "hydra.mode=MULTIRUN") for arg in args)
    for arg in args:
        match = re.fullmatch(r"\+{0,2}(hydra\.(run|sweep)\.dir)=([^$]+)", arg)
        if not match or (match.group(2) == "sweep") != sweep:
            continue
        path = Path(match.group(3).strip("'\""))
        existing = next(p for p in (path.absolute(), *path.absolute().parents) if p.exists())
        try:
            probe_write(existing)
        except OSError as err:
            return (f"{match.group(1)}={match.group(3)}: nothing can be written in {existing} ({err.strerror}), so "
                    f"Hydra cannot write its log there; set {match.group(1)}=... to a writable place")
    return None


def composition_problem(args: list[str]) -> str | None:
    """What Hydra cannot compose from the command line (a misspelt dotted key, an unknown preset, a value it
    cannot parse) as one line: its own message is a block, with exit 1. Left to Hydra when a flag is given
    (-m sweeps, --cfg), whose values it reads itself."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    if any(arg.startswith(("-", "hydra.mode=")) for arg in args):
        return None
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
            compose(config_name="config", overrides=args)
    except HydraException as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        missing = re.fullmatch(r"Could not override '(.+)'\.", lines[0])
        if missing and isinstance(err.__cause__, Exception) and "not in struct" in str(err.__cause__):
            arg = next((a for a in args if a.split("=", 1)[0] == missing.group(1)), missing.group(1))
            return f"{arg}: the config has no key {missing.group(1)} (a new key is +{arg})"
        if "Config search path:" in lines:
            lines = lines[:lines.index("Config search path:")]
        if err.__cause__ is not None and str(err.__cause__).strip():  # e.g. "Error merging override ...": why
            lines.append(str(err.__cause__).strip().splitlines()[0])
        said, listing = lines[0], False  # a heading's items ("Available options in 'preset':") on its line
        for before, line in zip(lines, lines[1:]):
            listing = before.endswith(":") or (listing and not line.endswith(":"))
            said += (" " if before.endswith(":") else ", " if listing else "; ") + line
        return said
    except Exception:  # noqa: BLE001 - anything else is Hydra's to say, as it would without this check
        return None
    return None


def make_context(cfg: DictConfig):
    from bench.experiments.context import Context, EvalSpec, VggSpec, recipe_from
    plain = OmegaConf.to_container(cfg, resolve=True)
    plain["eval"]["split"] = plain["eval"]["split"] or reported_split(cfg)  # apply_split's, when it ran
    problems = config_problems(plain)
    if problems:  # one bad value: one line
        listed = problems[0] if len(problems) == 1 else "\n  " + "\n  ".join(problems)
        raise UserError(f"bad config (nothing was run): {listed}")
    try:
        evaluation, vgg = EvalSpec(**plain["eval"]), VggSpec(**plain["vgg"])
    except TypeError as err:  # a key that is not a field (a typo in an override)
        raise UserError(f"bad config (nothing was run): eval or vgg: {err}") from None
    return Context(preset=plain["preset"]["name"], runs_dir=Path(plain["runs_dir"]),
                   results_dir=Path(plain["results_dir"]), data_dir=Path(plain["data_dir"]),
                   data_spec=plain["data"], train=recipe_from(plain["train"]), eval=evaluation, vgg=vgg,
                   models=plain["models"], budget_gmac=plain["preset"]["budget_gmac"], seeds=list(plain["seeds"]),
                   device=plain["device"], workers=plain["workers"], force=plain["force"],
                   progress=plain["progress"], render_data=plain["render_data"],
                   model_lr=plain.get("model_lr") or {}, shard=parse_shard(plain.get("shard")),
                   reuse_stale=plain["reuse_stale"],
                   runs_archive=Path(plain["runs_archive"]) if plain.get("runs_archive") else None)


def parse_shard(value) -> tuple[int, int] | None:
    """`shard=i/n` (0 <= i < n) -> (i, n); null -> None."""
    if value is None:
        return None
    try:
        index, count = (int(part) for part in str(value).split("/"))
    except ValueError:
        index, count = -1, 0
    if not 0 <= index < count:
        raise UserError(f"shard={value!r}: expected i/n with 0 <= i < n, e.g. shard=0/2")
    return index, count


def resolve_device(device: str) -> str:
    import torch
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise UserError("device=cuda but no CUDA GPU is available; use device=cpu or device=auto")
    if device not in ("cpu", "cuda"):
        raise UserError(f"device must be auto, cpu or cuda, got {device!r}")
    return device


def run_all(overrides: list[str], results_dir: Path, tables: list[str], name: str = "all") -> None:
    """Run each experiment in `tables` with the command line's other `overrides`, one after the other;
    write each one's wall time and recorded compute to `<results_dir>/<name>/table.{csv,md,tex}`, and a last row
    that counts every run once; then rewrite the results page `<results_dir>/README.md` from the tables.
    Runs shared between tables are trained once (the run store), so a restarted `all` continues where it
    stopped."""
    import pandas as pd
    from hydra import compose
    from bench.experiments import results_page
    from bench.table_writer import write_table
    available = [e for e in available_experiments() if e != "all"]
    if not isinstance(tables, list) or not tables:
        raise UserError(f"experiment.tables={tables!r}: expected a non-empty list of experiments, e.g. [sota,dilation]")
    unknown = [t for t in tables if t not in available]
    if unknown:  # before the first table runs (it may train for hours)
        raise UserError(f"experiment.tables: unknown experiment {unknown[0]!r}; available: {', '.join(available)}")
    rows, every_run, preset = [], {}, None
    for experiment in tables:
        t0 = time.perf_counter()
        cfg = compose(config_name="config", overrides=overrides + [f"+experiment={experiment}"])
        run_experiment(cfg)
        preset = cfg.preset.name
        archives = (cfg.runs_archive,) if cfg.get("runs_archive") else ()
        summary, minutes = table_summary(Path(cfg.results_dir) / experiment, cfg.runs_dir, archives)
        every_run.update(minutes)
        rows.append({"experiment": experiment, **summary, "this invocation (min)": (time.perf_counter() - t0) / 60})
        total = {"experiment": "all (each run once)", "this invocation (min)": sum(r["this invocation (min)"] for r in rows),
                 **compute_columns(every_run)}
        write_table(pd.DataFrame(rows + [total]), results_dir / name,
                    caption="Time per table of `+experiment=all`. compute: the training and evaluation wall time "
                            "of the table's runs as recorded in the run store or its archive, whenever and "
                            "wherever they ran (every seed; a run shared by several tables counts in each, and "
                            "once in the last row; empty for tables that are not made of trained rows). "
                            "trainings: the distinct training runs (each stage of a Cascade counts). runs not found: "
                            "runs of the table neither the store nor the archive holds, left out of compute (a "
                            "missing training still counts in trainings; a missing evaluation hides its "
                            "trainings from both). 'order as "
                            "paper': pairs of rows whose order by that metric is the paper's, of the pairs both "
                            "have. this invocation: wall time of this command, ~0 for reused runs.")
    if preset is not None:
        log.info("results page: %s", results_page.write(results_dir, preset))


def compute_columns(minutes: dict[str, float | None]) -> dict:
    """The compute (min), trainings and runs not found columns of `run_all`'s table, from
    `recorded_minutes` (None: a run neither the store nor the archive holds)."""
    return {"compute (min)": float(sum(m for m in minutes.values() if m is not None)),
            "trainings": sum(key.startswith("train/") for key in minutes),
            "runs not found": sum(m is None for m in minutes.values())}


def table_summary(table_dir: Path, runs_dir, archives=()) -> tuple[dict, dict[str, float | None]]:
    """From a table's table.csv: the recorded minutes of its distinct runs (`recorded_minutes`), their
    compute columns and, per metric, the pairs of rows ordered as in the paper (empty for tables that
    are not made of trained rows)."""
    from bench.experiments.row import recorded_minutes
    from bench.experiments.table import paper_agreement
    from bench.table_writer import listed_evaluations, read_table
    path = table_dir / "table.csv"
    if not path.exists():
        return {}, {}
    table = read_table(path)
    out, minutes = {}, {}
    if "train (min)" in table:
        minutes = recorded_minutes([h for cell in table["runs"] for h in listed_evaluations(cell)], runs_dir, archives)
        out.update(compute_columns(minutes))
        if out["runs not found"]:
            log.warning("%s: %d of its runs are in neither the run store nor the archive; compute (min) "
                        "leaves them out", table_dir.name, out["runs not found"])
    for metric, (agree, total) in paper_agreement(table).items():
        out[f"{metric} order as paper"] = f"{agree}/{total}"
    return out, minutes


def _sweep_job_results(cfg: DictConfig) -> None:
    """With -m (a sweep), each job writes its tables under results_dir/sweeps/<its overrides>, so jobs
    never overwrite each other's tables; their runs still share the run store."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return
    job = HydraConfig.get().job
    folder = re.sub(r"[^\w=.,+-]", "_", job.override_dirname) or f"job{job.num}"
    cfg.runs_archive = OmegaConf.select(cfg, "runs_archive")  # resolved: the archive stays where it is
    cfg.results_dir = str(Path(cfg.results_dir) / "sweeps" / folder)
    log.info("sweep job %s: tables go to %s", job.num, cfg.results_dir)


def reported_split(cfg: DictConfig) -> str:
    """The split an experiment reports, its results_dir's own: the data's frozen test split where it has
    one (else val), or val for an experiment that tunes (`experiment.tunes`: it chooses on what it scores)."""
    from bench.experiments.context import FROZEN_SPLIT, TUNING_SPLIT
    tunes = bool(OmegaConf.select(cfg, "experiment.tunes", default=False))
    splits = OmegaConf.select(cfg, "data.splits", default=None) or {}
    return TUNING_SPLIT if tunes or FROZEN_SPLIT not in splits else FROZEN_SPLIT


def apply_split(cfg: DictConfig) -> None:
    """Resolve `eval.split` in place (null: `reported_split`); an experiment that tunes may not read the
    frozen test split. Where the experiment reports the test split, tables of the preset's data on another
    split go to `<results_dir>/<split>/`, beside its own (e.g. results/cpu/val/sota); your frames'
    (`eval.data_dir`) go to results_dir as given, and their models are read from the preset's committed
    archive unless runs_archive is given."""
    from bench.experiments.context import FROZEN_SPLIT, TUNING_SPLIT
    reported = reported_split(cfg)
    split = cfg.eval.split or reported
    if split == FROZEN_SPLIT and OmegaConf.select(cfg, "experiment.tunes", default=False):
        raise UserError(f"eval.split={FROZEN_SPLIT}: this experiment tunes (chooses settings on what it scores), "
                        f"and the {FROZEN_SPLIT} split is frozen: nothing may be chosen on it; use "
                        f"eval.split={TUNING_SPLIT}")
    splits = list(OmegaConf.select(cfg, "data.splits", default=None) or {})
    if cfg.render_data and not cfg.eval.data_dir and splits and split not in splits:  # your frames: any name
        raise UserError(f"eval.split={split}: the {cfg.preset.name} preset's data has no such split; it has "
                        f"{', '.join(splits)}")
    cfg.eval.split = split
    if cfg.eval.data_dir and OmegaConf.to_container(cfg, resolve=False).get("runs_archive") == DEFAULT_ARCHIVE:
        # your frames are scored with the recorded trainings and nothing is archived: read the preset's
        # committed archive wherever results_dir points (else results_dir=/tmp/mine would find no model)
        cfg.runs_archive = str(committed_archive(cfg.preset.name))
    if reported == FROZEN_SPLIT and split != reported and not cfg.eval.data_dir:
        cfg.runs_archive = OmegaConf.select(cfg, "runs_archive")  # resolved: the archive stays where it is
        cfg.results_dir = str(Path(cfg.results_dir) / split)
        log.info("eval.split=%s: tables go to %s (the %s split's are in the folder above)", split,
                 cfg.results_dir, reported)


def apply_pin(cfg: DictConfig) -> None:
    """Merge the experiment's pin for this preset (`experiment.pin.<preset>`, conf/pin/) over `train`, in
    place and before anything resolves, so that the rows' `${train.steps}` see it too. Taken by
    `+experiment=lr_range` and `+study=dark_bias` (conf/pin/studies.yaml), which keep the recipe they were
    measured at, and `+experiment=generalization` (conf/pin/generalization.yaml), which keeps the domain its
    cpu table scored. A pin wins over `train.*` on the command line; `experiment.pin.<preset>.<key>=...`
    changes it."""
    pin = OmegaConf.select(cfg, f"experiment.pin.{cfg.preset.name}", default=None)
    if pin is not None:
        cfg.train = OmegaConf.merge(cfg.train, pin)


def check_experiment_keys(experiment, keys: dict, kind: str, supplied: tuple[str, ...] = ("ctx",)) -> None:
    """A misspelt or missing `experiment.<key>` is one line naming the keys its kind takes, before anything
    runs (not a TypeError from the call); `supplied`: the arguments the caller passes itself."""
    signature = inspect.signature(experiment)
    takes = [name for name in signature.parameters if name not in supplied]
    try:
        signature.bind(**dict.fromkeys(supplied), **keys)
    except TypeError as err:
        unknown = sorted(set(keys) - set(takes))
        raise UserError(f"experiment {keys.get('name', kind)!r} (kind {kind}): "
                        + (f"no key {', '.join(unknown)}" if unknown else str(err))
                        + f"; kind {kind} takes {', '.join(takes)}") from None
    for key, value in keys.items():  # a YAML `no` or a typo'd flag is a string, and a string is true
        parameter = signature.parameters.get(key)
        if parameter is not None and parameter.annotation in (bool, "bool") and not isinstance(value, bool):
            raise UserError(f"experiment.{key}={value!r}: expected true or false")


def warn_if_committed_archive_unread(ctx, kind: str, preset: str) -> None:
    """runs_archive follows results_dir: elsewhere, the preset's recorded runs would all be computed again.
    Said for experiments that read runs (not macs, speed), never for your own frames' (never archived)."""
    committed = committed_archive(preset)
    if kind not in RUNLESS_KINDS and ctx.render_data and not ctx.eval.data_dir and ctx.runs_archive is not None \
            and ctx.runs_archive.resolve() != committed.resolve() and not ctx.runs_archive.exists() \
            and committed.is_dir():
        log.warning("runs_archive=%s (by default it follows results_dir) holds no runs: the committed archive "
                    "%s is not read, so recorded runs are computed again; runs_archive=%s reads it",
                    ctx.runs_archive, committed.relative_to(ROOT), committed)


def run_experiment(cfg: DictConfig) -> None:
    from bench.train import TrainingInterrupted  # torch: imported once the command line is known to be good
    if "experiment" not in cfg:
        raise UserError("choose an experiment: python -m bench +experiment=NAME; available: "
                        + ", ".join(available_experiments()) + "; or a study, +study=NAME: "
                        + ", ".join(available_studies()))
    apply_pin(cfg)
    apply_split(cfg)
    exp = OmegaConf.to_container(cfg.experiment, resolve=True)
    exp.pop("pin", None)
    exp.pop("tunes", None)
    kind = exp.pop("kind", "table")
    if kind == "all":
        check_experiment_keys(run_all, exp, kind, supplied=("overrides", "results_dir"))
        from hydra.core.hydra_config import HydraConfig
        overrides = [o for o in HydraConfig.get().overrides.task if not o.lstrip("+").startswith("experiment")]
        t0 = time.perf_counter()
        run_all(overrides, Path(cfg.results_dir), **exp)
        log.info("all done in %.1f min", (time.perf_counter() - t0) / 60)
        return
    if kind not in KINDS:
        raise UserError(f"experiment kind {kind!r} is unknown; known kinds: {', '.join(KINDS)}")
    experiment = importlib.import_module(f"bench.experiments.{kind}").run
    check_experiment_keys(experiment, exp, kind)
    _sweep_job_results(cfg)
    ctx = make_context(cfg)
    ctx.device = resolve_device(ctx.device)
    yours = not ctx.render_data or ctx.eval.data_dir
    if yours and ctx.results_dir.resolve().is_relative_to(COMMITTED_RESULTS):
        raise UserError(f"results_dir={ctx.results_dir}: your frames' tables would replace the committed ones in "
                        f"{COMMITTED_RESULTS.name}/ (and a training on them would join its archive); give "
                        "results_dir=/elsewhere (e.g. results_dir=/tmp/mine)")
    ensure_writable(ctx.results_dir, "results_dir")
    ensure_writable(ctx.runs_dir, "runs_dir")
    if yours and ctx.results_dir.resolve().is_relative_to(ROOT):
        log.warning("your frames' tables and crops go to %s, inside the repository where git would commit "
                    "them; results_dir=/elsewhere keeps them out", ctx.results_dir)
    warn_if_committed_archive_unread(ctx, kind, cfg.preset.name)
    t0 = time.perf_counter()
    interrupted = False
    try:
        if cfg.jobs > 1:
            run_jobs(kind, cfg.jobs)
        experiment(ctx, **exp)
    except (KeyboardInterrupt, TrainingInterrupted):
        interrupted = True  # stop now: a scheduler's grace period is short; the next command mirrors them
        raise
    finally:  # what completed before a failure is worth browsing too
        if not interrupted:
            mirror_runs(cfg.tracking, ctx.runs_dir, cfg.tracking_uri, ctx.results_dir)
    log.info("%s done in %.1f s", exp.get("name", kind), time.perf_counter() - t0)


SHARDED_KINDS = ("table", "one_model")  # the kinds whose runs `shard=` divides (bench.experiments.table)


def run_jobs(kind: str, jobs: int) -> None:
    """`jobs=N`: the command's runs computed by N shards at once (bench.scheduler), before the command
    itself writes the table from them."""
    from hydra.core.hydra_config import HydraConfig
    from bench import scheduler
    if kind not in SHARDED_KINDS:
        raise UserError(f"jobs: experiment kind {kind!r} computes its runs in one process; jobs=N is for "
                        f"{' and '.join(SHARDED_KINDS)} experiments (the paper's tables, +experiment=train)")
    log.info("jobs=%d: the runs are computed by %d shards at once, %d threads each on this CPU's cores; then "
             "the table", jobs, jobs, scheduler.threads_per_job(jobs))
    scheduler.run_shards(list(HydraConfig.get().overrides.task), jobs, Path.cwd())


def run_or_serve(cfg: DictConfig) -> None:
    """Run the experiment; under torchrun (bench.distributed) rank 0 runs it and the other ranks only
    join its trainings."""
    from bench import distributed
    if not distributed.launched():
        run_experiment(cfg)
        return
    distributed.init(resolve_device(cfg.device))
    if distributed.rank_and_size()[0] > 0:
        from bench.experiments.training import serve_trainings
        serve_trainings()
        return
    run_experiment(cfg)
    distributed.share(None)  # no more trainings: the other ranks' loops end


def mirror_runs(tracking: str, runs_dir: Path, uri: str | None, results_dir: Path) -> None:
    """Mirror the run store into MLflow (bench.tracking); a tracking failure never fails the command."""
    if tracking == "none":
        return
    try:
        from bench import tracking as mlflow_view
        counts = mlflow_view.sync(runs_dir, uri, results_dir)
        log.info("tracking: %d runs logged to MLflow, %d replaced, %d with new tables, %d unchanged (%s)",
                 counts["logged"], counts["replaced"], counts["tables"], counts["unchanged"],
                 uri or mlflow_view.default_uri(runs_dir))
    except Exception as err:  # noqa: BLE001 - the run store holds the results; MLflow is only their view
        log.warning("tracking: mirroring runs to MLflow failed (%s: %s); the run store is unaffected",
                    type(err).__name__, err)


def entry() -> None:
    """`python -m bench`: an unknown experiment or study is one line, then Hydra parses the rest."""
    args = sys.argv[1:]
    problem = working_dir_problem(args) or hydra_dir_problem(args) or choice_problem(args) or composition_problem(args)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        sys.exit(2)
    main()


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's preemption) outside a training step, handled as Ctrl-C is: render workers
    are stopped and records closed, instead of the process vanishing and leaving its workers running.
    A training step has its own handler (bench.train): it checkpoints first."""
    exit_code = 128 + signal.SIGTERM


def _terminate(signum, frame):
    raise Terminated()


@hydra.main(config_path=CONF_DIR, config_name="config", version_base=None)
def main(cfg: DictConfig) -> None:
    # torch's modules, imported once Hydra has parsed the command line: an unknown experiment or a bad
    # override is one line without them (0.5 s, not 2.4 s); render workers, which import this module, too
    from bench.exrio import ExrError
    from bench.infer import keep_freed_memory
    from bench.measure import fused_kernels_on_cuda
    if cfg.keep_freed_memory:
        keep_freed_memory()
    on_main_thread = threading.current_thread() is threading.main_thread()  # (a launcher may run jobs in threads)
    previous = signal.signal(signal.SIGTERM, _terminate) if on_main_thread else None
    try:
        with fused_kernels_on_cuda():
            run_or_serve(cfg)
    except (UserError, *PATH_ERRORS) as err:
        print(f"error: {error_line(err)}", file=sys.stderr)
        sys.exit(getattr(err, "exit_code", 2))
    except KeyboardInterrupt as err:  # outside a training step (rendering, evaluating): nothing recorded is lost
        print("interrupted: runs recorded so far are kept; the same command again reuses them and resumes "
              "trainings from their checkpoints", file=sys.stderr)
        sys.exit(getattr(err, "exit_code", 130))
    except ExrError as err:  # a frame damaged after the last check (headers are checked at every start)
        fix = (f"`python -m bench +experiment=data preset={cfg.preset.name} data_dir={cfg.data_dir} "
               "experiment.verify=true` reads every frame and renders the damaged ones again" if cfg.render_data else
               f"the frames are yours to replace (render_data=false); `python -m bench +experiment=data "
               f"render_data=false data_dir={cfg.data_dir} experiment.verify=true` lists every damaged one")
        print(f"error: {err}; {fix}", file=sys.stderr)
        sys.exit(2)
    except (OSError, RuntimeError) as err:  # torch's own file writer says a full disk as a RuntimeError
        failed = Path(getattr(err, "filename", None) or cfg.runs_dir).resolve()
        setting = "data_dir" if failed.is_relative_to(Path(cfg.data_dir).resolve()) else "runs_dir"
        if not out_of_space(err, Path(cfg[setting])):
            raise
        print(f"error: no space left on the device under {setting}={cfg[setting]} ({err}); free some space, or "
              f"set {setting}=... to another disk, and run the same command again: recorded runs and rendered "
              "frames are kept and trainings resume from their last checkpoint", file=sys.stderr)
        sys.exit(1)
    finally:  # the caller's handler again, so a SIGTERM while the interpreter shuts down (joining
        # workers) is no Terminated traceback
        if on_main_thread:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)

"""The one trainer every learned model goes through.

A `Recipe` says how: Adam, a learning-rate schedule (linear warm-up then cosine decay by default; the
paper's "halve every quarter" as `schedule: halve`), gradient-norm clipping, an exponential moving
average (EMA) of the weights that validation and evaluation use, batches of T-frame sequences with aligned
random crops, and the loss weights on the final output and on the intermediate (SR-stage) head.

The trainer checkpoints atomically (weights, EMA, optimizer, step, curves) and resumes bit-exactly from
its last checkpoint. A non-finite loss or gradient stops the run with a clear message and leaves the last
good checkpoint in place. With a `validate` callable it scores the EMA weights before the first step,
every `val_every` steps and at the end, and records the learning curve (`val_curve.csv`: step, training seconds, mean training
loss since the previous point, and whatever `validate` returns, e.g. val relMSE/PSNR/SSIM).

Under torchrun (bench.distributed) each rank computes its share of every batch's slots and DDP averages
the gradients; rank 0 alone writes checkpoints and curves, and a stop requested on any rank stops all
of them at the same step.
"""
from __future__ import annotations

import contextlib
import copy
import logging
import math
import random
import signal
import threading
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import pandas as pd
import torch
from tqdm import tqdm

from bench import distributed
from bench.atomic import write_atomic
from bench.emitters import first_frame_exposure, with_emitter, with_fireflies
from bench.errors import UserError
from bench.exposure import DOMAINS, EXPOSURE_DOMAINS, encode, frame_exposure, pass_highlights
from bench.hdr import transforms
from bench.infer import frames_channels_last
from bench.losses import weighted_loss
from bench.macs import count_params
from bench.sanitize import sanitize_inputs, sanitize_radiance
from bench.tasks import Task

CHECKPOINT = "checkpoint.pt"
LOG_EVERY_S = 60.0   # without a terminal (logs, clusters) progress is a log line this often
READ_BACK_EVERY = 25  # steps whose losses stay on the device before one transfer reads them (bench.train.read_back)

log = logging.getLogger("bench")
SCHEDULES = ("cosine", "halve", "constant", "range")
PRECISIONS = ("fp32", "bf16")
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune")  # torch.compile's; reduce-overhead: CUDA graphs
# the exposure a lamp item is encoded at (train.emitters_exposure): "with" its lamp, as predict computes it
# on any frame; "without", that of the item as rendered. A lamp raises a training crop's exposure far more
# than a whole frame's (docs/studies.md, emitters_causes), so "with" encodes the rest of a lamp item darker
# than the frames the network meets at inference.
EMITTERS_EXPOSURES = ("with", "without")
EXPOSURE = "exposure"   # the batch key of the per-frame exposures that "without" hands to batch_loss


class TrainingInterrupted(UserError):
    """SIGINT or SIGTERM (Ctrl-C, a scheduler's preemption) stopped a training after a checkpoint."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum  # the shell's convention for a process ended by a signal


@contextlib.contextmanager
def _stop_requests():
    """A list that SIGINT and SIGTERM append to while the block runs, so the training loop can stop
    between steps with a checkpoint; a second signal stops at once (KeyboardInterrupt)."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():  # only the main thread may set handlers
        yield received
        return

    def request_stop(signum, frame):
        if received:
            raise KeyboardInterrupt(f"second {signal.Signals(signum).name}")
        received.append(signum)
    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class TrainingDiverged(RuntimeError):
    """Raised when the loss or a gradient becomes non-finite; `step` is where, and the run directory's
    curve.csv holds the loss of every step before it."""

    def __init__(self, message: str, step: int):
        super().__init__(message)
        self.step = step


@dataclass(frozen=True)
class Recipe:
    """How a model is trained: conf/config.yaml `train:` sets every field (presets override the sizes)
    and says what each one is; nothing here has a default, so the config is the one source of truth.

    Everything here but `checkpoint_every` and the validation settings determines the trained weights,
    so it is the training part of a run's identity (`identity()`)."""
    steps: int
    batch_size: int
    seq_len: int
    crop: int
    loss: dict                        # head -> {term: weight} (bench.losses)
    lr: float
    betas: tuple
    schedule: str                     # one of SCHEDULES
    warmup: float
    halve_every: float
    clip_grad_norm: float | None
    ema: float | None
    hdr: str                          # network domain, one of bench.exposure.DOMAINS
    colour_permute: bool
    emitters: float                   # share of training items given a lamp far above their exposure (bench.emitters)
    fireflies: float                  # share of training items given fireflies in their input only (bench.emitters)
    emitters_exposure: str            # one of EMITTERS_EXPOSURES: the exposure a lamp item is encoded at
    loss_knee: float | None           # None: the losses see the network domain as it is; else bench.losses.soft_knee
    precision: str                    # one of PRECISIONS
    channels_last: bool
    compile: str | None               # None: eager; else torch.compile's mode for forward, losses and backward
    checkpoint_every: int
    checkpoint_every_s: float
    val_every: int
    val_sequences: int

    NOT_IDENTITY = ("checkpoint_every", "checkpoint_every_s", "val_every", "val_sequences")
    # options left out of the identity at this value: the recipe as recorded before the option existed
    OMITTED_AT = {"compile": None, "emitters": 0.0, "fireflies": 0.0, "emitters_exposure": "with", "loss_knee": None}

    def __post_init__(self):
        if self.schedule not in SCHEDULES:
            raise ValueError(f"train.schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        if self.hdr not in DOMAINS:
            raise ValueError(f"train.hdr must be one of {DOMAINS}, got {self.hdr!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"train.precision must be one of {PRECISIONS}, got {self.precision!r}")
        for share in ("emitters", "fireflies"):
            if not 0.0 <= getattr(self, share) <= 1.0:
                raise ValueError(f"train.{share} is a share of the training items, in [0, 1], got {getattr(self, share)!r}")
        if self.emitters_exposure not in EMITTERS_EXPOSURES:
            raise ValueError(f"train.emitters_exposure must be one of {EMITTERS_EXPOSURES}, got {self.emitters_exposure!r}")
        if self.emitters_exposure == "without" and not (self.emitters and self.hdr in EXPOSURE_DOMAINS):
            raise ValueError("train.emitters_exposure=without sets the exposure of lamp items: it needs train.emitters "
                             f"> 0 and train.hdr one of {EXPOSURE_DOMAINS} (got {self.emitters}, {self.hdr!r})")
        if self.loss_knee is not None and not self.loss_knee > 0:
            raise ValueError(f"train.loss_knee must be null or a number > 0, got {self.loss_knee!r}")
        if self.compile not in (None, *COMPILE_MODES):
            raise ValueError(f"train.compile must be null or one of {COMPILE_MODES}, got {self.compile!r}")

    @classmethod
    def from_config(cls, config: dict) -> "Recipe":
        """The recipe of a `train:` config dict, which names every field: a missing or unknown key is an error."""
        known = {f.name for f in fields(cls)}
        unknown, missing = set(config) - known, known - set(config)
        if unknown:
            raise ValueError(f"unknown train.* keys {sorted(unknown)}; known: {sorted(known)}")
        if missing:
            raise ValueError(f"missing train.* keys {sorted(missing)} (conf/config.yaml sets every one)")
        return cls(**{**config, "betas": tuple(config["betas"])})

    def identity(self) -> dict:
        """Every option that determines the weights; a loss term of weight 0 is left out, as it adds nothing
        (a recipe that sets a term to 0 is the recipe without it)."""
        values = {k: v for k, v in asdict(self).items() if k not in self.NOT_IDENTITY
                  and not (k in self.OMITTED_AT and v == self.OMITTED_AT[k])}
        values["loss"] = without_zero_terms(values["loss"])
        return values


def without_zero_terms(loss: dict) -> dict:
    """The loss weights {head: {term: weight}} without the terms of weight 0."""
    return {head: {term: w for term, w in terms.items() if w != 0} for head, terms in loss.items()}


def lr_at(step: int, recipe: Recipe) -> float:
    """Learning rate of optimisation step `step` (0-based) of `recipe`."""
    lr, steps = recipe.lr, recipe.steps
    if recipe.schedule == "halve":
        if recipe.halve_every <= 0:
            return lr
        return lr * 0.5 ** math.floor(step / (recipe.halve_every * steps))
    if recipe.schedule == "constant":
        return lr
    if recipe.schedule == "range":
        return lr * 10 ** (4 * (step / max(1, steps - 1) - 1))
    warmup = round(recipe.warmup * steps)
    if step < warmup:
        return lr * (step + 1) / warmup
    progress = (step - warmup) / max(1, steps - warmup)
    return lr * 0.5 * (1 + math.cos(math.pi * progress))


def augmented(item: dict, task: Task, recipe: Recipe, seed: int, draw: int) -> dict:
    """The item with a lamp in `recipe.emitters` of the draws and fireflies in `recipe.fireflies` of them
    (bench.emitters), each decided apart, and with `train.emitters_exposure=without` the exposure of each
    of its frames as rendered under EXPOSURE; each slot of each step draws from its own RNGs, seeded by
    (seed, draw), so a resumed run and any split of the batch over ranks paste the same."""
    original, lamp, fireflies = item, random.Random(f"emitter {seed} {draw}"), random.Random(f"fireflies {seed} {draw}")
    if lamp.random() < recipe.emitters:
        item = with_emitter(item, task, lamp)
    if fireflies.random() < recipe.fireflies:   # at the levels of the item without its lamp, which would set them
        item = with_fireflies(item, task, fireflies, first_frame_exposure(original[task.x]))
    if recipe.emitters_exposure == "without":   # every item carries its exposure, so that a batch stacks
        item = {**item, EXPOSURE: frame_exposure(sanitize_radiance(original[task.x]), recipe.hdr)}
    return item


def collate(items: list[dict], keys: list[str]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([it[k] for it in items]) for k in keys}


def batch_loss(model, batch: dict, task: Task, loss_weights: dict, hdr: str, features=None, knee=None):
    """Total loss and its named parts for one batch of (B, T, C, H, W) buffers (`knee`: train.loss_knee)."""
    x, g = sanitize_inputs(batch[task.x], batch[task.g])
    # every image of a frame shares its LR input's exposure (or the one `augmented` recorded)
    exposure = batch[EXPOSURE] if EXPOSURE in batch else frame_exposure(x, hdr)
    x_net = encode(x, hdr, exposure)
    out = model(x_net, g)
    to_linear = transforms(hdr)[0]
    final = pass_highlights(out["final"], x, x_net, hdr, exposure)
    total, parts = weighted_loss(final, encode(batch[task.y], hdr, exposure), loss_weights["final"],
                                 features, to_linear, knee)
    parts = {f"final.{k}": v for k, v in parts.items()}
    if task.mid and out.get("intermediate") is not None and any(loss_weights["intermediate"].values()):
        mid, mid_parts = weighted_loss(out["intermediate"], encode(batch[task.mid], hdr, exposure),
                                       loss_weights["intermediate"], features, to_linear, knee)
        total = total + mid
        parts.update({f"intermediate.{k}": v for k, v in mid_parts.items()})
    return total, parts


@torch.no_grad()
def update_ema(ema_model, model, decay: float, step: int) -> None:
    """ema <- d * ema + (1 - d) * weights, with d = min(decay, (1 + step) / (10 + step)) so that the
    average is not dominated by the random initialisation early on (as TensorFlow's and timm's EMA)."""
    d = min(decay, (1 + step) / (10 + step))
    ema_params = [p for p in ema_model.parameters()]
    torch._foreach_lerp_(ema_params, [p.detach() for p in model.parameters()], 1 - d)
    for e, b in zip(ema_model.buffers(), model.buffers()):
        e.copy_(b)


def training_start(model, recipe: Recipe, device: str):
    """What a training starts from: `model` on `device` in training mode and the recipe's memory format,
    then its EMA copy (None without train.ema), in that layout too (the EMA's foreach update takes its
    fast path only over the same strides), and Adam over its parameters. The trainer and the speed
    table's training rows (bench.experiments.speed) both start here."""
    model.to(device).train()
    if recipe.channels_last:
        model.to(memory_format=torch.channels_last)
    ema_model = copy.deepcopy(model).eval().requires_grad_(False) if recipe.ema else None
    optimizer = torch.optim.Adam(model.parameters(), lr=recipe.lr, betas=tuple(recipe.betas))
    return ema_model, optimizer


def compiled_as(recipe: Recipe, loss_fn):
    """`loss_fn`, or where recipe.compile names a mode its torch.compile'd form: forward over the frames and
    the losses as one traced graph, backward as its compiled gradient (Adam and the EMA stay eager: a few
    foreach kernels). Dynamo's caches are per function: a process that compiles `loss_fn` in more than 8
    settings resets them between settings (bench.experiments.speed does)."""
    return loss_fn if recipe.compile is None else torch.compile(loss_fn, mode=recipe.compile)


def step_loss(loss_fn, net, batch: dict, task: Task | None, recipe: Recipe, features=None):
    """One step's loss and its parts, `loss_fn` (`batch_loss`, through `compiled_as`) under bf16 autocast
    where the recipe trains in bf16."""
    if recipe.compile is not None:  # CUDA graphs: this step may reuse the previous step's buffers
        torch.compiler.cudagraph_mark_step_begin()
    device_type = next(iter(batch.values())).device.type
    with torch.autocast(device_type, dtype=torch.bfloat16, enabled=recipe.precision == "bf16"):
        return loss_fn(net, batch, task, recipe.loss, recipe.hdr, features, recipe.loss_knee)


def update_weights(model, optimizer, ema_model, loss: torch.Tensor, recipe: Recipe, step: int) -> torch.Tensor:
    """From step `step`'s loss to the next weights: backward, the gradients clipped to
    recipe.clip_grad_norm, Adam at the step's learning rate, the EMA. Returns the gradient norm before
    the clip. The trainer and the speed table's training rows (bench.experiments.speed) both call this."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = torch.nn.utils.get_total_norm([p.grad for p in model.parameters() if p.grad is not None])
    if recipe.clip_grad_norm:
        torch.nn.utils.clip_grads_with_norm_(model.parameters(), recipe.clip_grad_norm, grad_norm)
    for group in optimizer.param_groups:
        group["lr"] = lr_at(step, recipe)
    optimizer.step()
    if ema_model is not None:
        update_ema(ema_model, model, recipe.ema, step)
    return grad_norm


@dataclass
class _State:
    step: int = 0
    curve: list = field(default_factory=list)       # per step: loss, lr, grad norm, loss parts
    val_curve: list = field(default_factory=list)   # per validation: step, train_s, loss, metrics
    train_s: float = 0.0                             # optimisation wall time so far (validation excluded)


def save_checkpoint(path: Path, model, ema_model, optimizer, state: _State) -> None:
    saved = {"model": model.state_dict(), "ema": ema_model.state_dict() if ema_model is not None else None,
             "optimizer": optimizer.state_dict(), "step": state.step, "curve": state.curve,
             "val_curve": state.val_curve, "elapsed_s": state.train_s}
    write_atomic(path, lambda tmp: torch.save(saved, tmp))


def load_weights(model, out_dir: str | Path, device: str = "cpu"):
    """Load a run's trained weights into `model` (in place) and return it: the EMA weights when the run
    kept an average (they are what validation scored), else the raw ones."""
    state = torch.load(Path(out_dir) / CHECKPOINT, map_location=device, weights_only=False)
    model.load_state_dict(state.get("ema") or state["model"])
    return model


def _resume(path: Path, model, ema_model, optimizer, device) -> _State:
    if not path.exists():
        return _State()
    saved = torch.load(path, map_location=device, weights_only=False)
    model.load_state_dict(saved["model"])
    if ema_model is not None:
        ema_model.load_state_dict(saved.get("ema") or saved["model"])
    optimizer.load_state_dict(saved["optimizer"])
    return _State(saved["step"], saved["curve"], saved.get("val_curve", []), saved.get("elapsed_s", 0.0))


def _write_curves(out_dir: Path, state: _State) -> None:
    """curve.csv and val_curve.csv, each replaced whole: a reader never sees half of one."""
    write_atomic(out_dir / "curve.csv", lambda tmp: pd.DataFrame(state.curve).to_csv(tmp, index=False))
    if state.val_curve:
        write_atomic(out_dir / "val_curve.csv", lambda tmp: pd.DataFrame(state.val_curve).to_csv(tmp, index=False))


def read_back(unread: list, names: list[str], state: _State, out_dir: Path | None, ckpt_path: Path) -> None:
    """Move the steps' reported losses (`unread`: (step, lr, tensor of the `names` values and the gradient
    norm)) to the host, in one transfer, onto `state.curve`, and empty `unread`. The first step whose loss
    or gradient norm is not finite raises TrainingDiverged naming it, after writing the curves of the steps
    before it to `out_dir` (None: another rank writes)."""
    values = torch.stack([v for _, _, v in unread]).cpu().tolist()
    taken = list(unread)
    unread.clear()
    for (step, lr, _), row in zip(taken, values):
        *losses, grad_norm = row
        if not (math.isfinite(losses[0]) and math.isfinite(grad_norm)):
            if out_dir is not None:
                _write_curves(out_dir, state)
            last = ckpt_path if ckpt_path.exists() else "none (diverged before the first)"
            what = f"loss ({losses[0]})" if not math.isfinite(losses[0]) else "gradient"
            raise TrainingDiverged(f"non-finite {what} at step {step - 1}; the last good checkpoint is {last}",
                                   step - 1)
        named = dict(zip(names, losses))
        state.curve.append({"step": step, "loss": named.pop("loss"), "lr": lr, "grad_norm": grad_norm, **named})


def _validation_point(state: _State, validate, model) -> dict:
    since = [c["loss"] for c in state.curve if c["step"] > (state.val_curve[-1]["step"] if state.val_curve else 0)]
    was_training = model.training
    model.eval()
    metrics = validate(model)
    model.train(was_training)
    return {"step": state.step, "train_s": state.train_s,
            "loss": sum(since) / len(since) if since else float("nan"), **metrics}


def train(model, dataset, task: Task, out_dir: str | Path, recipe: Recipe, *, features=None, seed: int = 0,
          device: str = "cpu", progress: bool = True,
          validate: Callable[[torch.nn.Module], dict] | None = None, distributed_ranks: bool = False) -> dict:
    """Train `model` on `dataset` with `recipe` and return a summary (the model keeps the weights that
    evaluation uses: the EMA when the recipe keeps one).

    `dataset.item(index, draw)` returns a dict of (T, C, H, W) tensors whose random crop/augmentation is
    fixed by `draw`; with the batch indices drawn from (seed, step), every step is reproducible.
    `validate(model) -> {metric: value}` scores a model in eval mode (the learning curve).
    `distributed_ranks`: train together with the other torchrun ranks (bench.distributed); only the
    pipeline's trainings do, so other callers (adopt's replays, the stability probes) train alone.

    Resumes from `out_dir/checkpoint.pt` when present. Writes `curve.csv` (per step) and, with
    `validate`, `val_curve.csv`.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path = out_dir / CHECKPOINT
    rank, ranks = distributed.rank_and_size() if distributed_ranks else (0, 1)
    if recipe.batch_size % ranks:
        raise UserError(f"train.batch_size={recipe.batch_size} is not divisible by the {ranks} processes")
    writes = rank == 0  # the one process that writes checkpoints and curves
    ema_model, optimizer = training_start(model, recipe, device)
    state = _resume(ckpt_path, model, ema_model, optimizer, device)
    resumed_from = state.step
    if ranks > 1 and distributed.mean_over_ranks(torch.tensor([float(state.step)])).item() != state.step:
        raise UserError(f"the {ranks} processes resumed {out_dir} from different steps (this one from {state.step}): "
                        "the run store must be on a filesystem every process sees")
    keys = task.buffers(with_mid=True) + ([EXPOSURE] if recipe.emitters_exposure == "without" else [])
    scored = ema_model if ema_model is not None else model
    val_every = recipe.val_every if validate is not None else 0
    if validate is not None and not state.val_curve:  # step 0: where training starts (input bilinear for
        state.val_curve.append(_validation_point(state, validate, scored))  # models with input_residual)
    # every rank resumed from the same checkpoint; unused parameters (a head without loss) get no gradient
    net = model if ranks == 1 else torch.nn.parallel.DistributedDataParallel(model, find_unused_parameters=True)
    loss_fn = compiled_as(recipe, batch_loss)
    bar = tqdm(total=recipe.steps, initial=state.step, desc=f"train {type(model).__name__}",
               disable=None if progress else True, dynamic_ncols=True, leave=False, mininterval=1.0)
    log_lines = progress and bar.disable  # no bar (not a terminal): a log line every LOG_EVERY_S
    if resumed_from:
        log.info("train %s: resuming from step %d of %d", type(model).__name__, resumed_from, recipe.steps)
    last_line = last_checkpoint = time.perf_counter()
    first_step, first_s = state.step, state.train_s
    data_s = 0.0  # of this process's steps: building and moving batches (the share the GPU may wait on)
    unread = []  # (step, lr, device tensor of the reported losses and the gradient norm) not yet read back
    with _stop_requests() as stop:  # Ctrl-C or preemption: finish the step, checkpoint, stop
        while state.step < recipe.steps:
            t0 = time.perf_counter()
            step = state.step
            # Each step draws its batch from an RNG seeded by (seed, step): a resumed run sees the same batches.
            rng = random.Random(seed * 1_000_003 + step)
            torch.manual_seed(seed * 1_000_003 + step)
            indices = [rng.randrange(len(dataset)) for _ in range(recipe.batch_size)]
            items = [dataset.item(indices[slot], step * recipe.batch_size + slot)
                     for slot in range(rank, recipe.batch_size, ranks)]  # this rank's slots of the batch
            if recipe.emitters or recipe.fireflies:
                items = [augmented(item, task, recipe, seed, step * recipe.batch_size + slot)
                         for item, slot in zip(items, range(rank, recipe.batch_size, ranks))]
            batch = {k: v.to(device, non_blocking=True) for k, v in collate(items, keys).items()}
            if recipe.channels_last:
                batch = {k: frames_channels_last(v) for k, v in batch.items()}
            data_s += time.perf_counter() - t0
            loss, parts = step_loss(loss_fn, net, batch, task, recipe, features)
            # copies: a CUDA graph's outputs are overwritten by its next replay, and these wait for read_back
            reported = {"loss": loss.detach().clone(), **{k: v.detach().clone() for k, v in parts.items()}}
            stopping = bool(stop)  # decided here, once per step: with several ranks, the same on all
            if ranks > 1:  # the global batch's loss (a mean of equal shares), and a stop asked on any rank
                means = distributed.mean_over_ranks(torch.stack([*reported.values(), loss.new_tensor(len(stop))]))
                reported, stopping = dict(zip(reported, means[:-1])), bool(means[-1] > 0)
            # the losses stay on the device until `read_back` (no host sync per step): a non-finite step is
            # found and named there, before any checkpoint or validation could take its weights
            grad_norm = update_weights(model, optimizer, ema_model, loss, recipe, step)
            state.step += 1
            state.train_s += time.perf_counter() - t0
            unread.append((state.step, optimizer.param_groups[0]["lr"],
                           torch.stack([v.float() for v in (*reported.values(), grad_norm)])))
            names = list(reported)
            bar.update(1)
            due_line = log_lines and time.perf_counter() - last_line >= LOG_EVERY_S
            validating = validate is not None and (state.step == recipe.steps
                                                   or (val_every and state.step % val_every == 0))
            checkpointing = writes and (state.step % recipe.checkpoint_every == 0 or state.step == recipe.steps
                                        or stopping or time.perf_counter() - last_checkpoint >= recipe.checkpoint_every_s)
            if (len(unread) >= READ_BACK_EVERY or due_line or validating or checkpointing or stopping
                    or state.step == recipe.steps):
                read_back(unread, names, state, out_dir if writes else None, ckpt_path)
                bar.set_postfix(loss=f"{state.curve[-1]['loss']:.4f}")
            if due_line:
                last_line = time.perf_counter()
                rate = (state.train_s - first_s) / (state.step - first_step)
                log.info("train %s: step %d/%d, %.2f s/step, loss %.4f, about %.0f min left",
                         type(model).__name__, state.step, recipe.steps, rate, state.curve[-1]["loss"],
                         rate * (recipe.steps - state.step) / 60)
            if validating:
                state.val_curve.append(_validation_point(state, validate, scored))
            if checkpointing:
                save_checkpoint(ckpt_path, model, ema_model, optimizer, state)
                last_checkpoint = time.perf_counter()
            if stopping and state.step < recipe.steps:
                bar.close()
                if writes:
                    _write_curves(out_dir, state)
                signum = stop[0] if stop else signal.SIGTERM  # (else another rank was stopped)
                raise TrainingInterrupted(f"{signal.Signals(signum).name} at step {state.step} of {recipe.steps}: "
                                          f"checkpoint saved in {ckpt_path}; run the same command again to resume",
                                          signum)
    bar.close()
    if ema_model is not None:
        model.load_state_dict(ema_model.state_dict())
    if writes:
        _write_curves(out_dir, state)
    tail = [c["loss"] for c in state.curve[-max(1, len(state.curve) // 10):]]
    summary = {"steps": state.step, "resumed_from_step": resumed_from, "final_loss": sum(tail) / len(tail),
               "first_loss": state.curve[0]["loss"] if state.curve else float("nan"),
               "train_time_s": state.train_s, "params": count_params(model)}
    if state.step > first_step:  # throughput of this process's steps (a resumed run: since it resumed)
        seconds = state.train_s - first_s
        summary["samples_per_s"] = (state.step - first_step) * recipe.batch_size / seconds
        summary["data_share"] = data_s / seconds
    if state.val_curve:
        summary["val"] = {k: v for k, v in state.val_curve[-1].items() if k not in ("step", "train_s", "loss")}
    return summary

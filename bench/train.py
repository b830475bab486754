"""The one trainer every learned model goes through (paper Sec. 4.2).

Adam (lr 6e-4, betas 0.9/0.99), the learning rate halved at fixed fractions of the schedule, batches of
T-frame sequences with aligned random crops, the paper's loss weights on the final output and on the
intermediate (SR-stage) head. Checkpoints atomically and resumes from the last checkpoint; a non-finite
loss or gradient stops the run with a clear message and leaves the last good checkpoint in place.
"""
from __future__ import annotations

import math
import random
import time
from pathlib import Path

import pandas as pd
import torch
from tqdm import tqdm

from bench.hdr import to_network
from bench.losses import weighted_loss
from bench.macs import count_params
from bench.sanitize import sanitize_inputs
from bench.tasks import Task

CHECKPOINT = "checkpoint.pt"


class TrainingDiverged(RuntimeError):
    """Raised when the loss or a gradient becomes non-finite."""


def lr_at(step: int, steps: int, lr: float, halve_every: float) -> float:
    """Learning rate at `step`: halved every `halve_every` fraction of the schedule (paper: 0.25)."""
    if halve_every <= 0:
        return lr
    return lr * 0.5 ** math.floor(step / (halve_every * steps))


def collate(items: list[dict], keys: list[str]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([it[k] for it in items]) for k in keys}


def batch_loss(model, batch: dict, task: Task, loss_weights: dict, hdr: str, features=None):
    """Total loss and its named parts for one batch of (B, T, C, H, W) buffers."""
    x, g = sanitize_inputs(batch[task.x], batch[task.g])
    out = model(to_network(x, hdr), g)
    total, parts = weighted_loss(out["final"], to_network(batch[task.y], hdr), loss_weights["final"], features)
    parts = {f"final.{k}": v for k, v in parts.items()}
    if task.mid and out.get("intermediate") is not None and any(loss_weights["intermediate"].values()):
        mid, mid_parts = weighted_loss(out["intermediate"], to_network(batch[task.mid], hdr),
                                       loss_weights["intermediate"], features)
        total = total + mid
        parts.update({f"intermediate.{k}": v for k, v in mid_parts.items()})
    return total, parts


def save_checkpoint(path: Path, model, optimizer, step: int, curve: list, elapsed: float) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                "curve": curve, "elapsed_s": elapsed}, tmp)
    tmp.replace(path)


def load_weights(model, out_dir: str | Path, device: str = "cpu"):
    """Load a run's trained weights into `model` (in place) and return it."""
    state = torch.load(Path(out_dir) / CHECKPOINT, map_location=device, weights_only=False)
    model.load_state_dict(state["model"])
    return model


def train(model, dataset, task: Task, out_dir: str | Path, *, steps: int, batch_size: int,
          loss_weights: dict, lr: float = 6e-4, betas=(0.9, 0.99), halve_every: float = 0.25,
          hdr: str = "clamp", features=None, seed: int = 0, device: str = "cpu",
          checkpoint_every: int = 100, progress: bool = True) -> dict:
    """Train `model` on `dataset` and return a summary.

    `dataset.item(index, draw)` returns a dict of (T, C, H, W) tensors whose random crop/augmentation is
    fixed by `draw`; with the batch indices drawn from (seed, step), every step is reproducible.

    Resumes from `out_dir/checkpoint.pt` when present. Writes `curve.csv` (loss per step).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path = out_dir / CHECKPOINT
    model.to(device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=lr, betas=tuple(betas))
    step, curve, elapsed0 = 0, [], 0.0
    if ckpt_path.exists():
        state = torch.load(ckpt_path, map_location=device, weights_only=False)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        step, curve, elapsed0 = state["step"], state["curve"], state.get("elapsed_s", 0.0)
    resumed_from = step
    keys = task.buffers(with_mid=True)
    # Each step draws its batch from an RNG seeded by (seed, step), so a resumed run sees the same batches.
    t0 = time.perf_counter()
    bar = tqdm(total=steps, initial=step, desc=f"train {type(model).__name__}", disable=None if progress else True,
               
               dynamic_ncols=True, leave=False, mininterval=1.0)
    while step < steps:
        rng = random.Random(seed * 1_000_003 + step)
        torch.manual_seed(seed * 1_000_003 + step)
        items = [dataset.item(rng.randrange(len(dataset)), step * batch_size + slot)
                 for slot in range(batch_size)]
        batch = {k: v.to(device) for k, v in collate(items, keys).items()}
        for group in optimizer.param_groups:
            group["lr"] = lr_at(step, steps, lr, halve_every)
        loss, parts = batch_loss(model, batch, task, loss_weights, hdr, features)
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"non-finite loss ({loss.item()}) at step {step}; the last good checkpoint "
                                   f"is {ckpt_path if ckpt_path.exists() else 'none (diverged before the first)'}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), float("inf"))
        if not torch.isfinite(grad_norm):
            raise TrainingDiverged(f"non-finite gradient at step {step}; the last good checkpoint is "
                                   f"{ckpt_path if ckpt_path.exists() else 'none'}")
        optimizer.step()
        step += 1
        curve.append({"step": step, "loss": loss.item(), "lr": optimizer.param_groups[0]["lr"],
                      **{k: v.item() for k, v in parts.items()}})
        bar.update(1)
        bar.set_postfix(loss=f"{loss.item():.4f}")
        if step % checkpoint_every == 0 or step == steps:
            save_checkpoint(ckpt_path, model, optimizer, step, curve, elapsed0 + time.perf_counter() - t0)
    bar.close()
    pd.DataFrame(curve).to_csv(out_dir / "curve.csv", index=False)
    tail = [c["loss"] for c in curve[-max(1, len(curve) // 10):]]
    return {"steps": step, "resumed_from_step": resumed_from, "final_loss": sum(tail) / len(tail),
            "first_loss": curve[0]["loss"] if curve else float("nan"),
            "train_time_s": elapsed0 + time.perf_counter() - t0,
            "params": count_params(model)}

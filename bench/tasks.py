"""Which buffers feed a model and which supervise it, per task (see ARCHITECTURE.md, "Tasks").

Besides the three tasks of the paper's tables, the cascade rows train each stage on its own sub-task.
"""
from __future__ import annotations

from dataclasses import dataclass

# The data contract (ARCHITECTURE.md): every buffer a dataset can hold, and the gBuffer layers in order.
BUFFERS = ("lr_noisy", "lr_gbuf", "lr_ref", "hr_noisy", "hr_gbuf", "hr_ref")
GBUF_LAYERS = ("albedo", "normal", "roughness")


@dataclass(frozen=True)
class Task:
    name: str
    x: str                 # input radiance buffer
    g: str                 # gBuffer at the input's resolution
    y: str                 # target
    scale: int             # output size / input size
    mid: str | None = None  # target of the intermediate (SR-stage) head, if the task has one

    def buffers(self, with_mid: bool = True) -> list[str]:
        names = [self.x, self.g, self.y] + ([self.mid] if with_mid and self.mid else [])
        return list(dict.fromkeys(names))


TASKS = {t.name: t for t in (
    Task("srd", x="lr_noisy", g="lr_gbuf", y="hr_ref", scale=2, mid="hr_noisy"),
    Task("sr", x="lr_ref", g="lr_gbuf", y="hr_ref", scale=2),
    Task("denoise", x="hr_noisy", g="hr_gbuf", y="hr_ref", scale=1),
    # Cascade sub-tasks: SR of the noisy image (first stage of SR->dn), HR denoising with the LR gBuffer
    # (its second stage: only the LR gBuffer exists at run time) and LR denoising (first of dn->SR).
    Task("sr_noisy", x="lr_noisy", g="lr_gbuf", y="hr_noisy", scale=2),
    Task("denoise_hr", x="hr_noisy", g="lr_gbuf", y="hr_ref", scale=1),
    Task("denoise_lr", x="lr_noisy", g="lr_gbuf", y="lr_ref", scale=1),
)}

# Cascade (paper Table 3): per stage order, each stage of SRDNet.forward_stage and the task it is
# trained on alone, in the order the stages run.
CASCADE_STAGES = {"sr_dn": (("sr", "sr_noisy"), ("dn", "denoise_hr")),
                  "dn_sr": (("dn", "denoise_lr"), ("sr", "sr"))}


def get_task(name: str) -> Task:
    if name not in TASKS:
        raise KeyError(f"unknown task {name!r}; known tasks: {', '.join(TASKS)}")
    return TASKS[name]

"""Several processes training one model with PyTorch's DDP, launched by torchrun.

`python -m torch.distributed.run --nproc_per_node N -m bench ...` starts N copies of the command. Rank 0
runs the experiment as one process would and is the only one that renders, writes the run store and
writes tables; every other rank only trains: rank 0 hands it each training it starts (`share`), and in
`bench.train.train` the global batch is split over the ranks and DDP averages the gradients, so N
processes follow the one-process run to float tolerance. Without torchrun nothing here is used.
"""
from __future__ import annotations

import datetime
import os

import torch
import torch.distributed as dist

# Workers wait for the next training while rank 0 renders, evaluates and writes tables.
WAIT_FOR_RANK0 = datetime.timedelta(hours=12)


def launched() -> bool:
    """True in a process torchrun started as one of several."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init(device: str) -> None:
    """Join torchrun's process group: gloo on CPU, NCCL on CUDA (each rank on the GPU of its LOCAL_RANK)."""
    if dist.is_initialized():
        return
    if device == "cuda":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    dist.init_process_group("nccl" if device == "cuda" else "gloo", timeout=WAIT_FOR_RANK0)


def rank_and_size() -> tuple[int, int]:
    """(this process's rank, number of processes); (0, 1) outside a process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def share(obj=None):
    """Rank 0's `obj` on every rank (what the other ranks pass is ignored)."""
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def mean_over_ranks(values: torch.Tensor) -> torch.Tensor:
    """The element-wise mean of `values` over all ranks (a new tensor; `values` itself unchanged)."""
    total = values.detach().clone()
    dist.all_reduce(total)
    return total / dist.get_world_size()

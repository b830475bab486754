"""Training frames held in GPU memory, so that building a batch never waits on the host (#62).

A training step reads `batch_size` items of `seq_len` frames, each frame several buffers. SequenceDataset
decodes them from their EXRs into a host cache of 2 GiB (for the srd task the cpu training split takes
0.3 GB, the gpu one 2.3 GB: the frames beyond the cache are decoded again at every use), the host crops
and stacks them, and the trainer copies each batch to the device from pageable memory, which the host
waits for. With the step captured as CUDA graphs that host work would be most of the step.
DeviceFrames decodes the split once into GPU memory instead: a batch's crops, flips, quarter turns and
stacking are then device ops, queued behind the previous step as the step itself is, and the host never
waits for data.

Its items are the bits SequenceDataset's are: the random draws are the same (the host RNG), and cropping,
flipping, turning, stacking, negating a normal and reordering channels copy values without computing
any. So a training's identity and code fingerprint do not name where its frames were held, as they do
not name the thread count (tests/test_dataset.py on the CPU, tests/test_cuda.py on a GPU).
"""
from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor

import torch

from bench.dataset import SequenceDataset

log = logging.getLogger("bench")

FREE_SHARE = 0.5   # of the device's free memory the frames may take: the rest is the trainings' (jobs=N shares it)
DECODE_THREADS = 8  # the decode runs outside the GIL: 2 threads took 1.8x less time than 1 on 2 cores


class DeviceFrames(SequenceDataset):
    """SequenceDataset with every frame of its split decoded once, when built, into memory on `device`."""

    def __init__(self, root, split, buffers, *, device, **options):
        super().__init__(root, split, buffers, cache_bytes=0, **options)
        self.device = torch.device(device)
        records = [rec for frames in self.sequences.values() for rec in frames]
        decode = super()._decode_frame
        t0 = time.perf_counter()
        self._frames = {}
        with ThreadPoolExecutor(DECODE_THREADS) as pool:
            for rec, frame in zip(records, pool.map(decode, records)):
                self._frames[rec["sequence"], rec["frame"]] = {k: v.to(self.device) for k, v in frame.items()}
        log.info("training frames on %s: %d frames of the %s split, %.2f GB, decoded in %.1f s", self.device,
                 len(records), split, self.nbytes() / 1e9, time.perf_counter() - t0)

    def _read_frame(self, rec):
        return self._frames[rec["sequence"], rec["frame"]]

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for frame in self._frames.values() for t in frame.values())


def split_bytes(dataset: SequenceDataset) -> int:
    """The bytes the decoded frames of `dataset`'s split take, from each frame's recorded LR size (which
    every training frame has: bench.experiments.datasets.check_training_frames)."""
    channels = {"noisy": 3, "ref": 3, "gbuf": dataset.gbuffer_channels}
    total = 0
    for frames in dataset.sequences.values():
        for rec in frames:
            width, height = rec["lr_size"]
            for buffer in dataset.buffers:
                resolution, kind = buffer.split("_")
                scale = 1 if resolution == "lr" else dataset.scale
                total += 4 * channels[kind] * width * height * scale * scale  # float32
    return total


def training_frames(root, split, buffers, *, device, **options) -> SequenceDataset:
    """The training set of `split`: held on `device` where that is a GPU whose free memory holds it
    `FREE_SHARE` times over, else read on the host through SequenceDataset's cache."""
    host = SequenceDataset(root, split, buffers, **options)
    device = torch.device(device)
    if device.type != "cuda":
        return host
    need = split_bytes(host)
    free = torch.cuda.mem_get_info(device)[0]
    if need > FREE_SHARE * free:
        log.warning("training frames stay on the host: the %s split takes %.1f GB, more than %.0f%% of the %.1f GB "
                    "free on %s", split, need / 1e9, 100 * FREE_SHARE, free / 1e9, device)
        return host
    return DeviceFrames(root, split, buffers, device=device, **options)

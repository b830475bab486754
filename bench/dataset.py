"""PyTorch dataset over a rendered dataset directory (see bench.datagen), plus the HDR transforms.

Items are dicts of float32 tensors (T, C, H, W) keyed by buffer (lr_noisy, lr_gbuf, lr_ref, hr_noisy,
hr_gbuf, hr_ref; only the requested ones are read) and 'meta' (scene, sequence, frames).

Cropping: an LR crop of c x c at (y, x) pairs with the HR crop of 2c x 2c at (2y, 2x), so both cover the
same scene area (LR pixel i spans HR pixels 2i and 2i+1).

Augmentation (training): the same random horizontal flip, vertical flip and rotation by k*90 degrees is
applied to every buffer of an item. Normals are stored in camera space (x = image right, y = image up,
z = towards the viewer; bench.render), so the image transform acts on them as a 2D transform of (x, y):
a horizontal flip negates x, a vertical flip negates y, and a counter-clockwise quarter turn
(torch.rot90 on (H, W)) maps (x, y) -> (-y, x). z never changes.

Colour permutation (training, `permute_colours`): one random order of the RGB channels per item, applied
to every radiance buffer and to the albedo alike. An RGB renderer transports each channel on its own, so
the result is the render of the same scene with its lights' and materials' channels permuted (its mean
exactly; its noise up to the path sampler's colour-dependent choices): the model sees light colours the
scenes never had, and cannot learn a colour prior from a few sequences of a scene family. Only the
dark_bias study trains with it (conf/study/dark_bias.yaml, `train.colour_permute`).

gBuffer channels: albedo RGB, normal XYZ, roughness (7); ``gbuffer_channels`` keeps a prefix. A scene
whose roughness pass was left out (all-diffuse: bench.scenes.scene_features) gets the constant 1.

The HDR transforms into the network domain (``to_network``/``from_network``, modes clamp, log1p, pu)
live in bench.hdr and are re-exported here, as the data contract names this module.
"""
import json
import os

import numpy as np
import torch
from torch.utils.data import Dataset

from bench import exrio
from bench.hdr import MODES, from_network, to_network
from bench.tasks import BUFFERS, GBUF_LAYERS

__all__ = ["SequenceDataset", "augment_sequence", "permute_colours", "to_network", "from_network", "MODES", "BUFFERS"]

GBUF_SIZES = {"albedo": 3, "normal": 3, "roughness": 1}
DEFAULT_ROUGHNESS = 1.0  # value of a left-out roughness pass (every BSDF diffuse)
CACHE_BYTES = 2 << 30    # decoded frames a dataset object keeps in memory (the whole cpu training split: ~0.3 GB)


def _layer_of(buffer):
    """(resolution 'lr'/'hr', EXR layer kind 'noisy'/'ref'/'gbuf') of a buffer key."""
    res, kind = buffer.split("_")
    return res, kind


def augment_sequence(item, hflip, vflip, rot90):
    """Apply the same flips and ``rot90`` counter-clockwise quarter turns to every (T, C, H, W) buffer.

    Normals (channels 3:6 of *_gbuf, camera space) are transformed with the image (see module doc).
    """
    out = {}
    for key, x in item.items():
        if not torch.is_tensor(x):
            out[key] = x
            continue
        is_gbuf = key.endswith("_gbuf") and x.shape[1] >= 6
        if hflip:
            x = x.flip(-1)
            if is_gbuf:
                x = x.clone()
                x[:, 3] = -x[:, 3]
        if vflip:
            x = x.flip(-2)
            if is_gbuf:
                x = x.clone()
                x[:, 4] = -x[:, 4]
        k = rot90 % 4
        if k:
            x = torch.rot90(x, k, dims=(-2, -1))
            if is_gbuf:
                x = x.clone()
                nx, ny = x[:, 3].clone(), x[:, 4].clone()
                for _ in range(k):  # (x, y) -> (-y, x) per quarter turn
                    nx, ny = -ny, nx
                x[:, 3], x[:, 4] = nx, ny
        out[key] = x.contiguous()
    return out


def permute_colours(item, order):
    """Reorder the RGB channels of every radiance buffer (noisy, ref) and of the albedo (channels 0:3
    of a gBuffer) of an item by `order` (a permutation of 0, 1, 2); normals and roughness stay."""
    order = torch.as_tensor(order)
    out = {}
    for key, x in item.items():
        if not torch.is_tensor(x):
            out[key] = x
        elif key.endswith("_gbuf"):
            out[key] = torch.cat([x[:, :3][:, order], x[:, 3:]], 1)
        else:
            out[key] = x[:, order]
    return out


class SequenceDataset(Dataset):
    """Sequences of frames of one split of a dataset directory.

    root: dataset directory with manifest.json. split: 'train' / 'val' / 'generalization' / ....
    buffers: keys to load. seq_len: frames per item (None: whole sequences; shorter: every window of
    seq_len consecutive frames is an item). crop: LR crop size (None: full frames). augment: random
    flips / quarter turns. permute_colours: with augment, also a random order of the RGB channels (module
    doc). Random crops and augmentations draw from a generator seeded by (seed, index, number of items
    drawn so far by this object), so a run is reproducible for a fixed access order.
    """

    def __init__(self, root, split, buffers, seq_len=None, crop=None, augment=False, seed=0,
                 gbuffer_channels=7, cache_bytes=CACHE_BYTES, permute_colours=False):
        self.root = os.fspath(root)
        with open(os.path.join(self.root, "manifest.json")) as f:
            manifest = json.load(f)
        unknown = set(buffers) - set(BUFFERS)
        if unknown:
            raise ValueError(f"unknown buffers {sorted(unknown)}; known: {BUFFERS}")
        self.buffers = list(buffers)
        self.scale = int(manifest.get("spec", {}).get("scale", 2))
        self.crop, self.augment, self.seed = crop, augment, seed
        self.permute_colours = permute_colours
        self.gbuffer_channels = int(gbuffer_channels)
        sequences = {}
        for rec in manifest["frames"]:
            if rec["split"] == split:
                sequences.setdefault(rec["sequence"], []).append(rec)
        if not sequences:
            splits = sorted({r["split"] for r in manifest["frames"]})
            raise ValueError(f"{self.root}: no frames in split {split!r} (has {splits})")
        self.sequences = {k: sorted(v, key=lambda r: r["frame"]) for k, v in sorted(sequences.items())}
        self.items = []
        for name, frames in self.sequences.items():
            n = len(frames) if seq_len is None else int(seq_len)
            if n > len(frames):
                raise ValueError(f"{self.root}: sequence {name} has {len(frames)} frames, seq_len={n}")
            self.items += [(name, start, n) for start in range(len(frames) - n + 1)]
        self._draws = 0
        # Decoded frames kept in memory (up to cache_bytes): a training step reads every one of its
        # frames again and again, and decoding the EXRs cost more than the model step at the cpu preset.
        self._cache, self._cache_left = {}, int(cache_bytes)

    def __len__(self):
        return len(self.items)

    def _frame_paths(self, rec):
        base = os.path.join(self.root, rec["split"], rec["sequence"], f"{rec['frame']:04d}")
        return {"lr": base + "_lr.exr", "hr": base + "_hr.exr"}

    def _read_frame(self, rec):
        """Every requested buffer of one frame as (C, H, W) tensors (from the cache when held)."""
        key = (rec["sequence"], rec["frame"])
        if key in self._cache:
            return self._cache[key]
        frame = self._decode_frame(rec)
        size = sum(t.numel() * t.element_size() for t in frame.values())
        if size <= self._cache_left:
            self._cache[key], self._cache_left = frame, self._cache_left - size
        return frame

    def _decode_frame(self, rec):
        """Every requested buffer of one frame as (C, H, W) tensors, read from its EXRs."""
        paths = self._frame_paths(rec)
        wanted = {"lr": set(), "hr": set()}
        for b in self.buffers:
            res, kind = _layer_of(b)
            wanted[res] |= set(GBUF_LAYERS) if kind == "gbuf" else {kind}
        images = {}
        for res, layers in wanted.items():
            if not layers:
                continue
            stored = set(exrio.exr_layers(paths[res]))
            missing = layers - stored
            if missing - {"roughness"} or ("roughness" in missing and "roughness" not in rec.get("left_out", {})):
                raise exrio.ExrError(f"{paths[res]}: missing layers {sorted(missing)} (has {sorted(stored)})")
            images[res] = exrio.read_exr(paths[res], sorted(layers & stored))
        out = {}
        for b in self.buffers:
            res, kind = _layer_of(b)
            if kind == "gbuf":
                planes = []
                for layer in GBUF_LAYERS:
                    if layer in images[res]:
                        planes.append(images[res][layer])
                    else:
                        h, w = next(iter(images[res].values())).shape[:2]
                        planes.append(np.full((h, w, GBUF_SIZES[layer]), DEFAULT_ROUGHNESS, np.float32))
                array = np.concatenate(planes, -1)[..., :self.gbuffer_channels]
            else:
                array = images[res][kind]
            out[b] = torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1)))
        return out

    def _crop_origin(self, rng, lr_h, lr_w):
        c = int(self.crop)
        if c > lr_h or c > lr_w:
            raise ValueError(f"{self.root}: crop {c} larger than the LR frame {lr_w}x{lr_h}")
        return int(rng.integers(0, lr_h - c + 1)), int(rng.integers(0, lr_w - c + 1))

    def __getitem__(self, index):
        item = self.item(index, self._draws)
        self._draws += 1
        return item

    def item(self, index, draw):
        """Item `index` with its crop and augmentation drawn from the RNG seeded by (seed, index, draw).

        The trainer passes `draw` explicitly (from its step), so a resumed run sees the same batches as an
        uninterrupted one; `dataset[index]` uses a per-object counter instead.
        """
        name, start, n = self.items[index]
        frames = self.sequences[name][start:start + n]
        per_frame = [self._read_frame(rec) for rec in frames]
        rng = np.random.default_rng([int(self.seed), int(index), int(draw)])
        windows = {b: (slice(None), slice(None)) for b in self.buffers}
        if self.crop is not None:  # crop each frame before stacking: only the crop is copied
            lr_w, lr_h = frames[0]["lr_size"]
            y, x = self._crop_origin(rng, lr_h, lr_w)
            c, s = int(self.crop), self.scale
            for b in self.buffers:  # HR origin = scale x LR origin: pixel areas coincide
                k = 1 if b.startswith("lr_") else s
                windows[b] = (slice(k * y, k * (y + c)), slice(k * x, k * (x + c)))
        item = {b: torch.stack([f[b][..., windows[b][0], windows[b][1]] for f in per_frame]) for b in self.buffers}
        if self.augment:
            hflip, vflip, rot = bool(rng.integers(2)), bool(rng.integers(2)), int(rng.integers(4))
            if self.crop is None and rot % 2:
                rot -= 1  # keep full frames in their shape (only square crops are turned by 90 degrees)
            item = augment_sequence(item, hflip, vflip, rot)
            if self.permute_colours:  # drawn after the flips, so items without it stay as they were
                item = permute_colours(item, rng.permutation(3))
        item = {k: v.contiguous() for k, v in item.items()}
        item["meta"] = {"scene": frames[0]["scene"], "sequence": name, "frames": [r["frame"] for r in frames]}
        return item

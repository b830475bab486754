"""bench.dataset: LR/HR crop alignment, augmentation that turns normals with the image, left-out passes,
HDR transforms. Uses synthetic datasets written with bench.exrio (no rendering)."""
import json

import numpy as np
import pytest
import torch

from bench.dataset import SequenceDataset, augment_sequence, permute_colours
from bench.exrio import ExrError, read_exr, write_exr

LR_H, LR_W, T = 10, 14, 3


def _coords(h, w):
    """Pixel-centre coordinates in [0, 1] (u right, v down) of an h x w image."""
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
    return u, v


def _height(u, v):
    """A smooth height field; its screen-space gradient defines the synthetic normals."""
    return 0.3 * u + 0.2 * v + 0.5 * u * v


def _normals(u, v, h, w):
    """Camera-space normals (x right, y up) of the height field z = _height, in pixel units."""
    dz_dx = (0.3 + 0.5 * v) / w            # d height / d(pixel to the right)
    dz_dy = -(0.2 + 0.5 * u) / h           # d height / d(pixel up) = - d / d(row)
    n = np.stack([-dz_dx, -dz_dy, np.ones_like(u)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _write_synthetic(root, with_roughness=True):
    """One sequence whose radiance is (u, v, frame) at each pixel centre, at LR and HR (2x)."""
    records = []
    for t in range(T):
        for res, (h, w) in (("lr", (LR_H, LR_W)), ("hr", (2 * LR_H, 2 * LR_W))):
            u, v = _coords(h, w)
            image = np.stack([u, v, np.full_like(u, t)], -1).astype(np.float32)
            layers = {"noisy": image, "ref": image * 2,
                      "albedo": np.stack([_height(u, v)] * 3, -1).astype(np.float32),
                      "normal": _normals(u, v, h, w).astype(np.float32)}
            if with_roughness:
                layers["roughness"] = np.full((h, w, 1), 0.25, np.float32)
            write_exr(root / "train" / "seq0" / f"{t:04d}_{res}.exr", layers,
                      suffixes={"normal": ("X", "Y", "Z"), "roughness": ("Y",)})
        records.append({"split": "train", "sequence": "seq0", "scene": "synthetic", "frame": t,
                        "lr_size": [LR_W, LR_H], "hr_size": [2 * LR_W, 2 * LR_H],
                        "left_out": {} if with_roughness else {"roughness": "all diffuse"}})
    (root / "manifest.json").write_text(json.dumps({"spec": {"scale": 2}, "frames": records}))


ALL = ["lr_noisy", "lr_gbuf", "lr_ref", "hr_noisy", "hr_gbuf", "hr_ref"]


def test_full_frames_shapes_and_channel_order(tmp_path):
    _write_synthetic(tmp_path)
    item = SequenceDataset(tmp_path, "train", ALL)[0]
    assert item["lr_noisy"].shape == (T, 3, LR_H, LR_W) and item["hr_ref"].shape == (T, 3, 2 * LR_H, 2 * LR_W)
    assert item["lr_gbuf"].shape == (T, 7, LR_H, LR_W) and item["lr_noisy"].dtype == torch.float32
    u, v = _coords(LR_H, LR_W)
    np.testing.assert_allclose(item["lr_gbuf"][1, 3:6].permute(1, 2, 0).numpy(), _normals(u, v, LR_H, LR_W),
                               atol=1e-6)
    assert torch.all(item["lr_gbuf"][:, 6] == 0.25)
    assert item["meta"]["frames"] == [0, 1, 2] and torch.all(item["lr_noisy"][2, 2] == 2)
    assert SequenceDataset(tmp_path, "train", ["lr_gbuf"], gbuffer_channels=6)[0]["lr_gbuf"].shape[1] == 6


@pytest.mark.parametrize("augment", [False, True])
def test_lr_and_hr_crops_cover_the_same_area(tmp_path, augment):
    _write_synthetic(tmp_path)
    ds = SequenceDataset(tmp_path, "train", ["lr_noisy", "hr_noisy", "hr_ref"], seq_len=2, crop=4,
                         augment=augment, seed=3)
    assert len(ds) == 2   # windows of 2 frames in a 3-frame sequence
    origins = set()
    for index in range(len(ds)):
        for _ in range(6):
            item = ds[index]
            lr, hr = item["lr_noisy"], item["hr_noisy"]
            assert lr.shape == (2, 3, 4, 4) and hr.shape == (2, 3, 8, 8)
            # The mean of each 2x2 HR block of pixel-centre coordinates is the LR pixel centre.
            pooled = torch.nn.functional.avg_pool2d(hr, 2)
            torch.testing.assert_close(pooled, lr, atol=1e-6, rtol=0)
            torch.testing.assert_close(item["hr_ref"], 2 * hr)
            origins.add((float(lr[0, 0].min()), float(lr[0, 1].min())))
    assert len(origins) > 3   # crops really move


def _gradient_normals(height):
    """Normals recomputed from a (H, W) height image by central differences (x right, y up)."""
    dz_dx = (height[1:-1, 2:] - height[1:-1, :-2]) / 2
    dz_dy = (height[:-2, 1:-1] - height[2:, 1:-1]) / 2   # "up" is the previous row
    n = np.stack([-dz_dx, -dz_dy, np.ones_like(dz_dx)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


@pytest.mark.parametrize("hflip, vflip, rot", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 2), (0, 0, 3), (1, 1, 1)])
def test_augmentation_turns_normals_with_the_image(tmp_path, hflip, vflip, rot):
    _write_synthetic(tmp_path)
    item = SequenceDataset(tmp_path, "train", ["hr_gbuf"], seq_len=1, crop=8)[0]
    out = augment_sequence(item, bool(hflip), bool(vflip), rot)["hr_gbuf"][0].numpy()
    # The augmented height image implies normals; they must equal the augmented normal channels.
    implied = _gradient_normals(out[0].astype(np.float64))
    stored = out[3:6].transpose(1, 2, 0)[1:-1, 1:-1]
    np.testing.assert_allclose(stored, implied, atol=2e-4)
    original = item["hr_gbuf"][0, 3:5].numpy().transpose(1, 2, 0)[1:-1, 1:-1]
    assert not np.allclose(stored[..., :2], original)   # every case really changes the normals


def test_colour_permutation_reorders_radiance_and_albedo_and_keeps_the_crop(tmp_path):
    _write_synthetic(tmp_path)
    # albedo channel c is (c + 1) / 10 everywhere, so a permuted albedo names the order
    for path in (tmp_path / "train" / "seq0").glob("*.exr"):
        layers = read_exr(path)
        layers["albedo"] = np.stack([np.full(layers["albedo"].shape[:2], (c + 1) / 10, np.float32)
                                     for c in range(3)], -1)
        write_exr(path, layers, suffixes={"normal": ("X", "Y", "Z"), "roughness": ("Y",)})
    kwargs = dict(seq_len=2, crop=4, augment=True, seed=5)
    plain = SequenceDataset(tmp_path, "train", ALL, **kwargs)
    permuted = SequenceDataset(tmp_path, "train", ALL, permute_colours=True, **kwargs)
    orders = set()
    for draw in range(12):
        a, b = plain.item(1, draw), permuted.item(1, draw)
        order = tuple(round(10 * float(b["lr_gbuf"][0, c, 0, 0])) - 1 for c in range(3))
        assert sorted(order) == [0, 1, 2]
        orders.add(order)
        for key in ("lr_noisy", "lr_ref", "hr_noisy", "hr_ref"):  # same crop and flips, channels reordered
            torch.testing.assert_close(b[key], a[key][:, list(order)], rtol=0, atol=0)
        for key in ("lr_gbuf", "hr_gbuf"):
            torch.testing.assert_close(b[key][:, :3], a[key][:, list(order)], rtol=0, atol=0)
            torch.testing.assert_close(b[key][:, 3:], a[key][:, 3:], rtol=0, atol=0)  # normals, roughness
    assert len(orders) > 2   # the order is drawn per item
    identity = permute_colours({"lr_noisy": a["lr_noisy"], "meta": a["meta"]}, [0, 1, 2])
    assert torch.equal(identity["lr_noisy"], a["lr_noisy"]) and identity["meta"] is a["meta"]


def test_left_out_roughness_is_the_constant_one(tmp_path):
    _write_synthetic(tmp_path, with_roughness=False)
    item = SequenceDataset(tmp_path, "train", ["lr_gbuf", "hr_gbuf"])[0]
    assert torch.all(item["lr_gbuf"][:, 6] == 1.0) and torch.all(item["hr_gbuf"][:, 6] == 1.0)


def test_missing_layer_that_was_not_left_out_is_an_error(tmp_path):
    _write_synthetic(tmp_path, with_roughness=False)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    for rec in manifest["frames"]:
        rec["left_out"] = {}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ExrError, match=r"0000_lr\.exr: missing layers \['roughness'\]"):
        SequenceDataset(tmp_path, "train", ["lr_gbuf"])[0]
    with pytest.raises(ValueError, match="no frames in split 'val'"):
        SequenceDataset(tmp_path, "val", ["lr_gbuf"])



def test_decoded_frames_are_cached_and_items_do_not_alias_the_cache(tmp_path):
    _write_synthetic(tmp_path)
    data = SequenceDataset(tmp_path, "train", ALL, seq_len=2, crop=4, augment=True, seed=3)
    first = data.item(0, 5)
    assert len(data._cache) == 2                              # both frames of the item, decoded once
    for path in tmp_path.glob("train/seq0/*.exr"):             # the cache serves them from now on
        path.write_bytes(b"")
    again = data.item(0, 5)
    expected = {key: first[key].clone() for key in ALL}      # a view of the cache would move with it
    for key in ALL:
        assert torch.equal(first[key], again[key])
        again[key].add_(1.0)                                  # an item is its own copy ...
    third = data.item(0, 5)
    for key in ALL:                                           # ... the cache is untouched
        assert torch.equal(third[key], expected[key])
    uncached = SequenceDataset(tmp_path, "train", ALL, seq_len=2, crop=4, cache_bytes=0)
    with pytest.raises(ExrError, match=r"000[01]_(lr|hr)\.exr: unreadable or corrupt EXR"):
        uncached.item(0, 5)                                   # without the cache the broken files are read


@pytest.mark.parametrize("with_roughness", [True, False])
def test_frames_held_on_a_device_give_the_host_items_bit_for_bit(tmp_path, with_roughness):
    """DeviceFrames (bench.device_frames) decodes the split once, when built, and serves every item of
    every draw as SequenceDataset does (crops, flips, turns, colour orders); tests/test_cuda.py checks the
    same on a GPU. Its items are copies, and the store is what split_bytes plans for."""
    from bench.device_frames import DeviceFrames, split_bytes, training_frames
    _write_synthetic(tmp_path, with_roughness)
    options = dict(seq_len=2, crop=4, augment=True, seed=3, permute_colours=True)
    host = SequenceDataset(tmp_path, "train", ALL, **options)
    held = DeviceFrames(tmp_path, "train", ALL, device="cpu", **options)
    assert held.nbytes() == split_bytes(host) == T * (LR_H * LR_W + 4 * LR_H * LR_W) * (3 + 7 + 3) * 4
    wanted = {(index, draw): host.item(index, draw) for index in range(len(host)) for draw in range(8)}
    for path in tmp_path.glob("train/seq0/*.exr"):  # decoded when built: the files are not read again
        path.write_bytes(b"")
    for (index, draw), want in wanted.items():
        got = held.item(index, draw)
        assert got["meta"] == want["meta"]
        for key in ALL:
            assert got[key].dtype == want[key].dtype and torch.equal(got[key], want[key]), (index, draw, key)
    held.item(0, 0)["hr_ref"].add_(1.0)
    assert torch.equal(held.item(0, 0)["hr_ref"], wanted[0, 0]["hr_ref"])
    assert type(training_frames(tmp_path, "train", ALL, device="cpu", **options)) is SequenceDataset  # host: its cache

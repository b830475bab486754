"""bench.exrio: multi-layer EXR round trips, atomic writes, clear errors on broken files."""
import os

import numpy as np
import pytest

from bench.exrio import ExrError, exr_layers, is_valid_exr, read_exr, write_exr

SUFFIXES = {"noisy": ("R", "G", "B"), "normal": ("X", "Y", "Z"), "roughness": ("Y",)}


def _layers(rng, h=5, w=7):
    return {"noisy": (rng.random((h, w, 3)) * 1000).astype(np.float32),   # HDR values well above 1
            "albedo": rng.random((h, w, 3)).astype(np.float32),
            "normal": (rng.random((h, w, 3)) * 2 - 1).astype(np.float32),
            "roughness": rng.random((h, w, 1)).astype(np.float32)}


def test_float_round_trip_every_channel_exact(tmp_path):
    layers = _layers(np.random.default_rng(0))
    path = tmp_path / "f.exr"
    write_exr(path, layers, suffixes=SUFFIXES)
    back = read_exr(path)
    assert sorted(back) == sorted(layers)
    for name, image in layers.items():
        assert back[name].dtype == np.float32 and back[name].shape == image.shape
        np.testing.assert_array_equal(back[name], image)   # channel order included (EXR stores sorted)


def test_half_round_trip_matches_float16_rounding(tmp_path):
    layers = _layers(np.random.default_rng(1))
    path = tmp_path / "h.exr"
    write_exr(path, layers, suffixes=SUFFIXES, half=["albedo", "normal"])
    back = read_exr(path)
    for name in ("albedo", "normal"):
        np.testing.assert_array_equal(back[name], layers[name].astype(np.float16).astype(np.float32))
        assert not np.array_equal(back[name], layers[name])  # really stored as half
    np.testing.assert_array_equal(back["noisy"], layers["noisy"])
    write_exr(path, layers, half=True)
    assert np.abs(read_exr(path, ["noisy"])["noisy"] - layers["noisy"]).max() <= 0.5  # half: 11-bit mantissa


def test_channel_names_and_layer_subset(tmp_path):
    path = tmp_path / "c.exr"
    write_exr(path, _layers(np.random.default_rng(2)), suffixes=SUFFIXES)
    assert exr_layers(path) == ["albedo", "noisy", "normal", "roughness"]
    assert list(read_exr(path, ["normal"])) == ["normal"]
    with pytest.raises(ExrError, match="no layer 'ref'"):
        read_exr(path, ["ref"])


def test_corrupt_and_truncated_files_are_reported_by_name(tmp_path):
    path = tmp_path / "frame_0003_lr.exr"
    write_exr(path, _layers(np.random.default_rng(3), 32, 32))
    data = path.read_bytes()
    for size in (len(data) - 16, len(data) // 2, 40):
        path.write_bytes(data[:size])
        with pytest.raises(ExrError, match="frame_0003_lr.exr"):
            read_exr(path)
        assert not is_valid_exr(path)
    path.write_bytes(b"not an exr at all" * 10)
    with pytest.raises(ExrError, match="frame_0003_lr.exr"):
        read_exr(path)
    assert not is_valid_exr(tmp_path / "missing.exr")


def test_write_is_atomic_and_leaves_no_temp_files(tmp_path):
    path = tmp_path / "sub" / "a.exr"
    write_exr(path, {"noisy": np.ones((4, 4, 3), np.float32)})
    bad = {"noisy": np.ones((4, 4, 3), np.float32), "albedo": np.ones((5, 4, 3), np.float32)}
    with pytest.raises(ExrError, match="a.exr"):
        write_exr(path, bad)   # shape mismatch: the old file must survive untouched
    np.testing.assert_array_equal(read_exr(path)["noisy"], 1.0)
    assert os.listdir(tmp_path / "sub") == ["a.exr"]

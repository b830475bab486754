"""Faults and bad input with real files and real processes: damaged frames are found and repaired (or
named), nothing computed is lost. (Signals: tests/test_train.py; bad config values: tests/test_cli.py;
stale code and abandoned runs: tests/test_runs.py.)"""
import numpy as np
import pytest

from bench import datagen, exrio
from bench.errors import UserError
from bench.experiments.pipeline import ensure_data
from conftest import smoke_context

SPEC = {"name": "tiny", "seed": 1, "lr_width": 8, "lr_height": 6, "scale": 2, "spp": 1, "ref_spp": 4,
        "seq_len": 2, "max_depth": 4, "splits": {"train": {"families": ["living_room"], "sequences": 1}}}
PASSES = {"lr_noisy", "lr_gbuf", "hr_ref"}


def _ctx(root, render_data=True):
    return smoke_context(preset="tiny", runs_dir=root / "runs", results_dir=root / "results", data_dir=root / "data",
                         data_spec=SPEC, render_data=render_data, progress=False)


@pytest.fixture
def rendered(tmp_path):
    ensure_data(_ctx(tmp_path), PASSES)
    hr = tmp_path / "data" / "train" / datagen.load_manifest(tmp_path / "data")["frames"][0]["sequence"] / "0001_hr.exr"
    return tmp_path, hr, exrio.read_exr(hr)


def test_a_truncated_frame_is_rendered_again_to_the_same_pixels(rendered):
    root, hr, original = rendered
    hr.write_bytes(hr.read_bytes()[:100])                         # cut in its header
    assert [p for p, _ in datagen.damaged_frames(root / "data", datagen.load_manifest(root / "data")["frames"],
                                                 sorted(PASSES))] == [str(hr)]
    ensure_data(_ctx(root), PASSES)
    repaired = exrio.read_exr(hr)
    np.testing.assert_array_equal(repaired["ref"], original["ref"])   # seeds are derived: same pixels


def test_a_frame_cut_inside_its_pixels_is_found_by_decoding(rendered):
    root, hr, _ = rendered
    data = hr.read_bytes()
    hr.write_bytes(data[:int(len(data) * 0.9)])                   # the header survives
    frames = datagen.load_manifest(root / "data")["frames"]
    assert datagen.damaged_frames(root / "data", frames, sorted(PASSES)) == []
    assert [p for p, _ in datagen.damaged_frames(root / "data", frames, sorted(PASSES), decode=True)] == [str(hr)]


def test_the_data_experiment_with_verify_repairs_what_only_decoding_finds(rendered):
    from bench.experiments import data
    root, hr, original = rendered
    data_bytes = hr.read_bytes()
    hr.write_bytes(data_bytes[:int(len(data_bytes) * 0.9)])
    data.run(_ctx(root), passes=sorted(PASSES), examples=0, verify=True)
    np.testing.assert_array_equal(exrio.read_exr(hr)["ref"], original["ref"])


def test_your_own_damaged_frame_is_named_not_rendered(rendered):
    root, hr, _ = rendered
    hr.unlink()
    with pytest.raises(UserError, match=f"{hr}: missing.*yours to replace"):
        ensure_data(_ctx(root, render_data=False), PASSES)
    assert not hr.exists()


def test_a_frame_damaged_during_a_run_is_one_line_with_the_fix(rendered):
    import subprocess
    import sys
    from pathlib import Path
    root, hr, _ = rendered
    data = hr.read_bytes()
    hr.write_bytes(data[:int(len(data) * 0.9)])
    out = subprocess.run([sys.executable, "-m", "bench", "+experiment=smoke", "preset=smoke", "render_data=false",
                          f"data_dir={root / 'data'}", f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}",
                          "experiment.rows=[{label:b,model:bilinear}]", "eval.split=train", "progress=false"],
                         cwd=Path(__file__).parent.parent, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert str(hr) in out.stderr and "verify=true" in out.stderr

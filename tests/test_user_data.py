"""Your own renders (render_data=false): every malformed dataset gets a message naming the file and what it
must be, before anything runs; a minimal valid one (no spec, only the buffers evaluation reads) is scored."""
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bench.datagen import manifest_problems
from bench.exrio import write_exr
from conftest import bench_here

REPO = Path(__file__).resolve().parent.parent
LR = (8, 12)  # h, w


def write_dataset(root, frames=2, hr_scale=2, layers_lr=("noisy", "albedo", "normal", "roughness"),
                  layers_hr=("ref",), splits=("val",), lr=LR):
    """A user's dataset with one sequence per split: LR noisy + gBuffer, HR reference only, no spec."""
    rng = np.random.default_rng(0)
    records = []
    for split in splits:
        for t in range(frames):
            for res, layers, k in (("lr", layers_lr, 1), ("hr", layers_hr, hr_scale)):
                h, w = lr[0] * k, lr[1] * k
                data = {name: rng.random((h, w, 1 if name == "roughness" else 3), dtype=np.float32)
                        for name in layers}
                write_exr(root / split / "seq0" / f"{t:04d}_{res}.exr", data,
                          suffixes={"normal": ("X", "Y", "Z"), "roughness": ("Y",)})
            records.append({"split": split, "sequence": "seq0", "scene": "mine", "frame": t,
                            "lr_size": [lr[1], lr[0]]})
    (root / "manifest.json").write_text(json.dumps({"frames": records}))
    return records


def edit_manifest(root, change):
    manifest = json.loads((root / "manifest.json").read_text())
    change(manifest)
    (root / "manifest.json").write_text(json.dumps(manifest))


def test_a_minimal_dataset_has_no_problems(tmp_path):
    write_dataset(tmp_path)
    assert manifest_problems(tmp_path) == []


@pytest.mark.parametrize("damage, message", [
    (lambda root: os.remove(root / "manifest.json"), "has no manifest.json"),
    (lambda root: (root / "manifest.json").write_text("{frames: oops"), "manifest.json: not JSON"),
    (lambda root: edit_manifest(root, lambda m: m.update(frames=[])), '"frames": a non-empty list'),
    (lambda root: edit_manifest(root, lambda m: m["frames"][1].pop("scene")),
     "frames[1]: 'scene' is None; expected a scene name"),
    (lambda root: edit_manifest(root, lambda m: m["frames"][0].update(frame="0")),
     "frames[0]: 'frame' is '0'; expected the frame index, an integer >= 0"),
    (lambda root: edit_manifest(root, lambda m: m["frames"][0].update(left_out={"albedo": "none"})),
     "'left_out' is {'albedo': 'none'}; expected layers the frame has none of"),
    (lambda root: edit_manifest(root, lambda m: m["frames"][0].update(lr_size=[10, 10])),
     "0000_lr.exr: 12x8 pixels, but its record's lr_size is [10, 10]"),
    (lambda root: edit_manifest(root, lambda m: m.update(spec={"scale": "2"})), '"scale"'),
])
def test_each_malformed_manifest_is_named_with_its_fix(tmp_path, damage, message):
    write_dataset(tmp_path)
    damage(tmp_path)
    assert any(message in p for p in manifest_problems(tmp_path)), manifest_problems(tmp_path)


def test_an_hr_frame_of_the_wrong_size_says_hr_must_be_2x_lr(tmp_path):
    write_dataset(tmp_path, hr_scale=3)
    problems = manifest_problems(tmp_path)
    assert len(problems) == 2 and "0000_hr.exr is 36x24 pixels and 0000_lr.exr beside it 12x8: HR must be 2x LR" in problems[0]


def user_table(root, tmp_path):
    return bench_here("+experiment=smoke", "render_data=false", f"data_dir={root}", f"runs_dir={tmp_path / 'runs'}",
                 f"results_dir={tmp_path / 'results'}", "progress=false", "++experiment.figure=false",
                 "experiment.rows=[{label: Input bilinear, model: bilinear}]")


def test_the_cli_stops_on_a_bad_dataset_with_one_message_and_no_traceback(tmp_path):
    root = tmp_path / "mine"
    write_dataset(root, hr_scale=3)
    out = user_table(root, tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "is not a dataset in the documented layout" in out.stderr and "HR must be 2x LR" in out.stderr


def test_evaluation_needs_only_lr_noisy_the_lr_gbuffer_and_the_hr_reference(tmp_path):
    root = tmp_path / "mine"
    write_dataset(root)
    out = user_table(root, tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    table = pd.read_csv(tmp_path / "results" / "smoke" / "table.csv")
    assert list(table["method"]) == ["Input bilinear"] and np.isfinite(table["PSNR"]).all()


def test_training_on_frames_without_lr_size_names_the_key(tmp_path):
    """lr_size is optional for evaluation (whole frames) but training crops need it: one message, not a
    KeyError from inside the data loader."""
    from bench.errors import UserError
    from bench.experiments.datasets import dataset
    from bench.tasks import get_task
    from conftest import smoke_context
    write_dataset(tmp_path / "data", splits=("train",))
    edit_manifest(tmp_path / "data", lambda m: m["frames"][1].pop("lr_size"))
    ctx = smoke_context(data_dir=tmp_path / "data", render_data=False, runs_dir=tmp_path / "runs")
    with pytest.raises(UserError, match=r"training crops need each 'train' frame's \"lr_size\".*1 frames \(seq0/1\)"):
        dataset(ctx, "train", get_task("srd"), training=True)
    assert len(dataset(ctx, "train", get_task("srd"), training=False)) > 0   # evaluation reads whole frames


def test_verify_reads_every_pixel_of_your_own_data_lists_nan_and_writes_nothing(tmp_path):
    """`+experiment=data render_data=false verify=true` on the minimal layout (no buffers, no passes):
    each file's own layers are decoded; NaN is listed by file; your manifest and frames are not written."""
    from bench.errors import UserError
    from bench.experiments import data
    from bench.exrio import read_exr
    from conftest import smoke_context
    root = tmp_path / "data"
    write_dataset(root)
    ctx = smoke_context(data_dir=root, render_data=False, runs_dir=tmp_path / "runs",
                        results_dir=tmp_path / "results")
    before = {p: p.stat().st_mtime_ns for p in root.rglob("*")}
    data.run(ctx, passes=[], examples=0, verify=True)
    assert {p: p.stat().st_mtime_ns for p in root.rglob("*")} == before
    hr = root / "val" / "seq0" / "0001_hr.exr"
    layers = read_exr(hr)
    layers["ref"][0, 0, 0] = np.nan
    write_exr(hr, layers)
    with pytest.raises(UserError, match=f"{hr}: non-finite pixel values"):
        data.run(ctx, passes=[], examples=0, verify=True)

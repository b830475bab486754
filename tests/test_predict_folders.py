"""`srd-bench predict` on real folders (issue 44, item 4), with real files, its console script's function
called in this process (a process of its own for the umask): folders are sequences whose outputs mirror
the input tree, a recurrent state never runs from one sequence into the next, two frames never write
one file, mostly non-finite frames are refused and every repair is printed, outputs follow the umask,
and damaged or foreign weights and a bad --tile are one line."""
import contextlib
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from bench import exrio
from bench.weights import FORMAT
from conftest import srd_bench_here

REPO = Path(__file__).resolve().parent.parent
RAE = {"_target_": "baselines.rae.RAE", "width": 8}        # recurrent: its state crosses frames
LR = (16, 16)


def write_weights(path, cfg=RAE, sidecar=True, seed=0):
    """An exported weights file of `cfg` with random weights (an untrained head would make the output
    ignore the recurrent state), and its JSON with the sha256 unless `sidecar` is False."""
    from hydra.utils import instantiate
    torch.manual_seed(seed)
    model = instantiate(cfg, scale=2)
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.2)
    meta = {"format": FORMAT, "model": cfg, "task": "srd", "scale": 2, "hdr": "pu", "run": "test"}
    torch.save({**meta, "state_dict": model.state_dict()}, path)
    if sidecar:
        meta["sha256"] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        Path(f"{path}.json").write_text(json.dumps(meta))
    return Path(path)


def write_lr(path, seed=0, size=LR):
    """An LR input frame in the dataset layout (noisy, albedo, normal, roughness)."""
    g = np.random.default_rng(seed)
    h, w = size
    exrio.write_exr(path, {"noisy": g.random((h, w, 3), dtype=np.float32),
                           "albedo": g.random((h, w, 3), dtype=np.float32),
                           "normal": g.random((h, w, 3), dtype=np.float32) - 0.5,
                           "roughness": g.random((h, w, 1), dtype=np.float32)},
                    suffixes={"normal": ("X", "Y", "Z"), "roughness": ("Y",)})
    return Path(path)


def views(root, n=2, frames=2):
    """`root/view0k/000t_lr.exr`: n sequences whose files share their names."""
    for k in range(n):
        for t in range(frames):
            write_lr(root / f"view{k:02d}" / f"{t:04d}_lr.exr", seed=10 * k + t)
    return root


def srd_bench(*args, umask=None) -> subprocess.CompletedProcess:
    """`srd-bench ARGS` in this process (conftest.srd_bench_here); in a process of its own where `umask` is
    given (a new process's umask is what that test checks), which also runs the module as a program."""
    if umask is None:
        return srd_bench_here(*args)
    return subprocess.run([sys.executable, "-m", "bench.predict", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)),
                          preexec_fn=lambda: os.umask(umask))


def predict(*args, umask=None) -> subprocess.CompletedProcess:
    """`srd-bench predict` on the fp32 path (the reference path, nothing measured)."""
    return srd_bench("predict", "--fast-path", "fp32", *args, umask=umask)


def one_line_error(out, *fragments):
    assert out.returncode == 2, out.stderr[-2000:]
    assert "Traceback" not in out.stderr and out.stderr.count("\n") == 1, out.stderr
    for fragment in fragments:
        assert fragment in out.stderr, out.stderr


def output(path):
    return exrio.read_exr(path)["output"]


def test_folders_are_sequences_mirrored_under_the_output_dir_and_each_starts_afresh(tmp_path):
    weights, data = write_weights(tmp_path / "rae.pt"), views(tmp_path / "views")
    out = predict("--weights", weights, "--output-dir", tmp_path / "out", data)
    assert out.returncode == 0, out.stderr
    written = sorted(p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").rglob("*.exr"))
    assert written == ["view00/0000_hr.exr", "view00/0001_hr.exr", "view01/0000_hr.exr", "view01/0001_hr.exr"]
    alone = predict("--weights", weights, "--output-dir", tmp_path / "alone", data / "view01")
    assert alone.returncode == 0, alone.stderr
    for t in range(2):     # view01 after view00 = view01 alone: no state carried over
        np.testing.assert_array_equal(output(tmp_path / "out" / "view01" / f"{t:04d}_hr.exr"),
                                      output(tmp_path / "alone" / f"{t:04d}_hr.exr"))
    assert not np.array_equal(output(tmp_path / "alone" / "0001_hr.exr"), output(tmp_path / "out" / "view00" / "0001_hr.exr"))


def test_files_sharing_a_name_in_two_views_write_two_outputs_two_sequences(tmp_path):
    """The issue's case: view00/0000_lr.exr and view01/0000_lr.exr given as files."""
    weights, data = write_weights(tmp_path / "rae.pt"), views(tmp_path / "views", frames=1)
    out = predict("--weights", weights, "--output-dir", tmp_path / "out",
                  data / "view00" / "0000_lr.exr", data / "view01" / "0000_lr.exr")
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [str(tmp_path / "out" / v / "0000_hr.exr") for v in ("view00", "view01")]
    alone = predict("--weights", weights, "--output-dir", tmp_path / "alone", data / "view01" / "0000_lr.exr")
    assert alone.returncode == 0, alone.stderr
    np.testing.assert_array_equal(output(tmp_path / "out" / "view01" / "0000_hr.exr"),
                                  output(tmp_path / "alone" / "0000_hr.exr"))


def test_a_collision_is_one_line_before_anything_is_written(tmp_path):
    weights = write_weights(tmp_path / "rae.pt")
    for root in ("a", "b"):                       # a/seq and b/seq both map to out/seq
        write_lr(tmp_path / root / "seq" / "0000_lr.exr")
    out = predict("--weights", weights, "--output-dir", tmp_path / "out", tmp_path / "a", tmp_path / "b")
    one_line_error(out, "would both write", str(tmp_path / "out" / "seq" / "0000_hr.exr"))
    assert not (tmp_path / "out").exists()
    # an output over a file that is not one of predict's (a dataset's reference) is refused the same way
    exrio.write_exr(tmp_path / "a" / "seq" / "0000_hr.exr", {"ref": np.zeros((32, 32, 3), np.float32)})
    one_line_error(predict("--weights", weights, "--output-dir", tmp_path / "a", tmp_path / "a"),
                   "is not an output of predict")


def test_a_mostly_non_finite_frame_is_refused_unless_accepted_and_the_repair_is_printed(tmp_path):
    weights = write_weights(tmp_path / "rae.pt")
    frame = write_lr(tmp_path / "seq" / "0000_lr.exr")
    layers = exrio.read_exr(frame)
    layers["noisy"][:] = np.inf                    # the all-Inf noisy layer: 256 pixels
    exrio.write_exr(frame, layers, suffixes={"normal": ("X", "Y", "Z"), "roughness": ("Y",)})
    one_line_error(predict("--weights", weights, "--output-dir", tmp_path / "out", frame),
                   str(frame), "100.0% of its pixels are non-finite", "--accept-nonfinite")
    assert not (tmp_path / "out").exists()
    accepted = predict("--weights", weights, "--output-dir", tmp_path / "out", "--accept-nonfinite", frame)
    assert accepted.returncode == 0, accepted.stderr
    assert f"{frame}: repaired 768 non-finite input values (100.00% of its pixels)" in accepted.stderr


def test_a_few_non_finite_pixels_are_repaired_and_printed_not_only_recorded(tmp_path):
    weights = write_weights(tmp_path / "rae.pt")
    frame = write_lr(tmp_path / "seq" / "0000_lr.exr")
    layers = exrio.read_exr(frame)
    layers["noisy"][3, 4, 1] = np.nan
    exrio.write_exr(frame, layers, suffixes={"normal": ("X", "Y", "Z"), "roughness": ("Y",)})
    out = predict("--weights", weights, "--output-dir", tmp_path / "out", frame)
    assert out.returncode == 0, out.stderr
    assert f"{frame}: repaired 1 non-finite input values (0.39% of its pixels)" in out.stderr
    assert np.isfinite(output(tmp_path / "out" / "0000_hr.exr")).all()


def test_outputs_get_the_mode_of_the_umask(tmp_path):
    weights, frame = write_weights(tmp_path / "rae.pt"), write_lr(tmp_path / "0000_lr.exr")
    out = predict("--weights", weights, "--output-dir", tmp_path / "out", frame, umask=0o002)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "out" / "0000_hr.exr").stat().st_mode & 0o777 == 0o664      # not exrio's private 0600


def damage(weights, case):
    """`weights` (no JSON beside it) made into the issue's bad weights; the arguments that go with them."""
    saved = torch.load(weights, weights_only=False)
    if case == "truncated weights without their JSON":
        weights.write_bytes(weights.read_bytes()[:weights.stat().st_size // 2])
    elif case == "weights of another model under its config":
        torch.save({**saved, "model": {"_target_": "baselines.edsr.EDSR", "channels": 8, "blocks": 2}}, weights)
    elif case == "a config that does not build":
        torch.save({**saved, "model": {"_target_": "baselines.edsr.EDSR", "channels": -4}}, weights)
    elif case == "a weights file without its model":
        torch.save({k: v for k, v in saved.items() if k != "model"}, weights)
    elif case == "an unknown fast path":
        return ["--fast-path", "fp64"]
    else:
        return [case]
    return []


@pytest.mark.parametrize("case, fragments", [
    ("truncated weights without their JSON", ["does not load (truncated or damaged", "export it again"]),
    ("weights of another model under its config", ["its weights are not those of its model baselines.edsr.EDSR"]),
    ("--tile=-5", ["argument --tile: '-5' is not a positive number of pixels"]),
])
def test_bad_weights_and_a_bad_tile_end_in_one_line(tmp_path, case, fragments):
    frame, weights = write_lr(tmp_path / "0000_lr.exr"), write_weights(tmp_path / "rae.pt", sidecar=False)
    extra = damage(weights, case)
    one_line_error(predict("--weights", weights, "--output-dir", tmp_path / "out", *extra, frame), *fragments)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("case, fragments", [
    ("a config that does not build", ["its model config (baselines.edsr.EDSR) does not build"]),
    ("a weights file without its model", ["an SRD-Bench weights file without its model", "export it again"]),
    ("--tile=abc", ["argument --tile: 'abc' is not a positive number of pixels"]),
    ("--tile=0", ["argument --tile: '0' is not a positive number of pixels"]),
    ("--max-nonfinite=2", ["argument --max-nonfinite: '2' is not a share between 0 and 1"]),
    ("an unknown fast path", ["--fast-path: unknown fast path switch 'fp64'"]),
])
def test_more_bad_weights_and_arguments_end_in_one_line(tmp_path, capsys, case, fragments):
    """The same in this process (the command line is the same function)."""
    from bench.predict import main
    frame, weights = write_lr(tmp_path / "0000_lr.exr"), write_weights(tmp_path / "rae.pt", sidecar=False)
    extra = damage(weights, case)
    with pytest.raises(SystemExit) if case.startswith("--") else contextlib.nullcontext() as stopped:
        code = main(["predict", "--weights", str(weights), "--output-dir", str(tmp_path / "out"), *extra, str(frame)])
    code = stopped.value.code if stopped else code
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and all(f in err for f in fragments), err
    assert not (tmp_path / "out").exists()

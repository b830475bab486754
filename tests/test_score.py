"""`srd-bench score` (issue 44, item 5): a folder of outputs computed elsewhere, scored against a dataset's
references with the evaluator's own metrics and put beside a table's recorded rows. The must-show in
miniature: predict's outputs of a tiny dataset, scored, equal bench.evaluate on the same frames, and
`--against` the evaluation's record says so."""
import json
import os

import numpy as np
import OpenEXR
import pandas as pd
import pytest

from bench import exrio
from bench.evaluate import SCORES
from conftest import python_process
from test_predict_folders import REPO, srd_bench, write_lr, write_weights

SEQUENCES, FRAMES, LR = ("atrium-1-v0", "atrium-1-v1"), 3, (16, 16)
TABLE = REPO / "results" / "cpu" / "sota" / "table.csv"


def write_dataset(root):
    """A split `val` in the layout bench.dataset reads: two sequences of LR inputs and HR references."""
    rng, records = np.random.default_rng(1), []
    for k, sequence in enumerate(SEQUENCES):
        for t in range(FRAMES):
            write_lr(root / "val" / sequence / f"{t:04d}_lr.exr", seed=10 * k + t, size=LR)
            exrio.write_exr(root / "val" / sequence / f"{t:04d}_hr.exr",
                            {"ref": rng.random((2 * LR[0], 2 * LR[1], 3), dtype=np.float32)})
            records.append({"split": "val", "sequence": sequence, "scene": "atrium-1", "frame": t,
                            "lr_size": [LR[1], LR[0]]})
    (root / "manifest.json").write_text(json.dumps({"frames": records}))
    return root


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    """predict --fast-path fp32 on data/val, the evaluator on the same frames (recorded as an evaluation
    run), then score of predict's outputs against that record, beside the sota table."""
    import torch
    from bench import runs
    from bench.dataset import SequenceDataset
    from bench.evaluate import evaluate
    from bench.weights import load_exported
    from bench.tasks import get_task
    root = tmp_path_factory.mktemp("score")
    data, weights = write_dataset(root / "data"), write_weights(root / "rae.pt")
    torch.set_num_threads(1)  # predict and the evaluator alike: the same summation order, so scores agree to 1e-6
    out = srd_bench("predict", "--weights", weights, "--fast-path", "fp32", "--output-dir", root / "out", data / "val")
    assert out.returncode == 0, out.stderr
    model, meta = load_exported(weights)
    task = get_task("srd")
    torch.manual_seed(0)
    per_image, metrics = evaluate(model, SequenceDataset(data, "val", task.buffers(with_mid=False)), task,
                                  hdr=meta["hdr"], out_dir=root / "eval")
    (root / "eval" / runs.RECORD).write_text(json.dumps({"kind": "eval", "status": "complete", "metrics": metrics}))
    result = srd_bench("score", "--outputs", root / "out", "--data", data, "--split", "val", "--label", "Mine",
                       "--table", TABLE, "--out-dir", root / "scores", "--against", root / "eval")
    return root, per_image, metrics, result


def test_predict_then_score_equals_the_evaluator_on_the_same_frames(scored):
    root, per_image, metrics, result = scored
    assert result.returncode == 0, result.stderr
    assert "matches" in result.stdout.splitlines()[-1], result.stdout
    mine = pd.read_csv(root / "scores" / "per_image.csv")
    assert list(mine[["sequence", "frame"]].itertuples(index=False)) == \
        list(per_image[["sequence", "frame"]].itertuples(index=False))
    for name in SCORES:
        np.testing.assert_allclose(mine[name], per_image[name], rtol=1e-6, err_msg=name)


def test_the_row_joins_the_recorded_rows_of_the_table(scored):
    root, _, metrics, result = scored
    recorded, table = pd.read_csv(TABLE), pd.read_csv(root / "scores" / "table.csv")
    assert list(table.columns) == list(recorded.columns)
    assert list(table["method"]) == [*recorded["method"], "Mine"]
    pd.testing.assert_frame_equal(table.iloc[:-1], recorded, check_dtype=False)
    for name in ("relMSE", "PSNR", "SSIM", "relMSE se"):
        assert table[name].iloc[-1] == pytest.approx(metrics[name], rel=1e-6)
    assert "| Mine |" in result.stdout and (root / "scores" / "table.md").exists()


def test_a_different_record_is_a_difference_and_exit_1(scored, tmp_path):
    root, *_ = scored
    record = json.loads((root / "eval" / "run.json").read_text())
    record["metrics"]["PSNR"] += 1e-3
    (tmp_path / "run.json").write_text(json.dumps(record))
    result = srd_bench("score", "--outputs", root / "out", "--data", root / "data", "--label", "Mine",
                       "--out-dir", tmp_path / "scores", "--against", tmp_path)
    assert result.returncode == 1 and "DIFFERS" in result.stdout, result.stdout + result.stderr


def test_outputs_of_another_framework_in_plain_rgb_channels_score_the_same(scored, tmp_path, capsys):
    from bench.predict import main
    root, *_ = scored
    for path in (root / "out").rglob("*_hr.exr"):      # R, G, B without a layer name, as most tools write
        image = exrio.read_exr(path)["output"]
        target = tmp_path / "foreign" / path.relative_to(root / "out")
        target.parent.mkdir(parents=True, exist_ok=True)
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                          {c: np.ascontiguousarray(image[..., i]) for i, c in enumerate("RGB")}) as f:
            f.write(str(target))
    assert main(["score", "--outputs", str(tmp_path / "foreign"), "--data", str(root / "data"), "--label", "Theirs",
                 "--out-dir", str(tmp_path / "scores")]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "scores" / "per_image.csv"),
                                  pd.read_csv(root / "scores" / "per_image.csv"))


@pytest.mark.parametrize("damage, message", [
    (lambda out: (out / SEQUENCES[1] / "0002_hr.exr").unlink(), "1 of the split's outputs are missing"),
    (lambda out: exrio.write_exr(out / SEQUENCES[0] / "0001_hr.exr", {"output": np.zeros((8, 8, 3), np.float32)}),
     "0001_hr.exr: 8x8x3, the reference is 32x32 RGB"),
    (lambda out: exrio.write_exr(out / SEQUENCES[0] / "0001_hr.exr", {"a": np.zeros((32, 32, 3), np.float32),
                                                                       "b": np.zeros((32, 32, 3), np.float32)}),
     "no layer `output` among its layers ['a', 'b']"),
    (lambda out: exrio.write_exr(out / SEQUENCES[0] / "0001_hr.exr", {"output": np.full((32, 32, 3), np.nan, np.float32)}),
     "1 of the outputs hold NaN or Inf values, e.g."),
    (lambda out: OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                              {f".{c}": np.zeros((32, 32), np.float32) for c in "RGB"}).write(
        str(out / SEQUENCES[0] / "0001_hr.exr")), "its channels are named like .R (a layer with an empty name)"),
])
def test_a_missing_or_foreign_output_is_one_line(scored, tmp_path, capsys, damage, message):
    import shutil
    from bench.predict import main
    root, *_ = scored
    shutil.copytree(root / "out", tmp_path / "out")
    damage(tmp_path / "out")
    assert main(["score", "--outputs", str(tmp_path / "out"), "--data", str(root / "data"), "--label", "x"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_score_imports_nothing_from_bench_experiments():
    code = "import sys, bench.score; sys.exit(any(m.startswith('bench.experiments') for m in sys.modules))"
    done = python_process("-c", code, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert done.returncode == 0, done.stderr[-2000:]


def test_nonfinite_outputs_score_only_when_accepted_and_a_table_without_scores_is_refused(scored, tmp_path, capsys):
    import shutil
    from bench.predict import main
    root, *_ = scored
    shutil.copytree(root / "out", tmp_path / "out")
    exrio.write_exr(tmp_path / "out" / SEQUENCES[0] / "0001_hr.exr", {"output": np.full((32, 32, 3), np.inf, np.float32)})
    args = ["score", "--outputs", str(tmp_path / "out"), "--data", str(root / "data"), "--label", "x"]
    assert main([*args, "--accept-nonfinite"]) == 0 and "scored as they are" in capsys.readouterr().err
    # a NaN output scores NaN, which a mean skips: the row says how many frames its means leave out
    exrio.write_exr(tmp_path / "out" / SEQUENCES[1] / "0000_hr.exr", {"output": np.full((32, 32, 3), np.nan, np.float32)})
    assert main([*args, "--accept-nonfinite"]) == 0
    per_image = pd.read_csv(tmp_path / "out" / "per_image.csv")
    said = f"1 of {len(per_image)} frames have NaN scores and are left out of the row's means ({SEQUENCES[1]} frame 0)"
    assert said in capsys.readouterr().err and said in (tmp_path / "out" / "table.md").read_text()
    pd.DataFrame([{"method": "A", "notes": "no scores"}]).to_csv(tmp_path / "t.csv", index=False)
    assert main([*args, "--accept-nonfinite", "--table", str(tmp_path / "t.csv")]) == 2
    assert "none of the score columns" in capsys.readouterr().err


def test_against_a_run_without_scores_is_one_line_not_a_match(scored, tmp_path, capsys):
    from bench.predict import main
    root, *_ = scored
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "run.json").write_text(json.dumps({"hash": "x", "status": "complete", "metrics": {}}))
    assert main(["score", "--outputs", str(root / "out"), "--data", str(root / "data"), "--label", "x",
                 "--out-dir", str(tmp_path / "o"), "--against", str(tmp_path / "run")]) == 2
    assert "holds none of the scores" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_scores_never_replace_a_committed_table(scored, capsys):
    """`--out-dir results/cpu/sota` (adding my row to the sota table) is refused: --table reads it."""
    from bench.predict import main
    root, *_ = scored
    table = REPO / "results" / "cpu" / "sota" / "table.csv"
    before = table.read_bytes()
    assert main(["score", "--outputs", str(root / "out"), "--data", str(root / "data"), "--label", "Mine",
                 "--table", str(table), "--out-dir", str(table.parent)]) == 2
    assert "under the committed results/" in capsys.readouterr().err and table.read_bytes() == before
    assert not (table.parent / "per_image.csv").exists()

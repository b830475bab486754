"""README's "Adding a model" holds: a toy model's module, its YAML and one defaults line (3 files, nothing
else) make it a row of a table and of the MAC audit, through the CLI."""
import filecmp
import os
import shutil
from pathlib import Path

import pandas as pd
import pytest

from conftest import python_process
from test_user_data import write_dataset

REPO = Path(__file__).resolve().parent.parent

TOY_MODULE = '''
import torch
import torch.nn.functional as F
from torch import nn


class ToyNet(nn.Module):
    """The smallest model that follows the contract: two convs on radiance + gBuffer, added to bilinear."""
    recurrent = False

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2, channels=8):
        super().__init__()
        self.scale = scale
        self.body = nn.Sequential(nn.Conv2d(in_channels + gbuffer_channels, channels, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(channels, 3 * scale * scale, 3, padding=1), nn.PixelShuffle(scale))

    def forward(self, x, g):
        b, t = x.shape[:2]
        x, g = x.flatten(0, 1), g.flatten(0, 1)
        up = F.interpolate(x, scale_factor=self.scale, mode="bilinear", align_corners=False)
        return {"final": (up + self.body(torch.cat([x, g], 1))).unflatten(0, (b, t))}
'''


def changed_files(before: Path, after: Path) -> list[str]:
    """Files added or changed in `after` relative to `before` (recursively)."""
    out = []
    def walk(cmp, prefix=""):
        out.extend(prefix + n for n in cmp.right_only + cmp.diff_files)
        for name, sub in cmp.subdirs.items():
            walk(sub, f"{prefix}{name}/")
    walk(filecmp.dircmp(before, after))
    return sorted(out)


def test_a_toy_model_takes_its_module_its_yaml_and_one_line(tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(REPO / "conf", conf)
    (tmp_path / "toy_model.py").write_text(TOY_MODULE)                                  # 1: the module
    (conf / "model" / "toy.yaml").write_text("_target_: toy_model.ToyNet\nchannels: 8\n")  # 2: its YAML
    config = (conf / "config.yaml").read_text()
    line = "  - model@models.bilinear: bilinear\n"
    (conf / "config.yaml").write_text(config.replace(line, line + "  - model@models.toy: toy\n"))  # 3: one line
    assert changed_files(REPO / "conf", conf) == ["config.yaml", "model/toy.yaml"]

    data = tmp_path / "data"
    write_dataset(data, frames=3, layers_hr=("noisy", "ref"), splits=("train", "val"), lr=(16, 16))
    env = dict(os.environ, PYTHONPATH=str(tmp_path), SRD_TRACKING="none", HYDRA_FULL_ERROR="0")
    common = [f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}", "progress=false"]
    run = lambda *args: python_process("-m", "bench", "--config-path", conf, *args, *common, env=env, timeout=300)

    table = run("+experiment=smoke", "experiment.rows=[{label: Toy, model: toy}]", "render_data=false",
                f"data_dir={data}", "train.steps=5", "++experiment.figure=false")
    assert table.returncode == 0, table.stderr[-3000:]
    assert "train Toy: trained" in table.stdout + table.stderr
    row = pd.read_csv(tmp_path / "results" / "smoke" / "table.csv").iloc[0]
    assert row["method"] == "Toy" and row["params"] == (10 * 8 * 9 + 8) + (8 * 12 * 9 + 12)

    audit = run("+experiment=macs", "+experiment.rows=[{label: Toy, model: toy}]")
    assert audit.returncode == 0, audit.stderr[-3000:]
    macs = pd.read_csv(tmp_path / "results" / "macs" / "table.csv").iloc[0]
    pixels = 540 * 960  # two 3x3 convs at LR: (3+7 -> 8) and (8 -> 3*2*2)
    assert macs["GMac (analytic)"] * 1e9 == pytest.approx((10 * 8 * 9 + 8 * 12 * 9) * pixels, rel=1e-9)

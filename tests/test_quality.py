"""The learned models must beat the input's bilinear upsampling at the smoke preset (`make run`'s defaults).

Slow (several minutes on 2 cores: the smoke data and 600 training steps per model); run with
`make test-slow`. The numbers it checks are the ones `make run` prints.
"""
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from bench.cli import CONF_DIR, run_experiment


@pytest.mark.slow
@pytest.mark.parametrize("model", ["srd", "edsr", "rae", "kpcn", "cfm"])
def test_learned_model_beats_input_bilinear_on_every_metric(tmp_path_factory, model):
    root = tmp_path_factory.getbasetemp() / "quality"  # one dataset for every model
    overrides = ["+experiment=smoke", f"runs_dir={root / 'runs'}", f"results_dir={root / 'results' / model}",
                 f"data_dir={root / 'data'}", "progress=false",
                 f"experiment.rows=[{{label:Input bilinear,model:bilinear}},{{label:{model},model:{model}}}]"]
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        run_experiment(compose("config", overrides=overrides))
    table = pd.read_csv(root / "results" / model / "smoke" / "table.csv").set_index("method")
    ours, bilinear = table.loc[model], table.loc["Input bilinear"]
    assert ours["relMSE"] < bilinear["relMSE"], table
    assert ours["PSNR"] > bilinear["PSNR"], table
    assert ours["SSIM"] > bilinear["SSIM"], table

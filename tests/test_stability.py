"""`+experiment=stability` at the smoke preset: every case gives finite output or a clear error, for the
proposed model, a baseline and the non-learned rows; the cases that need sanitation are caught by it."""
import math

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from bench.cli import CONF_DIR, run_experiment
from bench.experiments.stability import INPUT_CASES, metric_rows
from conftest import smoke_overrides


@pytest.fixture(scope="module")
def stability_table(tmp_path_factory):
    root = tmp_path_factory.mktemp("stability")
    overrides = smoke_overrides(root) + ["experiment.models=[srd,rae,kpcn,bilinear,oidn_lr]",
                                         "experiment.long_frames=12"]
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=["+experiment=stability", *overrides])
    run_experiment(cfg)
    out = root / "results" / "stability"
    return pd.read_csv(out / "table.csv"), out


def test_every_case_is_finite_or_a_clear_error(stability_table):
    table, out = stability_table
    assert (out / "table.md").exists() and (out / "table.tex").exists()
    bad = table[~table["finite"].astype(bool) & table["error"].isna()] if "error" in table else \
        table[~table["finite"].astype(bool)]
    assert bad.empty, bad[["model", "case"]].to_string()
    steps = table["train step"].dropna()
    assert steps.map(lambda s: s == "ok" or s.startswith("divergence detected")).all(), steps.to_string()


def test_every_case_ran_for_every_model(stability_table):
    table, _ = stability_table
    for model in ("srd", "rae", "kpcn", "bilinear", "oidn_lr"):
        cases = set(table.loc[table["model"] == model, "case"])
        assert set(INPUT_CASES) <= cases, model
        assert {"size 1x1", "sequence of 12 frames", "bf16 autocast (CPU)"} <= cases, model
    srd = set(table.loc[table["model"] == "srd", "case"])
    assert {"deform offsets +1e+03", "deform offsets -1e+03", "train at 10x lr"} <= srd


def test_sanitation_is_what_keeps_nan_inputs_finite(stability_table):
    table, _ = stability_table
    nan = table[(table["model"] == "srd") & (table["case"] == "NaN radiance")].iloc[0]
    assert bool(nan["finite"]) and not bool(nan["finite without sanitation"])


def test_recurrent_state_does_not_drift(stability_table):
    table, _ = stability_table
    long = table[(table["model"] == "srd") & (table["case"] == "sequence of 12 frames")].iloc[0]
    assert long["relMSE vs clean case"] < 1e-2  # a periodic input gives a (nearly) periodic output


def test_metric_edge_cases():
    rows = {r["case"]: r for r in metric_rows()}
    assert all(r["finite"] for r in rows.values())
    assert rows["PSNR, identical images (inf)"]["max |output|"] == math.inf
    assert math.isfinite(rows["relMSE, reference all zero (uses eps)"]["max |output|"])

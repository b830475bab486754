"""Helpers shared by the tests that run experiments at smoke scale."""
import os

# Mirroring to MLflow costs seconds per command; the tests that check it turn it on (tracking=mlflow).
os.environ.setdefault("SRD_TRACKING", "none")


def smoke_overrides(root, steps=4):
    """Hydra overrides for a fast smoke-scale run whose runs, results and data stay under `root`."""
    return ["scale=smoke", f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}",
            f"data_dir={root / 'data'}", "progress=false", f"train.steps={steps}",
            f"train.checkpoint_every={steps}", "data.splits.train.sequences=4"]

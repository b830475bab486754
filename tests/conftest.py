"""Helpers shared by the tests that run experiments at the smoke preset."""
import dataclasses
import os
import tempfile

# Mirroring to MLflow costs seconds per command; the tests that check it turn it on (tracking=mlflow).
os.environ.setdefault("SRD_TRACKING", "none")
# What the suite caches per machine (predict's measured fast path) stays out of the user's home.
os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="srd-bench-test-cache-")


def smoke_overrides(root, steps=4):
    """Hydra overrides for a fast smoke-preset run whose runs, results and data stay under `root`."""
    return ["preset=smoke", f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}",
            f"data_dir={root / 'data'}", "progress=false", f"train.steps={steps}",
            f"train.checkpoint_every={steps}", "data.splits.train.sequences=4"]


def smoke_context(**fields):
    """The experiments' Context as the CLI builds it from the real config at the smoke preset (`make_context`),
    with `fields` replaced: tests never restate the config's defaults."""
    from hydra import compose, initialize_config_dir
    from bench.cli import CONF_DIR, make_context
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        ctx = make_context(compose("config", overrides=["preset=smoke"]))
    return dataclasses.replace(ctx, **fields)

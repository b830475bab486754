"""The shared trainer and the run identities that decide reuse, on synthetic data (no rendering)."""
import copy
import json

import pytest
import torch

from baselines.edsr import EDSR
from bench.experiments.pipeline import Context, _train_identity
from bench.tasks import get_task
from bench.train import CHECKPOINT, TrainingDiverged, load_weights, lr_at, train

TASK = get_task("srd")
WEIGHTS = {"final": {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 0},
           "intermediate": {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 0}}


class SyntheticSequences:
    """Deterministic random crops keyed by (index, draw), like SequenceDataset.item."""

    def __init__(self, n=4, t=2, c=8, interrupt_at_draw=None, nan_at_draw=None):
        self.n, self.t, self.c = n, t, c
        self.interrupt_at_draw, self.nan_at_draw = interrupt_at_draw, nan_at_draw

    def __len__(self):
        return self.n

    def item(self, index, draw):
        if draw == self.interrupt_at_draw:
            raise KeyboardInterrupt("simulated interruption")
        g = torch.Generator().manual_seed(index * 7919 + draw)
        hr = torch.rand(self.t, 3, 2 * self.c, 2 * self.c, generator=g)
        lr = torch.nn.functional.avg_pool2d(hr, 2) + 0.05 * torch.randn(self.t, 3, self.c, self.c, generator=g)
        if draw == self.nan_at_draw:
            hr = hr * float("nan")
        return {"lr_noisy": lr, "lr_gbuf": torch.rand(self.t, 7, self.c, self.c, generator=g),
                "hr_ref": hr, "hr_noisy": hr + 0.05 * torch.randn(hr.shape, generator=g)}


def _model():
    torch.manual_seed(0)
    return EDSR(channels=8, blocks=2)


def _train(data, out_dir, steps=6):
    return train(_model(), data, TASK, out_dir, steps=steps, batch_size=2, loss_weights=WEIGHTS,
                 checkpoint_every=3, progress=False)


def test_lr_halves_every_quarter():
    assert [lr_at(s, 400, 6e-4, 0.25) for s in (0, 99, 100, 200, 300, 399)] == \
        pytest.approx([6e-4, 6e-4, 3e-4, 1.5e-4, 7.5e-5, 7.5e-5])


def test_training_reduces_the_loss(tmp_path):
    summary = _train(SyntheticSequences(), tmp_path, steps=30)
    assert summary["steps"] == 30 and summary["final_loss"] < summary["first_loss"]
    assert (tmp_path / "curve.csv").exists()


def test_interrupted_training_resumes_to_the_same_weights(tmp_path):
    full = _model()
    train(full, SyntheticSequences(), TASK, tmp_path / "full", steps=6, batch_size=2, loss_weights=WEIGHTS,
          checkpoint_every=3, progress=False)
    with pytest.raises(KeyboardInterrupt):  # dies in step 5, after the checkpoint of step 3
        _train(SyntheticSequences(interrupt_at_draw=4 * 2), tmp_path / "cut")
    assert torch.load(tmp_path / "cut" / CHECKPOINT, weights_only=False)["step"] == 3
    summary = _train(SyntheticSequences(), tmp_path / "cut")
    assert summary["resumed_from_step"] == 3 and summary["steps"] == 6
    resumed = load_weights(_model(), tmp_path / "cut")
    for a, b in zip(full.state_dict().values(), resumed.state_dict().values()):
        assert torch.equal(a, b)


def test_non_finite_loss_stops_with_a_clear_error_and_keeps_the_last_checkpoint(tmp_path):
    with pytest.raises(TrainingDiverged, match=r"non-finite loss \(nan\) at step 4; the last good checkpoint is .*checkpoint.pt"):
        _train(SyntheticSequences(nan_at_draw=4 * 2), tmp_path)
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    assert state["step"] == 3
    assert all(torch.isfinite(v).all() for v in state["model"].values())


@pytest.fixture
def ctx(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "manifest.json").write_text(json.dumps(
        {"spec": {"spp": 8}, "passes": ["lr_noisy"], "frames": [
            {"split": "train", "sequence": "a", "frame": 0, "settings_hash": "x"}]}))
    train_cfg = {"steps": 10, "batch_size": 2, "seq_len": 2, "crop": 8, "lr": 6e-4, "betas": [0.9, 0.99],
                 "halve_every": 0.25, "hdr": "clamp", "checkpoint_every": 5, "loss": WEIGHTS}
    return Context(scale="smoke", runs_dir=tmp_path / "runs", results_dir=tmp_path / "results",
                   data_dir=tmp_path / "data", data_spec={"spp": 8}, train=train_cfg, eval={},
                   models={"edsr": {"_target_": "baselines.edsr.EDSR", "channels": 8}})


def test_train_identity_changes_exactly_with_what_determines_the_result(ctx, tmp_path):
    cfg = ctx.models["edsr"]
    base = _train_identity(ctx, cfg, TASK, 0, None)
    same = copy.deepcopy(ctx)
    same.train["checkpoint_every"] = 99
    same.workers, same.progress, same.results_dir = 7, False, tmp_path / "elsewhere"
    assert _train_identity(same, cfg, TASK, 0, None) == base
    changed = []
    for key, value in (("steps", 11), ("lr", 1e-3), ("crop", 16)):
        other = copy.deepcopy(ctx)
        other.train[key] = value
        changed.append(_train_identity(other, cfg, TASK, 0, None))
    changed.append(_train_identity(ctx, {**cfg, "channels": 9}, TASK, 0, None))
    changed.append(_train_identity(ctx, cfg, TASK, 1, None))
    changed.append(_train_identity(ctx, cfg, get_task("sr"), 0, None))
    changed.append(_train_identity(ctx, cfg, TASK, 0, {"weights": "a.pth", "sha256": "1", "layer": "relu3_3"}))
    manifest = json.loads((ctx.data_dir / "manifest.json").read_text())
    manifest["frames"][0]["settings_hash"] = "y"           # the data on disk changed
    (ctx.data_dir / "manifest.json").write_text(json.dumps(manifest))
    changed.append(_train_identity(ctx, cfg, TASK, 0, None))
    assert all(ident != base for ident in changed)
    assert len({json.dumps(i, sort_keys=True) for i in changed}) == len(changed)


def test_intermediate_supervision_is_used_only_when_weighted():
    from bench.models.srd import SRDNet
    from bench.train import batch_loss, collate
    torch.manual_seed(0)
    model = SRDNet(channels=8, dn_levels=2, dn_deform_blocks=1)
    batch = collate([SyntheticSequences().item(i, 0) for i in range(2)], TASK.buffers())
    _, parts = batch_loss(model, batch, TASK, WEIGHTS, "clamp")
    assert "intermediate.spatial" in parts and "final.spatial" in parts
    off = {**WEIGHTS, "intermediate": {"edge": 0, "temporal": 0, "spatial": 0, "perceptual": 0}}
    _, parts = batch_loss(model, batch, TASK, off, "clamp")
    assert not any(k.startswith("intermediate.") for k in parts)

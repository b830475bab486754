"""The shared trainer and the run identities that decide reuse, on synthetic data (no rendering)."""
import dataclasses
import math
import time
import json

import pandas as pd
import pytest
import torch

from baselines.edsr import EDSR
from bench.experiments.training import _train_identity
from bench.tasks import get_task
from bench.train import CHECKPOINT, Recipe, TrainingDiverged, load_weights, lr_at, train
from conftest import config_recipe, smoke_context

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


def _recipe(steps=6, **changes):
    return config_recipe(**{"steps": steps, "batch_size": 2, "seq_len": 2, "crop": 8, "loss": WEIGHTS,
                     "checkpoint_every": 3, "warmup": 0.2, "val_every": 2, **changes})


def _train(data, out_dir, steps=6, model=None, **changes):
    return train(model or _model(), data, TASK, out_dir, _recipe(steps, **changes), progress=False)


def test_paper_schedule_halves_every_quarter():
    recipe = config_recipe(steps=400, lr=6e-4, schedule="halve", halve_every=0.25)
    assert [lr_at(s, recipe) for s in (0, 99, 100, 200, 300, 399)] == \
        pytest.approx([6e-4, 6e-4, 3e-4, 1.5e-4, 7.5e-5, 7.5e-5])


def test_cosine_schedule_warms_up_linearly_then_decays_to_zero():
    recipe = config_recipe(steps=100, lr=1e-3, schedule="cosine", warmup=0.1)
    lrs = [lr_at(s, recipe) for s in range(100)]
    assert lrs[:10] == pytest.approx([1e-4 * (s + 1) for s in range(10)])          # linear warm-up
    assert lrs[10] == pytest.approx(1e-3)                                            # the peak
    assert lrs[55] == pytest.approx(0.5e-3, rel=0.05)                               # half way down
    assert all(a >= b for a, b in zip(lrs[10:], lrs[11:])) and lrs[-1] < 1e-6       # monotone to ~0


def test_the_identity_names_every_option_but_loss_terms_of_weight_zero():
    base = config_recipe(loss=WEIGHTS)
    assert set(base.identity()) == ({f for f in Recipe.__dataclass_fields__} - set(Recipe.NOT_IDENTITY)
                                    - {"compile", "emitters", "fireflies", "emitters_exposure", "loss_knee"})
    # eager, no pasted emitters or fireflies, lamp items at their own exposure, no loss knee: left out
    # (Recipe.OMITTED_AT), so runs recorded before the options keep their hash
    assert (base.compile, base.emitters, base.fireflies, base.emitters_exposure, base.loss_knee) == (None, 0.0, 0.0, "with", None)
    assert config_recipe(emitters=0.25).identity()["emitters"] == 0.25
    assert config_recipe(fireflies=0.25).identity()["fireflies"] == 0.25
    assert config_recipe(emitters=0.25, emitters_exposure="without").identity()["emitters_exposure"] == "without"
    assert config_recipe(loss_knee=2.0).identity()["loss_knee"] == 2.0
    assert base.identity()["colour_permute"] is False and config_recipe(colour_permute=True).identity()["colour_permute"]
    assert "perceptual" not in base.identity()["loss"]["final"]
    # a term set to 0 (conf/pin/studies.yaml takes out a term the preset has since added) is the recipe without it
    with_term = {head: {**terms, "ssim": 8} for head, terms in WEIGHTS.items()}
    zeroed = {head: {**terms, "ssim": 0} for head, terms in WEIGHTS.items()}
    assert config_recipe(loss=zeroed).identity() == base.identity() != config_recipe(loss=with_term).identity()


def test_recipe_from_config_needs_every_key_and_rejects_unknown_keys_and_values():
    config = dataclasses.asdict(config_recipe())
    with pytest.raises(ValueError, match="unknown train"):
        Recipe.from_config({**config, "lrr": 1})
    with pytest.raises(ValueError, match=r"missing train.* keys \['lr'\]"):
        Recipe.from_config({k: v for k, v in config.items() if k != "lr"})
    assert Recipe.from_config(config) == config_recipe()
    with pytest.raises(ValueError, match="schedule"):
        config_recipe(schedule="step")


def test_channels_last_training_is_the_same_training_and_bf16_stays_near_it(tmp_path):
    """train.channels_last changes the memory format only (the same losses to float reordering);
    train.precision=bf16 runs forward and loss under bfloat16 autocast, close to fp32 and with float32
    weights; every run records its throughput and the share of it spent building batches."""
    data = SyntheticSequences()
    fp32 = _train(data, tmp_path / "fp32", steps=4)
    nhwc_model = _model()
    nhwc = _train(data, tmp_path / "nhwc", steps=4, model=nhwc_model, channels_last=True)
    assert next(p for p in nhwc_model.parameters() if p.dim() == 4).is_contiguous(memory_format=torch.channels_last)
    assert nhwc["final_loss"] == pytest.approx(fp32["final_loss"], rel=1e-4)
    bf16_model = _model()
    bf16 = _train(data, tmp_path / "bf16", steps=4, model=bf16_model, precision="bf16")
    assert all(p.dtype == torch.float32 for p in bf16_model.parameters())
    assert bf16["final_loss"] == pytest.approx(fp32["final_loss"], rel=0.05) and bf16["final_loss"] != fp32["final_loss"]
    for summary in (fp32, nhwc, bf16):
        assert summary["samples_per_s"] > 0 and 0 < summary["data_share"] < 1
    with pytest.raises(ValueError, match="precision"):
        config_recipe(precision="fp16")


def test_ema_is_the_average_of_the_weights_and_what_the_run_keeps(tmp_path):
    model = _model()
    _train(SyntheticSequences(), tmp_path, steps=8, model=model, ema=0.5)
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    raw, ema = state["model"], state["ema"]
    assert any(not torch.equal(raw[k], ema[k]) for k in raw)             # the average lags the weights
    for k, v in model.state_dict().items():                              # train() leaves the EMA in the model
        assert torch.equal(v, ema[k])
    assert all(torch.equal(v, ema[k]) for k, v in load_weights(_model(), tmp_path).state_dict().items())


def test_ema_update_follows_its_formula():
    from bench.train import update_ema
    a, b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    before = a.weight.detach().clone()
    update_ema(a, b, decay=0.9, step=1000)                               # d = min(0.9, 1001 / 1010) = 0.9
    assert torch.allclose(a.weight, 0.9 * before + 0.1 * b.weight.detach())


def test_a_training_starts_with_its_ema_in_its_models_memory_format():
    """training_start (the trainer's and the speed table's): with train.channels_last the model's convs are
    channels-last and so are the EMA copy's, made after (the EMA's foreach update takes same-strided
    lists); without an EMA, none; Adam at the recipe's lr and betas."""
    from bench.train import training_start
    model = EDSR(channels=4, blocks=1)
    ema, optimizer = training_start(model, config_recipe(channels_last=True, lr=3e-4, betas=[0.8, 0.9]), "cpu")
    weights = [p for p in model.parameters() if p.ndim == 4]
    assert weights and all(p.is_contiguous(memory_format=torch.channels_last) and not p.is_contiguous() for p in weights)
    assert [p.stride() for p in ema.parameters()] == [p.stride() for p in model.parameters()]
    assert model.training and not ema.training and not any(p.requires_grad for p in ema.parameters())
    assert optimizer.param_groups[0]["lr"] == 3e-4 and optimizer.param_groups[0]["betas"] == (0.8, 0.9)
    assert training_start(model, config_recipe(ema=None), "cpu")[0] is None


def test_gradient_clipping_bounds_the_update_norm(tmp_path):
    _train(SyntheticSequences(), tmp_path / "c", steps=3, clip_grad_norm=1e-3)
    curve = torch.load(tmp_path / "c" / CHECKPOINT, weights_only=False)["curve"]
    assert all(c["grad_norm"] > 1e-3 for c in curve)  # the recorded norm is before clipping ...
    clipped, free = _model(), _model()
    _train(SyntheticSequences(), tmp_path / "clip", steps=1, model=clipped, clip_grad_norm=1e-9, ema=None)
    _train(SyntheticSequences(), tmp_path / "free", steps=1, model=free, clip_grad_norm=None, ema=None)
    start = _model()
    moved = lambda m: sum((p - q).abs().sum() for p, q in zip(m.parameters(), start.parameters()))
    assert moved(clipped) < moved(free)  # ... and a tiny bound makes Adam's first step smaller


def test_validation_curve_is_recorded_every_k_steps_and_at_the_end(tmp_path):
    calls = []

    def validate(model):
        assert not model.training
        calls.append(1)
        return {"PSNR": float(len(calls))}
    summary = train(_model(), SyntheticSequences(), TASK, tmp_path, _recipe(7, val_every=3), progress=False,
                    validate=validate)
    curve = pd.read_csv(tmp_path / "val_curve.csv")
    assert curve["step"].tolist() == [0, 3, 6, 7] and curve["PSNR"].tolist() == [1, 2, 3, 4]
    assert (curve["train_s"].diff().dropna() > 0).all() and curve["loss"][1:].notna().all()
    assert summary["val"] == {"PSNR": 4.0}


def test_training_reduces_the_loss(tmp_path):
    summary = _train(SyntheticSequences(), tmp_path, steps=30, lr=2e-3)
    assert summary["steps"] == 30 and summary["final_loss"] < summary["first_loss"]
    assert (tmp_path / "curve.csv").exists()


def test_interrupted_training_resumes_to_the_same_weights(tmp_path):
    """Bit-exact: weights, EMA, optimizer, schedule and the validation curve."""
    full = _model()
    validate = lambda model: {"w": float(next(model.parameters()).sum())}
    train(full, SyntheticSequences(), TASK, tmp_path / "full", _recipe(), progress=False, validate=validate)
    with pytest.raises(KeyboardInterrupt):  # dies in step 5, after the checkpoint of step 3
        train(_model(), SyntheticSequences(interrupt_at_draw=4 * 2), TASK, tmp_path / "cut", _recipe(),
              progress=False, validate=validate)
    assert torch.load(tmp_path / "cut" / CHECKPOINT, weights_only=False)["step"] == 3
    summary = train(_model(), SyntheticSequences(), TASK, tmp_path / "cut", _recipe(), progress=False,
                    validate=validate)
    assert summary["resumed_from_step"] == 3 and summary["steps"] == 6
    resumed = load_weights(_model(), tmp_path / "cut")
    for a, b in zip(full.state_dict().values(), resumed.state_dict().values()):
        assert torch.equal(a, b)
    full_state, cut_state = (torch.load(tmp_path / d / CHECKPOINT, weights_only=False) for d in ("full", "cut"))
    for a, b in zip(full_state["model"].values(), cut_state["model"].values()):
        assert torch.equal(a, b)
    assert [c["lr"] for c in full_state["curve"]] == [c["lr"] for c in cut_state["curve"]]
    assert [c["w"] for c in full_state["val_curve"]] == [c["w"] for c in cut_state["val_curve"]]


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
            {"split": "train", "sequence": "a", "frame": 0, "settings_hash": "x"},
            {"split": "val", "sequence": "b", "frame": 0, "settings_hash": "v"}]}))
    train = config_recipe(steps=10, batch_size=2, seq_len=2, crop=8, hdr="clamp", checkpoint_every=5, loss=WEIGHTS,
                   val_every=5)
    return smoke_context(runs_dir=tmp_path / "runs", results_dir=tmp_path / "results", data_dir=tmp_path / "data",
                         data_spec={"spp": 8}, train=train, render_data=False,  # the frames as they are on disk
                         models={"edsr": {"_target_": "baselines.edsr.EDSR", "channels": 8}})


def test_train_identity_changes_exactly_with_what_determines_the_result(ctx, tmp_path):
    cfg = ctx.models["edsr"]
    base = _train_identity(ctx, cfg, TASK, 0, None)
    # how often it is checkpointed and watched, not what it learns
    same = dataclasses.replace(ctx, train=dataclasses.replace(ctx.train, checkpoint_every=99, val_every=3,
                                                              val_sequences=9),
                               workers=7, progress=False, results_dir=tmp_path / "elsewhere")
    assert _train_identity(same, cfg, TASK, 0, None) == base
    changed = []
    for key, value in (("steps", 11), ("lr", 1e-3), ("crop", 16), ("ema", None), ("schedule", "halve"),
                       ("clip_grad_norm", 0.5), ("hdr", "pu")):
        other = dataclasses.replace(ctx, train=dataclasses.replace(ctx.train, **{key: value}))
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


def test_train_identity_ignores_the_other_splits(ctx):
    """Re-rendering validation references (more samples) must not make trained runs stale."""
    cfg = ctx.models["edsr"]
    base = _train_identity(ctx, cfg, TASK, 0, None)
    manifest = json.loads((ctx.data_dir / "manifest.json").read_text())
    manifest["frames"][1]["settings_hash"] = "v2"
    (ctx.data_dir / "manifest.json").write_text(json.dumps(manifest))
    import os
    os.utime(ctx.data_dir / "manifest.json", ns=(1, 1))  # a new mtime whatever the clock's resolution
    assert _train_identity(ctx, cfg, TASK, 0, None) == base


def test_your_own_data_is_fingerprinted_by_its_files_size_and_mtime(ctx):
    """render_data=false: a changed pixel (new mtime) or a file of another size is other data; the
    rendered data's fingerprint (render_data=true) follows its spec and settings only."""
    import os
    from bench.experiments.datasets import data_fingerprint
    for split, seq in (("train", "a"), ("val", "b")):
        (ctx.data_dir / split / seq).mkdir(parents=True)
        for res in ("lr", "hr"):
            (ctx.data_dir / split / seq / f"0000_{res}.exr").write_bytes(b"exr" * 10)
    ctx.render_data = True
    rendered = data_fingerprint(ctx, "train")
    ctx.render_data = False
    before = data_fingerprint(ctx, "train")
    hr = ctx.data_dir / "train" / "a" / "0000_hr.exr"
    os.utime(hr, ns=(10**18, 10**18))                       # rewritten in place, same size
    touched = data_fingerprint(ctx, "train")
    hr.write_bytes(b"exr" * 11)                              # another size
    os.utime(hr, ns=(10**18, 10**18))
    resized = data_fingerprint(ctx, "train")
    assert len({before, touched, resized}) == 3
    os.utime(ctx.data_dir / "val" / "b" / "0000_lr.exr", ns=(10**18, 10**18))
    assert data_fingerprint(ctx, "train") == resized          # another split's files do not count
    ctx.render_data = True
    assert data_fingerprint(ctx, "train") == rendered


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


def test_lr_range_analysis_finds_the_valley_and_the_divergence_of_a_known_curve():
    import numpy as np
    from bench.experiments.lr_range import analyse
    lr = np.logspace(-5, -1, 400)
    x = np.log10(lr)
    loss = 1.0 - 0.5 / (1 + np.exp(-4 * (x + 3.5))) + 20.0 * np.clip(x + 2.0, 0, None) ** 2  # falls, then blows up
    found = analyse(lr, loss, smoothing=0.0)
    assert found["lowest-loss lr"] == pytest.approx(10 ** -2.0, rel=0.1)
    # 4x the minimum (0.5): 20 (x + 2)^2 + 0.5 = 2 at x = -2 + sqrt(0.075)
    assert found["diverged"] and found["divergence lr"] == pytest.approx(10 ** (-2 + 0.075 ** 0.5), rel=0.05)
    assert found["suggested lr"] == pytest.approx(found["divergence lr"] / 10)
    loss[250:] = float("nan")                                    # a NaN loss is a divergence too
    assert analyse(lr, loss, smoothing=0.0)["divergence lr"] == pytest.approx(lr[250])


def test_without_a_terminal_training_logs_its_progress(tmp_path, caplog, monkeypatch):
    import bench.train
    monkeypatch.setattr(bench.train, "LOG_EVERY_S", 0.0)  # every step, for the test
    with caplog.at_level("INFO", logger="bench"):         # pytest's output is not a terminal: no bar
        train(_model(), SyntheticSequences(), TASK, tmp_path, _recipe(3), progress=True)
    lines = [r.getMessage() for r in caplog.records if "s/step" in r.getMessage()]
    assert len(lines) == 3 and lines[-1].startswith("train EDSR: step 3/3,") and "min left" in lines[-1]


def test_checkpoints_also_on_wall_time(tmp_path):
    with pytest.raises(KeyboardInterrupt):  # dies in step 5; checkpoint_every alone would have saved none
        train(_model(), SyntheticSequences(interrupt_at_draw=4 * 2), TASK, tmp_path,
              _recipe(checkpoint_every=100, checkpoint_every_s=0.0), progress=False)
    assert torch.load(tmp_path / CHECKPOINT, weights_only=False)["step"] == 4


_INTERRUPTIBLE = '''
import sys, time
import torch
torch.set_num_threads(1)  # the same reduction order as the resuming test process
sys.path.insert(0, sys.argv[2])
from test_train import SyntheticSequences, TASK, _model, _recipe
from bench.train import TrainingInterrupted, train

class Slow(SyntheticSequences):
    def item(self, index, draw):
        if draw == 4:
            print("training", flush=True)
        time.sleep(0.1)
        return super().item(index, draw)

try:
    train(_model(), Slow(), TASK, sys.argv[1], _recipe(steps=40, checkpoint_every=1000), progress=False)
except TrainingInterrupted as err:
    print(err, flush=True)
    sys.exit(err.exit_code)
'''


def test_sigterm_saves_a_checkpoint_and_the_resumed_run_equals_an_uninterrupted_one(tmp_path):
    """A real process, a real signal: preemption loses nothing and changes nothing."""
    import signal
    import subprocess
    import sys
    from pathlib import Path
    cut = tmp_path / "cut"
    proc = subprocess.Popen([sys.executable, "-c", _INTERRUPTIBLE, str(cut), str(Path(__file__).parent)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "training"
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "SIGTERM at step" in out and "run the same command again to resume" in out
    stopped_at = torch.load(cut / CHECKPOINT, weights_only=False)["step"]
    assert 2 <= stopped_at < 40
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # bit-exact across processes needs one reduction order
    try:
        summary = train(_model(), SyntheticSequences(), TASK, cut, _recipe(steps=40, checkpoint_every=1000),
                        progress=False)
        full = _model()
        train(full, SyntheticSequences(), TASK, tmp_path / "full", _recipe(steps=40, checkpoint_every=1000),
              progress=False)
    finally:
        torch.set_num_threads(threads)
    assert summary["resumed_from_step"] == stopped_at
    for a, b in zip(full.state_dict().values(), load_weights(_model(), cut).state_dict().values()):
        assert torch.equal(a, b)


def test_last_fifth_gain_reads_the_learning_curve(tmp_path):
    from bench.experiments.row import last_fifth_gain
    curve = tmp_path / "val_curve.csv"
    pd.DataFrame({"step": [0, 100, 200, 300, 400, 500], "PSNR": [20.0, 25, 27, 28, 28.5, 28.6]}).to_csv(curve)
    assert last_fifth_gain(tmp_path) == pytest.approx(0.1)       # 500 vs the point at step 400
    assert last_fifth_gain(tmp_path / "missing") is None


def test_losses_are_read_back_every_25_steps_not_every_step(tmp_path, monkeypatch):
    """The step leaves its losses on the device (no host sync per step): one read-back per READ_BACK_EVERY
    steps, one at the end, and the curve still has every step's loss, learning rate and gradient norm."""
    import bench.train as trainer
    calls = []
    real = trainer.read_back
    monkeypatch.setattr(trainer, "read_back", lambda unread, *a: calls.append(len(unread)) or real(unread, *a))
    _train(SyntheticSequences(), tmp_path, steps=60, checkpoint_every=1000, val_every=0)
    assert trainer.READ_BACK_EVERY == 25 and calls == [25, 25, 10]
    curve = pd.read_csv(tmp_path / "curve.csv")
    assert curve["step"].tolist() == list(range(1, 61)) and curve[["loss", "grad_norm", "lr"]].notna().all().all()


def test_a_divergence_between_read_backs_is_named_by_its_step_and_never_checkpointed(tmp_path):
    """A NaN at step 30 is found at the next read-back, which comes before step 40's checkpoint: the error
    names step 30, curve.csv ends at the step before it, and the checkpoint stays step 20's."""
    with pytest.raises(TrainingDiverged, match=r"non-finite loss \(nan\) at step 30; the last good checkpoint is "
                                                r".*checkpoint.pt") as err:
        _train(SyntheticSequences(nan_at_draw=30 * 2), tmp_path, steps=60, checkpoint_every=20, val_every=0)
    assert err.value.step == 30
    assert pd.read_csv(tmp_path / "curve.csv")["step"].tolist() == list(range(1, 31))
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    assert state["step"] == 20 and all(torch.isfinite(v).all() for v in state["model"].values())


COMPILED_RTOL = 1e-5  # torch.compile fuses ops (another rounding order): the step's losses agree to this


def _compiled_matches_eager(out_dir):
    """Three steps eager and three with train.compile=default from the same weights: the same losses and
    gradient norms per step within COMPILED_RTOL, the same final weights within 1e-4."""
    curves, weights = {}, {}
    for mode in (None, "default"):
        model = _model()
        train(model, SyntheticSequences(), TASK, out_dir / str(mode), _recipe(3, compile=mode, val_every=0),
              progress=False)
        curves[mode] = pd.read_csv(out_dir / str(mode) / "curve.csv")
        weights[mode] = model.state_dict()
    for column in ("loss", "grad_norm"):
        assert curves["default"][column].tolist() == pytest.approx(curves[None][column].tolist(), rel=COMPILED_RTOL)
    for name, value in weights[None].items():
        assert torch.allclose(weights["default"][name], value, rtol=1e-4, atol=1e-6), name
    assert "compile" not in _recipe(3).identity() and _recipe(3, compile="default").identity()["compile"] == "default"


@pytest.mark.slow  # Inductor builds about 21 C++ kernels: 42 s, make test's longest test; make test-slow. make
# test keeps the rest of it (the test below: the same step traced, without Inductor's code generation)
def test_a_compiled_training_step_equals_eager_within_its_tolerance(tmp_path):
    """train.compile=default (Inductor on the CPU) traces forward, losses and backward: the same losses
    and gradient norms per step as eager within COMPILED_RTOL, the same final weights within 1e-4, and
    its identity names the option (eager's leaves it out, so recorded runs keep their hashes)."""
    _compiled_matches_eager(tmp_path)


def test_the_compiled_training_step_traces_forward_losses_and_backward_as_eager_computes_them(tmp_path,
                                                                                            monkeypatch):
    """What the trainer does with train.compile, short of Inductor's C++ kernels (the slow test above has
    them): torch.compile with the recipe's mode, over forward and losses, whose backward is the traced
    graph's (TorchDynamo and AOT autograd: backend aot_eager); eager's losses, gradient norms and weights;
    the identity names the option."""
    from torch._dynamo.utils import counters
    modes, compile_ = [], torch.compile

    def traced(fn, mode=None):
        modes.append(mode)
        return compile_(fn, backend="aot_eager")
    monkeypatch.setattr(torch, "compile", traced)
    counters.clear()
    _compiled_matches_eager(tmp_path)
    assert modes == ["default"]                          # compiled once, with the recipe's mode
    assert counters["aot_autograd"]["ok"] >= 1 and not counters["graph_break"], dict(counters)  # traced, whole


def _item(t=3, c=8, seed=0):
    """An srd training item: LR input and gBuffer (c x c), HR target and intermediate target (2c x 2c)."""
    g = torch.Generator().manual_seed(seed)
    return {"lr_noisy": torch.rand(t, 3, c, c, generator=g), "lr_gbuf": torch.rand(t, 7, c, c, generator=g),
            "hr_ref": torch.rand(t, 3, 2 * c, 2 * c, generator=g), "hr_noisy": torch.rand(t, 3, 2 * c, 2 * c, generator=g)}


def test_an_emitter_is_one_noise_free_level_over_the_same_area_of_the_input_and_both_targets():
    """bench.emitters: a rectangle of one radiance, 1e1-1e4x the first frame's exposure, in every frame of
    the input and of the HR target and intermediate target over the pixels it covers; the gBuffer and
    every other pixel as they were, and the item given in left untouched."""
    import random
    from bench.emitters import LOG10_LEVEL, with_emitter
    from bench.exposure import frame_exposure
    for n in range(20):
        item = _item(seed=n)
        before = {k: v.clone() for k, v in item.items()}
        out = with_emitter(item, TASK, random.Random(n))
        assert all(torch.equal(item[k], before[k]) for k in item) and out["lr_gbuf"] is item["lr_gbuf"]
        lit = out["lr_noisy"] != item["lr_noisy"]
        level = out["lr_noisy"][lit].unique()
        assert level.numel() == 1 and lit.any(), n                       # one level, no noise on it
        ratio = float(level) / float(frame_exposure(item["lr_noisy"][:1], "exposure").flatten()[0])
        assert 10 ** LOG10_LEVEL[0] * (1 - 1e-5) <= ratio <= 10 ** LOG10_LEVEL[1] * (1 + 1e-5), n
        area = lit[0, 0]                                                  # the same pixels in every frame and channel
        assert torch.equal(lit, area.expand_as(lit))
        rows, cols = area.any(1).nonzero()[:, 0], area.any(0).nonzero()[:, 0]
        assert area.sum() == len(rows) * len(cols) >= 4                  # a rectangle, at least 2x2
        hr_area = area.repeat_interleave(2, 0).repeat_interleave(2, 1)   # the HR pixels it covers
        for name in ("hr_ref", "hr_noisy"):
            assert (out[name][..., hr_area] == level).all(), name
            assert torch.equal(out[name][..., ~hr_area], item[name][..., ~hr_area]), name


@pytest.mark.parametrize("share", ["emitters", "fireflies"])
def test_a_share_of_emitters_or_fireflies_pastes_that_share_of_the_draws_and_the_same_ones_each_time(share):
    from bench.train import augmented
    item, quarter = _item(t=1, c=4), config_recipe(**{share: 0.25})
    pasted = [augmented(item, TASK, quarter, seed=0, draw=d) is not item for d in range(2000)]
    assert 0.22 <= sum(pasted) / len(pasted) <= 0.28
    again = [augmented(item, TASK, quarter, seed=0, draw=d) is not item for d in range(2000)]
    other_seed = [augmented(item, TASK, quarter, seed=1, draw=d) is not item for d in range(2000)]
    assert pasted == again and pasted != other_seed
    assert not any(augmented(item, TASK, config_recipe(), seed=0, draw=d) is not item for d in range(100))
    one, two = (augmented(item, TASK, config_recipe(**{share: 1.0}), seed=0, draw=7) for _ in range(2))
    assert all(torch.equal(one[k], two[k]) for k in item)


def test_the_lamps_are_those_recorded_before_fireflies_and_fireflies_take_the_level_of_the_item_without_its_lamp():
    """A recipe's lamps are drawn as the trainings recorded with `emitters` before fireflies existed drew
    them (the RNG seeded "emitter {seed} {draw}": its first number decides, the rest place the lamp), with or
    without fireflies, which draw from their own RNG; where both land, the fireflies' levels are those of the
    item without its lamp (a lamp would raise the exposure they are measured against)."""
    import random
    from bench.emitters import LOG10_LEVEL, with_emitter
    from bench.exposure import frame_exposure
    from bench.train import augmented
    item = _item(t=2, c=8)
    exposure = float(frame_exposure(item[TASK.x][:1, :3], "exposure").flatten()[0])
    lamps, both = config_recipe(emitters=0.5), config_recipe(emitters=0.5, fireflies=0.5)
    seen = set()
    for draw in range(200):
        recorded = random.Random(f"emitter 3 {draw}")
        expected = with_emitter(item, TASK, recorded) if recorded.random() < 0.5 else item
        a, b = augmented(item, TASK, lamps, seed=3, draw=draw), augmented(item, TASK, both, seed=3, draw=draw)
        for name in (TASK.x, TASK.y, TASK.mid):
            assert torch.equal(a[name], expected[name]), (draw, name)
        for name in (TASK.y, TASK.mid):                      # the targets hold the lamps only
            assert torch.equal(b[name], expected[name]), (draw, name)
        fireflies = b[TASK.x] != a[TASK.x]
        lamp = a[TASK.x] is not item[TASK.x]
        seen.add((lamp, bool(fireflies.any())))
        if fireflies.any():
            levels = b[TASK.x][fireflies] / exposure
            assert (levels <= 10 ** LOG10_LEVEL[1] * (1 + 1e-5)).all(), draw        # not the lamp's exposure
            assert (levels >= 10 ** LOG10_LEVEL[0] * (1 - 1e-5)).all(), draw
    assert seen == {(False, False), (False, True), (True, False), (True, True)}      # decided apart


def test_fireflies_are_single_pixels_of_one_frame_in_the_input_only():
    """bench.emitters.with_fireflies: in each frame 1-4 pixels of all three channels at 1e1-3e4x the first
    frame's exposure, placed per frame; the targets and the gBuffer as they were, the item given untouched."""
    import random
    from bench.emitters import FIREFLIES_PER_FRAME, LOG10_LEVEL, with_fireflies
    from bench.exposure import frame_exposure
    places = []
    for n in range(20):
        item = _item(t=3, c=16, seed=n)
        before = {k: v.clone() for k, v in item.items()}
        out = with_fireflies(item, TASK, random.Random(n))
        assert all(torch.equal(item[k], before[k]) for k in item)
        assert all(out[k] is item[k] for k in item if k != TASK.x)
        hit = out[TASK.x] != item[TASK.x]
        assert hit.shape[1] == 3 and torch.equal(hit.all(1), hit.any(1))         # all three channels of a pixel
        exposure = float(frame_exposure(item[TASK.x][:1, :3], "exposure").flatten()[0])
        for frame in range(3):
            pixels = hit[frame].any(0).nonzero()
            assert 1 <= len(pixels) <= FIREFLIES_PER_FRAME[1], (n, frame)
            levels = out[TASK.x][frame, 0][hit[frame, 0]] / exposure
            assert ((levels >= 10 ** LOG10_LEVEL[0] * (1 - 1e-5)) & (levels <= 10 ** LOG10_LEVEL[1] * (1 + 1e-5))).all()
            places.append({tuple(p.tolist()) for p in pixels})
    assert sum(a != b for a, b in zip(places[::3], places[1::3])) >= 18    # each frame its own


def test_lamp_items_without_their_lamp_carry_the_exposure_they_had_as_rendered():
    """train.emitters_exposure=without: `augmented` hands every item (lamp or not) the per-frame exposure of
    its input as rendered, under bench.train.EXPOSURE; batch_loss encodes at it. A lamp raises the item's
    own exposure, and an exposure equal to the item's own gives batch_loss's loss without the key."""
    from bench.exposure import frame_exposure
    from bench.train import EXPOSURE, augmented, batch_loss, collate
    recipe = config_recipe(emitters=0.5, emitters_exposure="without", hdr="exposure")
    items = [_item(t=2, c=16, seed=n) for n in range(2)]
    out = [augmented(item, TASK, recipe, seed=0, draw=d) for d, item in enumerate(items * 8)]
    lamps = 0
    for item, aug in zip(items * 8, out):
        assert torch.equal(aug[EXPOSURE], frame_exposure(item[TASK.x], "exposure"))
        if not torch.equal(aug[TASK.x], item[TASK.x]):   # a lamp: brighter than the exposure recorded
            lamps += 1
            assert (frame_exposure(aug[TASK.x], "exposure") > aug[EXPOSURE]).all()
    assert 0 < lamps < len(out)
    assert EXPOSURE not in augmented(items[0], TASK, config_recipe(emitters=0.5, hdr="exposure"), seed=0, draw=0)
    batch = collate(items, TASK.buffers(with_mid=True))
    own = {**batch, EXPOSURE: frame_exposure(batch[TASK.x], "exposure")}
    model = _model()
    assert batch_loss(model, own, TASK, WEIGHTS, "exposure")[0] == batch_loss(model, batch, TASK, WEIGHTS, "exposure")[0]
    half = {**batch, EXPOSURE: own[EXPOSURE] / 2}
    assert batch_loss(model, half, TASK, WEIGHTS, "exposure")[0] != batch_loss(model, batch, TASK, WEIGHTS, "exposure")[0]


def test_the_loss_in_exposure_pass_takes_no_gradient_from_the_network_where_a_lamp_passes():
    """bench.exposure.pass_highlights inside batch_loss: on the HR pixels of a lamp far above the exposure the
    final output is the input's, so the network's output there gets no gradient (in `exposure` it does);
    the rest of the frame trains as before."""
    from bench.train import batch_loss, collate
    item = _item(t=2, c=32)
    for name, s in (("lr_noisy", 1), ("hr_ref", 2), ("hr_noisy", 2)):
        item[name][..., :3, 2 * s:7 * s, 2 * s:7 * s] = 5e3   # in one of the 16 exposure blocks: about 6e3x
    batch, model, seen = collate([item], TASK.buffers(with_mid=True)), _model(), {}

    def forward(x, g):   # the model, keeping its final output's gradient
        out = model(x, g)
        out["final"].retain_grad()
        seen["final"] = out["final"]
        return out
    on_lamp = {}
    for domain in ("exposure", "exposure_pass"):
        batch_loss(forward, batch, TASK, WEIGHTS, domain)[0].backward()
        grad = seen["final"].grad
        on_lamp[domain] = grad[..., 4:14, 4:14].abs().max()
        assert grad[..., 20:, :].abs().max() > 0
    assert on_lamp["exposure_pass"] == 0 and on_lamp["exposure"] > 0


def test_the_lamp_options_refuse_recipes_they_do_nothing_in():
    with pytest.raises(ValueError, match="emitters_exposure=without"):
        config_recipe(emitters_exposure="without", hdr="exposure")                # no lamps
    with pytest.raises(ValueError, match="emitters_exposure=without"):
        config_recipe(emitters=0.25, emitters_exposure="without", hdr="pu")       # no exposure
    with pytest.raises(ValueError, match="emitters_exposure must be one of"):
        config_recipe(emitters=0.25, emitters_exposure="room")
    with pytest.raises(ValueError, match="loss_knee"):
        config_recipe(loss_knee=0)


def test_a_training_with_lamps_at_their_room_exposure_or_a_loss_knee_trains_on_them(tmp_path):
    """Lamps in every item (train.emitters=1), encoded at the exposure without them, or with the losses
    behind a knee: each curve differs from plain lamps', stays finite, and a second run repeats it."""
    options = {"plain": {}, "without": {"emitters_exposure": "without"}, "without again": {"emitters_exposure": "without"},
               "knee": {"loss_knee": 0.5}}
    curves = {}
    for name, changes in options.items():
        _train(SyntheticSequences(t=2, c=16), tmp_path / name, steps=3, val_every=0, emitters=1.0, hdr="exposure", **changes)
        curves[name] = pd.read_csv(tmp_path / name / "curve.csv")["loss"].tolist()
    assert curves["without"] == curves["without again"]
    assert curves["without"] != curves["plain"] and curves["knee"] != curves["plain"]
    assert all(map(math.isfinite, curves["without"] + curves["knee"]))


@pytest.mark.parametrize("share", ["emitters", "fireflies"])
def test_a_training_with_emitters_or_fireflies_trains_on_them(tmp_path, share):
    """train.emitters=1 (fireflies=1): every item of every step holds a lamp (fireflies); the losses differ
    from the training without, stay finite, and a second run gives the same curve."""
    curves = {}
    for name, value in (("none", 0.0), ("all", 1.0), ("all again", 1.0)):
        _train(SyntheticSequences(), tmp_path / name, steps=3, val_every=0, **{share: value})
        curves[name] = pd.read_csv(tmp_path / name / "curve.csv")["loss"].tolist()
    assert curves["all"] == curves["all again"] and curves["all"] != curves["none"]
    assert all(map(math.isfinite, curves["all"]))

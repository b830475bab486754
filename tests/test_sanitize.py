"""Input sanitation (bench.sanitize): every documented rule, and that the trainer and evaluator apply it."""
import math

import numpy as np
import torch

from bench.render import repair_nonfinite as render_repair
from bench.sanitize import sanitize_gbuffer, sanitize_inputs, sanitize_radiance


def test_radiance_nonfinite_repaired_like_the_renderer():
    torch.manual_seed(0)
    x = torch.rand(2, 3, 9, 11) * 5
    x[0, 1, 4, 4], x[1, 0, 0, 0], x[1, 2, 8, 10] = math.nan, math.inf, -math.inf
    x[0, 0, 2:5, 2:5] = math.nan  # a pixel with no finite neighbour in its channel
    out = sanitize_radiance(x)
    assert torch.isfinite(out).all() and (out >= 0).all()
    for b in range(2):  # same rule as the renderer's numpy repair (HxWxC)
        expected, _ = render_repair(x[b].permute(1, 2, 0).numpy())
        np.testing.assert_allclose(out[b].permute(1, 2, 0).numpy(), np.clip(expected, 0, None), rtol=1e-6)
    assert out[0, 0, 3, 3] == 0
    finite = torch.isfinite(x)
    torch.testing.assert_close(out[finite], x[finite].clamp_min(0))  # finite fireflies are kept


def test_negative_radiance_is_zero_and_fireflies_stay():
    x = torch.tensor([[[[-1.0, 1e6]]]])
    assert sanitize_radiance(x).flatten().tolist() == [0.0, 1e6]


def test_gbuffer_rules():
    g = torch.zeros(1, 7, 1, 4)
    g[0, 0:3, 0, 0] = torch.tensor([-0.5, 2.0, math.nan])       # albedo clamped, NaN -> 0
    g[0, 3:6, 0, 1] = torch.tensor([3.0, 0.0, 4.0])              # non-unit normal -> unit
    g[0, 3:6, 0, 2] = torch.tensor([0.0, 0.0, 0.0])              # zero-length normal stays 0
    g[0, 3:6, 0, 3] = torch.tensor([math.inf, 1.0, 0.0])         # non-finite component -> 0, then normalised
    g[0, 6, 0, :] = torch.tensor([-1.0, 5.0, math.nan, 0.3])     # roughness clamped to [0, 1]
    out = sanitize_gbuffer(g)
    assert out[0, 0:3, 0, 0].tolist() == [0.0, 1.0, 0.0]
    torch.testing.assert_close(out[0, 3:6, 0, 1], torch.tensor([0.6, 0.0, 0.8]))
    assert out[0, 3:6, 0, 2].tolist() == [0.0, 0.0, 0.0]
    torch.testing.assert_close(out[0, 3:6, 0, 3], torch.tensor([0.0, 1.0, 0.0]))
    torch.testing.assert_close(out[0, 6, 0], torch.tensor([0.0, 1.0, 0.0, 0.3]))
    assert sanitize_gbuffer(g[:, :3]).shape == (1, 3, 1, 4)      # a prefix layout keeps its size


def test_clean_inputs_pass_unchanged():
    torch.manual_seed(0)
    x = torch.rand(1, 2, 3, 5, 6)
    n = torch.randn(1, 2, 3, 5, 6)
    g = torch.cat([torch.rand(1, 2, 3, 5, 6), n / n.norm(dim=2, keepdim=True), torch.rand(1, 2, 1, 5, 6)], 2)
    sx, sg = sanitize_inputs(x, g)
    torch.testing.assert_close(sx, x, rtol=0, atol=0)
    torch.testing.assert_close(sg, g)
    assert sanitize_inputs(x, None)[1] is None


def test_trainer_and_evaluator_sanitize():
    from bench.evaluate import predict
    from bench.tasks import get_task
    from bench.train import batch_loss
    from baselines.edsr import EDSR
    torch.manual_seed(0)
    model = EDSR(channels=4, blocks=1)
    x, g = torch.rand(1, 2, 3, 6, 6), torch.rand(1, 2, 7, 6, 6)
    x[0, 0, :, 2, 2], g[0, 1, 3, 1, 1] = math.nan, math.inf
    assert torch.isfinite(predict(model, x, g, "clamp")).all()
    assert not torch.isfinite(predict(model, x, g, "clamp", sanitize=False)).all()
    batch = {"lr_noisy": x, "lr_gbuf": g, "hr_ref": torch.rand(1, 2, 3, 12, 12)}
    loss, _ = batch_loss(model, batch, get_task("sr_noisy").__class__("t", "lr_noisy", "lr_gbuf", "hr_ref", 2),
                         {"final": {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 0}}, "clamp")
    assert torch.isfinite(loss)

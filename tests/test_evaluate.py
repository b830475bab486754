"""The evaluator's ways of running a model: fp32 untiled (the reference), fast paths and tiles."""
import pytest
import torch

from baselines.edsr import EDSR
from bench.evaluate import evaluate
from bench.models.srd import SRDNet
from bench.tasks import get_task

TASK = get_task("srd")


class Frames:
    """Two full-frame sequences of random radiance and gBuffer (what SequenceDataset gives evaluate)."""

    def __init__(self, h=40, w=72, t=2):
        g = torch.Generator().manual_seed(0)
        self.items = [{"lr_noisy": torch.rand(t, 3, h, w, generator=g),
                       "lr_gbuf": torch.rand(t, 7, h, w, generator=g),
                       "hr_ref": torch.rand(t, 3, 2 * h, 2 * w, generator=g),
                       "meta": {"scene": f"s{i}", "sequence": f"s{i}-v0", "frames": list(range(t))}}
                      for i in range(2)]

    def __len__(self):
        return len(self.items)

    def __getitem__(self, index):
        return self.items[index]


def _nonzero(model):
    """Random weights everywhere (zero-initialised output convs would hide differences)."""
    torch.manual_seed(1)
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.05)
    return model.eval()


@pytest.mark.parametrize("make", [lambda: EDSR(channels=8, blocks=2),
                                  lambda: SRDNet(channels=8, cond_channels=8)])
def test_bf16_and_channels_last_score_like_fp32(make):
    model = _nonzero(make())
    _, ref = evaluate(model, Frames(), TASK)
    for path in ("channels_last", "bf16"):
        _, fast = evaluate(model, Frames(), TASK, path=path)
        tolerance = 1e-4 if path == "channels_last" else 0.02
        assert fast["relMSE"] == pytest.approx(ref["relMSE"], rel=tolerance), path
        assert fast["SSIM"] == pytest.approx(ref["SSIM"], rel=tolerance), path


def test_tiled_evaluation_of_a_conv_model_equals_whole_frames():
    model = _nonzero(EDSR(channels=8, blocks=2))  # receptive radius ~6 LR pixels < the 32-pixel overlap
    whole, _ = evaluate(model, Frames(h=40, w=72), TASK)
    tiled, _ = evaluate(model, Frames(h=40, w=72), TASK, tile=32)
    assert torch.allclose(torch.tensor(tiled["PSNR"].values), torch.tensor(whole["PSNR"].values), atol=1e-4)


def test_methods_on_linear_radiance_run_their_own_way():
    from baselines.oidn import OIDN
    from bench.evaluate import runner
    assert runner(OIDN(scale=2), "bf16", tile=32) is None  # OIDN takes linear HDR and runs its own library


def test_aggregate_gives_means_over_frames_and_standard_errors_over_sequences():
    import numpy as np
    import pandas as pd
    from bench.evaluate import aggregate
    per_image = pd.DataFrame({"sequence": ["a", "a", "b", "b", "c", "c"],
                              "relMSE": [1.0, 3.0, 2.0, 2.0, 6.0, 8.0],
                              "temporal relMSE": [np.nan, 1.0, np.nan, 2.0, np.nan, 6.0]})
    out = aggregate(per_image)
    assert out["relMSE"] == pytest.approx(22 / 6) and out["sequences"] == 3
    assert out["relMSE se"] == pytest.approx(np.std([2.0, 2.0, 7.0], ddof=1) / np.sqrt(3))
    assert out["temporal relMSE"] == pytest.approx(3.0)   # the first frames have none
    assert out["temporal relMSE se"] == pytest.approx(np.std([1.0, 2.0, 6.0], ddof=1) / np.sqrt(3))


def test_every_score_is_reported_per_frame():
    from bench.evaluate import SCORES
    per_image, metrics = evaluate(_nonzero(EDSR(channels=8, blocks=2)), Frames(t=3), TASK)
    for name in SCORES:
        assert name in per_image and f"{name} se" in metrics
    assert per_image["temporal relMSE"].isna().sum() == 2       # the first frame of each sequence


def test_scores_asked_for_are_the_ones_computed_with_the_same_values():
    """`evaluate(scores=...)` (the learning curve's three) computes only those, each equal to the full run's."""
    model = _nonzero(EDSR(channels=8, blocks=2))
    every, every_mean = evaluate(model, Frames(h=16, w=24), TASK)
    some, some_mean = evaluate(model, Frames(h=16, w=24), TASK, scores=("relMSE", "PSNR", "SSIM"))
    assert {"LDR-FLIP", "HDR-FLIP", "temporal relMSE"} <= set(every) and not {"LDR-FLIP", "HDR-FLIP"} & set(some)
    for name in ("relMSE", "PSNR", "SSIM"):
        assert some[name].tolist() == every[name].tolist() and some_mean[name] == every_mean[name]
        assert some_mean[f"{name} se"] == every_mean[f"{name} se"]

"""How much float16-rounded weights (the run archive's form, bench.archived) move the scores.

For each archived training with float32 weights (one per model class and task, seeds and Cascade stages
left out) and each committed weights file (results/<preset>/weights/*.pt), the model is scored by the
evaluator on synthetic frames twice, with its float32 weights and with them rounded to float16 (the
computation stays float32), and the per-frame relMSE, PSNR and SSIM are compared as adopt compares them
(largest relative difference over frames). Prints one row per model and the largest of each; adopt's
`rtol_rounded_weights` (conf/experiment/adopt.yaml) is set from it, with a margin for real frames.

    PYTHONPATH=$PWD .venv/bin/python scripts/fp16_weights_accuracy.py results/cpu/runs results/cpu/weights
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F

from bench import archived, runs
from bench.evaluate import evaluate
from bench.experiments.replay import COMPARED, relative_difference
from bench.models.factory import build_model
from bench.tasks import get_task
from bench.weights import load_exported

SEQUENCES, FRAMES, LR_SIZE = 2, 3, 48


def _smooth(gen, channels: int, size: int, low: int = 6) -> torch.Tensor:
    """(FRAMES, channels, size, size) of smooth random structure drifting from frame to frame."""
    base = torch.randn(1, channels, low, low, generator=gen)
    drift = torch.randn(1, channels, low, low, generator=gen) * 0.2
    frames = torch.cat([base + t * drift for t in range(FRAMES)])
    edges = (torch.rand(1, channels, 4 * low, 4 * low, generator=gen) > 0.7).float()  # some sharp detail
    return F.interpolate(frames, size=size, mode="bicubic", align_corners=False) \
        + 0.5 * F.interpolate(edges, size=size, mode="nearest")


def synthetic_sequence(seed: int) -> dict:
    """Every buffer of a full-frame sequence (T, C, H, W): an HDR reference over about three decades,
    Monte-Carlo-like noisy renders (gamma-distributed per-pixel sample means), gBuffers."""
    gen = torch.Generator().manual_seed(seed)
    hr = 2 * LR_SIZE
    hr_ref = torch.exp(1.2 * _smooth(gen, 3, hr) - 1.0)
    albedo = torch.sigmoid(_smooth(gen, 3, hr))
    normal = F.normalize(_smooth(gen, 3, hr) + torch.tensor([0.0, 0.0, 1.5]).view(1, 3, 1, 1), dim=1)
    roughness = torch.sigmoid(_smooth(gen, 1, hr))
    hr_gbuf = torch.cat([albedo, normal, roughness], 1)
    noise = lambda ref: ref * torch.distributions.Gamma(4.0, 4.0).sample(ref.shape)  # mean 1, 4 spp-like
    torch.manual_seed(seed)
    lr_ref = F.avg_pool2d(hr_ref, 2)
    return {"hr_ref": hr_ref, "hr_noisy": noise(hr_ref), "lr_ref": lr_ref, "lr_noisy": noise(lr_ref),
            "hr_gbuf": hr_gbuf, "lr_gbuf": F.avg_pool2d(hr_gbuf, 2),
            "meta": {"scene": f"synthetic{seed}", "sequence": f"synthetic{seed}", "frames": list(range(FRAMES))}}


def rounded(state: dict) -> dict:
    return {k: v.half().to(v.dtype) if v.is_floating_point() else v for k, v in state.items()}


def compare(model, task_name: str, hdr: str, frames: list) -> dict:
    task = get_task(task_name)
    exact, _ = evaluate(model, frames, task, hdr=hdr)
    model.load_state_dict(rounded(model.state_dict()))
    approx, _ = evaluate(model, frames, task, hdr=hdr)
    out = {m: relative_difference(approx[m], exact[m]) for m in COMPARED}
    out["PSNR dB"] = float(np.max(np.abs(approx["PSNR"] - exact["PSNR"])))
    return out


def models(archive: Path, weights_dir: Path):
    """(name, model with float32 weights, task, hdr) of every committed weights file and of one archived
    training per model class and task; weights rounded already (an exported file of a float16-rounded
    run, an archive converted to its compact form) are left out: rounding them again moves nothing."""
    for path in sorted(weights_dir.glob("*.pt")):
        model, meta = load_exported(path)
        if meta.get("weights_rounded_to_float16"):
            print(f"{path}: rounded to float16 already, left out", flush=True)
            continue
        yield path.name, model, meta["task"], meta["hdr"]
    seen = set()
    for path in sorted(archive.glob(f"train/*/{runs.RECORD}")):
        record = json.loads(path.read_text())
        identity = record["identity"]
        key = (identity["model"]["_target_"], identity["task"])
        if identity.get("stage") or key in seen or not (path.parent / archived.CHECKPOINT).exists():
            continue
        seen.add(key)
        model = archived.load_weights(build_model(identity["model"], get_task(identity["task"]).scale), path.parent)
        yield f"{record.get('label')} [{record['hash']}]", model, identity["task"], identity["train"]["hdr"]


def main(archive: str, weights_dir: str) -> None:
    torch.set_num_threads(2)
    frames = [synthetic_sequence(seed) for seed in range(SEQUENCES)]
    rows = []
    for name, model, task, hdr in models(Path(archive), Path(weights_dir)):
        rows.append({"model": name, "task": task, **compare(model.eval(), task, hdr, frames)})
        print(rows[-1], flush=True)
    if not rows:  # a table of zeros would read as "rounding moves nothing"
        sys.exit(f"nothing to compare: every weights file in {weights_dir} and every training in {archive} holds "
                 "float16-rounded weights (the float32 ones are in a run store's checkpoints, before archiving)")
    table = pd.DataFrame(rows)
    pd.set_option("display.width", 200)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.2e}"))
    print("largest:", {c: f"{table[c].max():.2e}" for c in (*COMPARED, "PSNR dB")}, f"over {len(table)} models")


if __name__ == "__main__":
    usage = f"usage: {sys.argv[0]} RUN_ARCHIVE WEIGHTS_DIR (e.g. results/cpu/runs results/cpu/weights)"
    if sys.argv[1:2] in (["-h"], ["--help"]):
        print(usage)
        sys.exit(0)
    if len(sys.argv) != 3:
        sys.exit(usage)
    main(*sys.argv[1:3])

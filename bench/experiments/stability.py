"""`+experiment=stability`: numerical stability of every model on stiff and extreme inputs.

Each named case perturbs a clean validation sequence (or replaces it) and is run through every model
(proposed, baselines, non-learned rows) in evaluation, with and without the input sanitation
(bench.sanitize, which the trainer and evaluator always apply), and, for learned models, through one
training step (gradients and updated weights must be finite). A case passes when the output is finite
or the model refuses the input with a clear error, and, where a case has a reference to judge it by, right
(`status`: scaled scenes, a lamp far above the frame's exposure, black frames). Special cases: sizes, 1- and 100-frame sequences
(recurrent state must not drift or blow up), bf16 autocast (fp16 on GPU), deformable offsets driven to
+-1e3, a few training steps at 10x the learning rate (divergence must be detected, never silent NaN
weights), and the metrics' own edge cases.

Writes `<results_dir>/stability/table.csv` (one row per case and model) and `table.md` (case x model:
"ok" with max |output|, or what failed).
"""
from __future__ import annotations

import copy
import dataclasses
import logging
import math
import tempfile

import pandas as pd
import torch
import torch.nn.functional as F

from bench.evaluate import predict
from bench.experiments.context import Context, model_config, training_splits, with_training, working_split
from bench.experiments.datasets import dataset, ensure_data
from bench.experiments.training import trained_model
from bench.exposure import NAMES, decode, encode, frame_exposure
from bench.measure import time_call
from bench.metrics import psnr, relmse, ssim
from bench.models.factory import is_learned
from bench.nn import DeformConv2d
from bench.table_writer import write_table
from bench.tasks import get_task
from bench.train import TrainingDiverged, batch_loss, train

log = logging.getLogger("bench")
def stability_loss(ctx: Context) -> dict:
    """The preset's loss weights without the perceptual term (the cases need no VGG16 weights)."""
    return {stage: {**weights, "perceptual": 0} for stage, weights in ctx.train.loss.items()}


def _pixels(x, fraction=0.002, seed=0):
    """A fixed random mask of about `fraction` of the pixels (at least 3), shaped (..., 1, H, W)."""
    gen = torch.Generator().manual_seed(seed)
    mask = torch.rand(*x.shape[:-3], 1, *x.shape[-2:], generator=gen) < fraction
    mask.view(-1)[:3] = True
    return mask


def _set(t, channels, value, seed=0):
    """A copy of t with `value` written into `channels` at a few fixed pixels."""
    t = t.clone()
    t[..., channels, :, :].masked_fill_(_pixels(t, seed=seed), value)
    return t


ALL, ALBEDO, NORMAL, ROUGH = slice(0, 3), slice(0, 3), slice(3, 6), slice(6, 7)

# name -> (x, g) -> (x, g), on linear radiance and the raw gBuffer
INPUT_CASES = {
    "clean": lambda x, g: (x, g),
    "firefly 1e3": lambda x, g: (_set(x, ALL, 1e3), g),
    "firefly 1e4": lambda x, g: (_set(x, ALL, 1e4), g),
    "firefly 1e6": lambda x, g: (_set(x, ALL, 1e6), g),
    "NaN radiance": lambda x, g: (_set(x, ALL, math.nan), g),
    "+Inf radiance": lambda x, g: (_set(x, ALL, math.inf), g),
    "-Inf radiance": lambda x, g: (_set(x, ALL, -math.inf), g),
    "NaN albedo": lambda x, g: (x, _set(g, ALBEDO, math.nan)),
    "+Inf albedo": lambda x, g: (x, _set(g, ALBEDO, math.inf)),
    "NaN normal": lambda x, g: (x, _set(g, NORMAL, math.nan)),
    "-Inf normal": lambda x, g: (x, _set(g, NORMAL, -math.inf)),
    "NaN roughness": lambda x, g: (x, _set(g, ROUGH, math.nan)),
    "+Inf roughness": lambda x, g: (x, _set(g, ROUGH, math.inf)),
    "all-black frame": lambda x, g: (torch.zeros_like(x), g),
    "constant frame": lambda x, g: (torch.full_like(x, 0.5), g),
    "zero albedo": lambda x, g: (x, torch.cat([torch.zeros_like(g[..., ALBEDO, :, :]), g[..., 3:, :, :]], -3)),
    "zero-length normals": lambda x, g: (x, torch.cat([g[..., :3, :, :], torch.zeros_like(g[..., NORMAL, :, :]),
                                                       g[..., 6:, :, :]], -3)),
    "non-unit normals (x5)": lambda x, g: (x, torch.cat([g[..., :3, :, :], 5 * g[..., NORMAL, :, :],
                                                         g[..., 6:, :, :]], -3)),
    "roughness -1 and 5": lambda x, g: (x, _set(_set(g, ROUGH, -1.0, seed=1), ROUGH, 5.0, seed=2)),
}
# The same scene k times brighter or darker: judged against the reference k times brighter or darker.
SCALES = {"HDR scale 1e-6": 1e-6, "HDR scale 1e-4": 1e-4, "HDR scale 1e-2": 1e-2, "HDR scale 1e2": 1e2,
          "HDR scale 1e4": 1e4}
INPUT_CASES.update({case: (lambda k: lambda x, g: (x * k, g))(k) for case, k in SCALES.items()})
# An emitter seen directly: a noise-free block (a quarter of the frame's height and width, on the LR grid)
# at k times the exposure of the frame without it, in the input and the reference alike. The scaled scenes
# above move the whole frame, which the exposure domain divides out; a lamp raises the exposure a few times
# at most (it is a few of the blocks averaged), so the network sees radiance far above what it trained on.
# Judged, for every model, by the energy it returns on the lamp's pixels ("lamp energy").
LAMPS = {"lamp 1e2x the exposure": 1e2, "lamp 1e4x the exposure": 1e4}
RELMSE_FACTOR = 2.0      # a scaled case passes within this factor of the unscaled case's relMSE to its reference
ENERGY_TOLERANCE = 0.10  # a learned model returns the energy above the domain's training range within 10%
BLACK_MAX = 1e-6         # an all-black input gives at most this radiance

SIZES = {"size 1x1": (1, 1), "size 13x7 (odd)": (13, 7), "size 33x17 (not a multiple of 32)": (33, 17),
         "size 4x200 (wide strip)": (4, 200)}


def _lamp(x, ref, k, scale):
    """(x, ref, the lamp's pixels in ref, its radiance): LAMPS' emitter at k times the exposure of x's
    first frame, on LR rows h/4..h/2 and columns w/2..3w/4 and the HR pixels they cover."""
    level = k * float(frame_exposure(x[:, :1], "exposure").flatten()[0])
    h, w = x.shape[-2:]
    rows, cols = slice(h // 4, h // 2), slice(w // 2, 3 * w // 4)
    hr_rows, hr_cols = slice(scale * rows.start, scale * rows.stop), slice(scale * cols.start, scale * cols.stop)
    x, ref, on_lamp = x.clone(), ref.clone(), torch.zeros_like(ref, dtype=torch.bool)
    x[..., rows, cols] = level
    ref[..., hr_rows, hr_cols] = level
    on_lamp[..., hr_rows, hr_cols] = True
    return x, ref, on_lamp, level


def _resize(t, hw):
    return F.interpolate(t.flatten(0, 1), size=hw, mode="nearest").unflatten(0, t.shape[:2])


def _finite(t) -> bool:
    return bool(torch.isfinite(t).all())


def _eval_row(model, x, g, hdr, ref=None, clean=None, sanitize=True, above=math.inf, scale=None,
              on_lamp=None) -> dict:
    """A case through the model: finite, its largest output, time, and its relMSE against `ref` and
    against the clean case's output; where `ref` holds radiance over `above` (the network domain's
    ceiling), the share of that energy the output returns on those pixels. `scale`: the case is the
    scene times `scale` (and `ref` too): also the relMSE of the output divided by `scale` against the
    unscaled reference, which the unscaled case's relMSE is compared with (relMSE's epsilon is not
    scale-free: on the scaled images themselves a linear method's relMSE grows with the scale).
    `on_lamp`: the pixels of a lamp case's emitter; the share of its energy the output returns."""
    try:
        timed = time_call(lambda: predict(model, x, g, hdr, sanitize=sanitize), "cpu", repeats=1, warmup=0)
        out, ms = timed["result"], timed["ms"]
    except Exception as err:  # recorded; `status` tells a refusal from a crash by its type
        return {"finite": False, "error": f"{type(err).__name__}: {err}"[:200]}
    row = {"finite": _finite(out), "max |output|": float(out.abs().nan_to_num(math.inf).max()), "time_ms": ms}
    if row["finite"] and ref is not None and ref.shape == out.shape:
        row["relMSE vs reference"] = float(relmse(out.flatten(0, 1), ref.flatten(0, 1)).mean())
    if row["finite"] and clean is not None and clean.shape == out.shape:
        row["relMSE vs clean case"] = float(relmse(out.flatten(0, 1), clean.flatten(0, 1)).mean())
    if row["finite"] and scale is not None and ref is not None and ref.shape == out.shape:
        row["relMSE at unit scale"] = float(relmse((out / scale).flatten(0, 1), (ref / scale).flatten(0, 1)).mean())
    if row["finite"] and ref is not None and ref.shape == out.shape and bool((ref > above).any()):
        bright = ref > above
        row["energy above range"] = float(out[bright].sum() / ref[bright].sum())
    if row["finite"] and on_lamp is not None and on_lamp.shape == out.shape:
        row["lamp energy"] = float(out[on_lamp].sum() / ref[on_lamp].sum())
    return row


def _train_step_row(model, batch, task, hdr, loss_weights: dict, lr: float) -> dict:
    """One Adam step on a copy of `model`: are the loss, the gradients and the new weights finite?"""
    model = copy.deepcopy(model).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    try:
        loss, _ = batch_loss(model, batch, task, loss_weights, hdr)
        loss.backward()
    except Exception as err:
        return {"train step": f"error: {type(err).__name__}: {err}"[:200]}
    grads_ok = all(p.grad is None or _finite(p.grad) for p in model.parameters())
    optimizer.step()
    weights_ok = all(_finite(p) for p in model.parameters())
    ok = _finite(loss) and grads_ok and weights_ok
    return {"train step": "ok" if ok else f"non-finite (loss {_finite(loss)}, grads {grads_ok}, weights {weights_ok})"}


def _deform_rows(model, x, g, hdr) -> list[dict]:
    """Offsets driven to +-1e3 (sampling far outside the image): finite output and gradients."""
    rows = []
    for value in (1e3, -1e3):
        m = copy.deepcopy(model).train()
        layers = [mod for mod in m.modules() if isinstance(mod, DeformConv2d)]
        with torch.no_grad():
            for layer in layers:
                layer.offset_conv.bias.fill_(value)
        out = m(encode(x, hdr, frame_exposure(x, hdr)), g)["final"]
        out.square().mean().backward()
        grads = all(p.grad is None or _finite(p.grad) for p in m.parameters())
        offset_grads = all(_finite(layer.offset_conv.bias.grad) for layer in layers if layer.offset_conv.bias.grad is not None)
        rows.append({"case": f"deform offsets {value:+.0e}", "finite": _finite(out) and grads and offset_grads,
                     "max |output|": float(out.detach().abs().max()),
                     "train step": "ok" if grads and offset_grads else "non-finite gradients"})
    return rows


def _high_lr_row(ctx: Context, model, task, hdr, factor=10.0, steps=5) -> dict:
    """A few real training steps at `factor` x the learning rate: finite weights, or divergence detected."""
    m = copy.deepcopy(model)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            base = ctx.train
            recipe = dataclasses.replace(base, steps=steps, loss=stability_loss(ctx), lr=factor * base.lr, hdr=hdr,
                                         warmup=0, clip_grad_norm=None, checkpoint_every=steps)
            train(m, dataset(ctx, "train", task, training=True), task, tmp, recipe, device="cpu", progress=False)
        except TrainingDiverged as err:
            return {"case": f"train at {factor:g}x lr", "finite": True, "train step": f"divergence detected: {err}"[:200]}
    ok = all(_finite(p) for p in m.parameters())
    return {"case": f"train at {factor:g}x lr", "finite": ok, "train step": "ok" if ok else "SILENT NaN WEIGHTS"}


def metric_rows() -> list[dict]:
    """The metrics' edge cases: zero reference, identical images, constant images."""
    zero, img = torch.zeros(1, 3, 16, 16), torch.rand(1, 3, 16, 16)
    const_a, const_b = torch.full((1, 3, 16, 16), 0.3), torch.full((1, 3, 16, 16), 0.7)
    checks = {
        "relMSE, reference all zero (uses eps)": float(relmse(img, zero)),
        "PSNR, identical images (inf)": float(psnr(img, img)),
        "SSIM, identical constant images": float(ssim(const_a, const_a)),
        "SSIM, different constant images": float(ssim(const_a, const_b)),
    }
    expected = {"PSNR, identical images (inf)": math.inf, "SSIM, identical constant images": 1.0}
    rows = []
    for case, value in checks.items():
        ok = value == expected[case] if case in expected else math.isfinite(value)
        rows.append({"case": case, "model": "metrics", "finite": ok, "max |output|": value})
    return rows


def model_rows(ctx: Context, name: str, seed: int, frames: int, long_frames: int) -> list[dict]:
    task = get_task("srd")
    cfg = model_config(ctx, name)
    ctx = with_training(ctx, None, name)
    model, _ = trained_model(ctx, cfg, task, seed, f"{name} (stability)")
    model.eval()
    hdr = ctx.train.hdr
    item = dataset(ctx, working_split(ctx), task, training=False)[0]
    x0, g0, ref = (item[k][None, :frames] for k in (task.x, task.g, task.y))
    clean = predict(model, x0, g0, hdr)
    rows = []
    above = output_ceiling(hdr) if is_learned(model) else math.inf  # the energy rule is the learned models'
    for case, make in INPUT_CASES.items():
        x, g = make(x0, g0)
        scale_ref = ref * SCALES.get(case, 1)
        row = {"case": case, **_eval_row(model, x, g, hdr, scale_ref, None if case in SCALES else clean,
                                         above=above, scale=SCALES.get(case))}
        row["finite without sanitation"] = _eval_row(model, x, g, hdr, sanitize=False).get("finite", False)
        if is_learned(model):
            mid = _resize(ref, (2 * x.shape[-2], 2 * x.shape[-1]))
            batch = {"lr_noisy": x, "lr_gbuf": g, "hr_ref": scale_ref, "hr_noisy": mid}
            row.update(_train_step_row(model, batch, task, hdr, stability_loss(ctx), ctx.train.lr))
        rows.append(row)
    for case, k in LAMPS.items():   # every model: a method on linear radiance returns the lamp too
        x, lamp_ref, on_lamp, level = _lamp(x0, ref, k, task.scale)
        rows.append({"case": case, **_eval_row(model, x, g0, hdr, lamp_ref, on_lamp=on_lamp),
                     "note": f"lamp radiance {level:.3g}"})
    for case, hw in SIZES.items():
        x, g = _resize(x0[:, :2], hw), _resize(g0[:, :2], hw)
        row = {"case": case, **_eval_row(model, x, g, hdr)}
        if row.get("finite"):
            shape = tuple(predict(model, x, g, hdr).shape[-2:])
            if shape != (2 * hw[0], 2 * hw[1]):
                row.update(finite=False, error=f"output size {shape} for input {hw}")
        rows.append(row)
    rows.append({"case": "sequence of 1 frame", **_eval_row(model, x0[:, :1], g0[:, :1], hdr, ref[:, :1])})
    reps = -(-long_frames // x0.shape[1])
    x_long, g_long = x0.repeat(1, reps, 1, 1, 1)[:, :long_frames], g0.repeat(1, reps, 1, 1, 1)[:, :long_frames]
    row = {"case": f"sequence of {long_frames} frames", **_eval_row(model, x_long, g_long, hdr)}
    if row.get("finite"):  # drift: the last frame against the same input frame one cycle after the start
        out = predict(model, x_long, g_long, hdr)
        t_last = long_frames - 1
        t_early = t_last % x0.shape[1] + x0.shape[1]
        row["relMSE vs clean case"] = float(relmse(out[0, t_last], out[0, t_early]).mean())
        row["note"] = f"relMSE vs clean case = drift of frame {t_last} against frame {t_early} (same input)"
    rows.append(row)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        rows.append({"case": "bf16 autocast (CPU)", **_eval_row(model, x0, g0, hdr, ref, clean)})
    if torch.cuda.is_available():
        gpu = copy.deepcopy(model).cuda()
        with torch.autocast("cuda", dtype=torch.float16):
            row = _eval_row(gpu, x0.cuda(), g0.cuda(), hdr)
        rows.append({"case": "fp16 autocast (GPU)", **row})
    if any(isinstance(m, DeformConv2d) for m in model.modules()):
        rows += _deform_rows(model, x0, g0, hdr)
    if is_learned(model):
        rows.append(_high_lr_row(ctx, model, task, hdr))
    return [{"model": name, **r} for r in rows]


def _number(row, key) -> float | None:
    value = row.get(key)
    return float(value) if isinstance(value, (int, float)) and not math.isnan(value) else None


# the exceptions a model or the input checks raise on purpose, with a message saying what is refused
REFUSALS = ("UserError", "ValueError")


def status(row, clean_relmse: float | None = None) -> str:
    """The Markdown cell of a row: "ok" + max |output|, "error (clear)", or FAIL with its reason. Finite is
    necessary, not sufficient: a case of the scene scaled by k passes when its relMSE to the reference
    scaled by k is within RELMSE_FACTOR of the unscaled case's (`clean_relmse`), and a learned model's
    output returns the energy above its domain's ceiling within ENERGY_TOLERANCE, as every model does the
    energy of a lamp case's emitter; an all-black input gives at most BLACK_MAX."""
    error = row.get("error")
    if isinstance(error, str):  # a refusal with a message is an acceptable outcome, any other error is not
        first_line = error.splitlines()[0].replace("|", "/")[:80] if error.strip() else "error"  # a Markdown cell
        return "error (clear)" if error.split(":")[0] in REFUSALS else f"FAIL ({first_line})"
    train = row.get("train step")
    bad_train = isinstance(train, str) and not (train == "ok" or train.startswith("divergence detected"))
    if not row.get("finite") or bad_train:
        return "FAIL" + (f" ({train})" if bad_train else "")
    value, relmse_k, energy, lamp = (_number(row, k) for k in ("max |output|", "relMSE at unit scale",
                                                               "energy above range", "lamp energy"))
    if row.get("case") == "all-black frame" and value is not None and value > BLACK_MAX:
        return f"FAIL (black in, {value:.2g} out)"
    if row.get("case") in SCALES and (relmse_k is None or clean_relmse is None):
        return "not judged" + (f" {value:.3g}" if value is not None else "")  # measured before the rule
    if row.get("case") in SCALES and relmse_k > RELMSE_FACTOR * clean_relmse:
        return f"FAIL (relMSE {relmse_k:.3g}, unscaled {clean_relmse:.3g})"
    if energy is not None and abs(energy - 1) > ENERGY_TOLERANCE:
        return f"FAIL (energy above range {energy:.0%})"
    if lamp is not None and abs(lamp - 1) > ENERGY_TOLERANCE:
        return f"FAIL (lamp energy {lamp:.0%})"
    return "ok" + (f" {value:.3g}" if value is not None else "")


def statuses(table: pd.DataFrame) -> list[str]:
    """`status` of every row, each judged against its own model's clean case."""
    clean = {r["model"]: _number(r, "relMSE vs reference") for r in table.to_dict("records") if r["case"] == "clean"}
    return [status(r, clean.get(r["model"])) for r in table.to_dict("records")]


def output_ceiling(hdr: str) -> float:
    """The largest linear radiance a learned model can output through the network domain `hdr`: what the
    inverse transform gives for the brightest input (inf where nothing saturates)."""
    if frame_exposure(torch.ones(1, 3, 1, 1), hdr) is not None:  # the output scales with the frame's exposure
        return math.inf
    top = float(decode(encode(torch.tensor([1e30], dtype=torch.float64), hdr, None), hdr, None)[0])
    return top if top < 1e29 else math.inf




def _firefly_level(case: str) -> float:
    return float(case.split()[-1])


def range_note(table: pd.DataFrame, hdr: str) -> str:
    """What the network domain's ceiling clips, told from the table's rows: each learned model's output on the
    brightest firefly case (learned: the models with a training-step row) against the methods that work on
    linear radiance."""
    ceiling, domain = output_ceiling(hdr), f"{NAMES[hdr]} network domain (train.hdr={hdr}"
    if math.isinf(ceiling):
        return f"Learned models work in the {domain}), which has no ceiling."
    fireflies = [c for c in table["case"].unique() if str(c).startswith("firefly ")]
    head = (f"Learned models work in the {domain}, bench/hdr.py), whose inverse saturates "
            f"at radiance {ceiling:.3g}: their outputs are capped there, so any pixel brighter than {ceiling:.3g} is "
            f"clipped by construction (a scene brighter than that cannot be reproduced).")
    if not fireflies:
        return head
    case = max(fireflies, key=_firefly_level)
    rows = table[table["case"] == case].set_index("model")["max |output|"].astype(float)
    learned = set(table.loc[table["train step"].notna(), "model"])
    shown = lambda models: ", ".join(f"{m} {rows[m]:.3g}" for m in rows.index if (m in learned) == models)
    return (f"{head} On '{case}' (pixels set to radiance {_firefly_level(case):g}) the learned models give "
            f"{shown(True)}; the methods on linear radiance give {shown(False)}.")


def caption(table: pd.DataFrame, preset: str, device: str, hdr: str) -> str:
    energy = ("" if "relMSE at unit scale" in table else " ('not judged': this table.csv was measured before "
              "these two rules, and the next run of the experiment measures what they need)")
    lamps = (f"'lamp kx the exposure' (a noise-free emitter block at k times the exposure of the frame without "
             f"it, in the input and the reference) passes when the model returns the lamp's energy within "
             f"{ENERGY_TOLERANCE:.0%} (every model), " if table["case"].isin(list(LAMPS)).any() else "")
    return (f"Stability at preset {preset} on {device}: each case through each model (trained at this "
            f"preset), inputs sanitized (bench.sanitize). 'ok' + max |output| (linear radiance); 'error "
            f"(clear)': the model refused with a message ({' or '.join(REFUSALS)}); FAIL: any other error, "
            f"non-finite output, gradients or weights, or a "
            f"case judged against its reference: 'HDR scale k' passes when its output divided by k has a relMSE "
            f"to the reference within {RELMSE_FACTOR:g}x the unscaled case's, a learned model's output returns the energy "
            f"above its network domain's ceiling within {ENERGY_TOLERANCE:.0%}{energy}, {lamps}and an all-black "
            f"input gives at most {BLACK_MAX:g}. {range_note(table, hdr)} Per-row details (relMSE vs reference "
            f"and vs the clean case, energy above range, lamp energy, time, the same case without sanitation, "
            f"training step) in table.csv.")


def write_tables(table: pd.DataFrame, out_dir, preset: str, device: str, hdr: str) -> None:
    """table.md/.tex (case x model) and table.csv (the long form, one row per case and model)."""
    pivot = table.pivot_table(index="case", columns="model", values="status", aggfunc="first", sort=False).fillna("")
    write_table(pivot.reset_index(), out_dir, caption=caption(table, preset, device, hdr), csv_table=table)


def run(ctx: Context, name: str, models: list[str], frames: int, long_frames: int,
        from_csv: bool = False) -> pd.DataFrame:
    """conf/experiment/stability.yaml says what each argument is. from_csv: rewrite table.md/.tex from the
    recorded table.csv (its rows unchanged, no case run): a caption change without retraining."""
    out_dir = ctx.results_dir / name
    if from_csv:
        table = pd.read_csv(out_dir / "table.csv")
        table["status"] = statuses(table)  # the verdicts, by today's rules, from the recorded measurements
        write_tables(table, out_dir, ctx.preset, ctx.device, ctx.train.hdr)
        log.info("stability: table.md/.tex and the verdicts rewritten from the recorded %s", out_dir / "table.csv")
        return table
    ensure_data(ctx, set(get_task("srd").buffers(with_mid=True)), training_splits(ctx))
    rows = []
    for model_name in models:
        log.info("stability: %s", model_name)
        rows += model_rows(ctx, model_name, ctx.seeds[0], frames, long_frames)
    rows += metric_rows()
    table = pd.DataFrame(rows)
    table["status"] = statuses(table)
    write_tables(table, out_dir, ctx.preset, ctx.device, ctx.train.hdr)
    failures = table[table["status"].str.startswith("FAIL")]
    for r in failures.to_dict("records"):
        log.warning("stability: %s on %s: %s", r["case"], r["model"], r["status"])
    log.info("stability: %d of %d cases pass; table in %s", len(table) - len(failures), len(table), out_dir)
    return table

"""`+experiment=time`: error against run time on this machine, the trade-off behind the paper's claim that
rendering at low resolution and low spp and running SRD beats path tracing the HR image for longer.

For a few validation views (the last frame of the first `views` val sequences, scored against that
frame's `hr_ref` from the dataset) it measures:

- brute force: HR path tracing at 1, 2, 4, ... spp up to half the reference's spp;
- HR at low spp + a denoiser (methods with task `denoise`: OIDN, the RAE trained on the denoise task);
- LR at 1..16 spp + each SRD method (task `srd`); the networks were trained at the dataset's spp (8), so
  the other spp show how they degrade off their operating point.

Total time per frame = render time (radiance and gBuffer in one pass, as the dataset is rendered;
`render_view`'s wall time on an already loaded scene after a warm-up render, so neither scene loading nor
Mitsuba's JIT compilation counts) + network time (median of `repeats` warm runs, per frame). Recurrent
models were trained and scored on sequences, so every input is rendered for each frame of the view's
sequence, the render time is the mean over those frames, and the error is taken on the last frame.

Derived per method (bench/experiments/time_curves.py): the equal-quality speed-up (the time brute-force path tracing needs to reach the
method's relMSE, PSNR or SSIM on its fitted curve, divided by the method's time) and, at the operating
point, path tracing's values at the method's total time (speedup.*); and the paper's head-to-head, SRD at
LR 8 spp against the denoisers of HR renders at equal time (equal_time.*). Every point carries the
standard error over views; path tracing's curve is checked for slope (about 1/spp) and for rising with
more samples beyond noise (paired over views).

The paper-resolution step (`paper_resolution`, on by default) gives the equal-time table again on render
times at 960x540 / 1920x1080 and the networks' 1080p times (issue 43, item 7: at the cpu preset's sizes fixed
costs decide it). Only the seconds change: the quality axis stays the cpu preset's, read from the time table
(`table.csv`) the cpu-size part wrote, or the committed one with `only=true`.

Renders: the last `frames` frames of the time table's views (the first `views` val sequences in the
loader's order, planned from the data spec, so no dataset is read), at LR `operating_spp` and at each HR
spp of the table, radiance and gBuffer in one pass, JIT warmed first. Each is a run of kind `time` that
records wall seconds, the process CPU seconds of the render (every render thread) and the 1-minute load
average; no image is kept. The axis takes CPU seconds / render threads as a render's seconds (other work on
a shared host stretches wall time, not CPU time); a second verdict column uses wall seconds.

Network seconds per frame come from the speed table (`<results_dir>/speed/<machine>/table.csv`, fp32 rows
at these sizes) where it has the method; the others are measured here on random inputs (median of
`repeats` warm calls, untrained weights: time does not depend on them).

Renders are runs of kind `time`, keyed by view, size, spp, passes, seed, Mitsuba variant and host, so
a rerun re-renders nothing and a time measured on another machine is never reused. force=true re-renders
and re-times them; it never retrains networks here (run the tables with force=true for that). Network
times are measured afresh on every run.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench import render, runs, scenes
from bench.datagen import derive_seed, frame_view, plan_sequences, render_settings
from bench.dataset import SequenceDataset
from bench.errors import UserError
from bench.evaluate import predict
from bench.experiments.context import Context, model_config, with_training
from bench.experiments.datasets import ensure_data
from bench.experiments.speed import LABELS
from bench.experiments.table import domain_note
from bench.experiments.time_curves import (BRUTE_FORCE, EXPECTED_SLOPE, SPEEDUP_COLUMNS, add_speedups, average,
                                           brute_force_spp, equal_time_table, loglog_slope, plot,
                                           reference_noise_slope, rising_steps, slope_ok, speedup_table)
from bench.experiments.training import trained_model, training_records, untrained, working_split
from bench.machine import cpu_isa, cpu_model, device_tag, gpu_model
from bench.measure import time_call
from bench.metrics import HIGHER_IS_BETTER, LOWER_IS_BETTER, METRICS, RELMSE_FORMULA, mse
from bench.models.factory import build_model, is_learned
from bench.table_writer import write_table
from bench.tasks import GBUF_LAYERS, get_task

log = logging.getLogger("bench")

RUN_KIND = "time"                           # the renders' runs: runs/time/<hash>, named as the experiment
INPUT_RES = {"srd": "lr", "denoise": "hr"}  # a method's task -> the resolution it renders its input at
PAPER_SPEEDUP = 4                           # what the paper implies at LR 8 spp


# ---------------------------------------------------------------- views and renders

@dataclass
class View:
    """One validation sequence; its last frame is scored against `ref` (3, H, W), the dataset's hr_ref."""
    sequence: str
    frames: list
    scene: object
    gbuf_layers: list
    max_depth: int
    ref: torch.Tensor


def pick_views(ctx: Context, count: int, split: str = "val") -> list[View]:
    """The first `count` sequences of `split` (in the loader's order), fewer when the split has fewer."""
    data = SequenceDataset(ctx.data_dir, split, ["hr_ref"])
    views = []
    for index, (name, records) in enumerate(list(data.sequences.items())[:count]):
        scene, _, layers, depth = frame_view(records[-1])
        views.append(View(name, records, scene, layers, depth, data.item(index, 0)["hr_ref"][-1]))
    return views


class Renderer:
    """Renders frames of one view, loading its scene once and warming Mitsuba's JIT once per image size
    and set of passes (Dr.Jit bakes both into its kernels; the first render of each costs about 0.5 s of
    compilation whatever the spp): the timed render then measures path tracing, not compilation."""

    def __init__(self, view: View, variant: str):
        self.view, self.variant = view, variant
        self._scene, self._warm = None, set()

    def warm_up(self, camera, width: int, height: int, passes: list) -> None:
        if self._scene is None:
            self._scene = render.load_scene(self.view.scene, self.variant)
        key = (width, height, tuple(passes))
        if key not in self._warm:
            render.render_view(self._scene, camera, width, height, 1, 0, passes, max_depth=self.view.max_depth)
            self._warm.add(key)

    def __call__(self, camera, width: int, height: int, spp: int, seed: int, passes: list) -> dict:
        self.warm_up(camera, width, height, passes)
        return render.render_view(self._scene, camera, width, height, spp, seed, passes,
                                  max_depth=self.view.max_depth)


def gbuffer_tensor(out: dict, layers: list) -> torch.Tensor:
    """The 7-channel gBuffer (albedo, normal, roughness) of a render as (7, H, W); a left-out roughness
    is the constant 1, as the dataset loader supplies it."""
    h, w = out["radiance"].shape[:2]
    planes = [out[name] if name in layers else np.ones((h, w, 1), np.float32) for name in GBUF_LAYERS]
    return torch.from_numpy(np.concatenate(planes, -1).transpose(2, 0, 1).copy())


def cached_render(ctx: Context, view: View, renderer: Renderer, frame: int, res: str, spp: int,
                  gbuffer: bool, stats: dict) -> dict:
    """One frame at `res` ('lr'/'hr') and `spp`, from the run store when recorded; returns radiance
    (3, H, W), gbuf (7, H, W) or None, and render_s (wall seconds of that render on this host)."""
    record = view.frames[frame]
    width, height = record[f"{res}_size"]
    passes = list(view.gbuf_layers) if gbuffer else []
    seed = derive_seed(ctx.data_spec["seed"], "timing", record["scene"], record["view"], record["frame"],
                       res, spp, int(gbuffer))
    identity = {"scene": record["scene"], "sequence": record["sequence"], "frame": record["frame"],
                "camera": record.get("camera"), "size": [width, height], "spp": spp, "seed": seed,
                "passes": passes, "max_depth": view.max_depth, "variant": renderer.variant,
                "host": socket.gethostname()}
    run = runs.begin(ctx.runs_dir, RUN_KIND, identity, seed=seed, device=_render_device(renderer.variant),
                     label=f"render {record['sequence']}/{record['frame']} {res} {spp} spp", force=ctx.force,
                     code=runs.code_fingerprint(["bench.render"]), reuse_stale=ctx.reuse_stale)
    stats["renders"] += 1
    if run.reused:
        stats["reused"] += 1
        with np.load(run.dir / "render.npz") as saved:
            gbuf = torch.from_numpy(saved["gbuf"]) if gbuffer else None
            return {"radiance": torch.from_numpy(saved["radiance"]), "gbuf": gbuf,
                    "render_s": run.metrics["render_s"]}
    out = renderer(record.get("camera"), width, height, spp, seed, passes)
    radiance, repaired = render.repair_nonfinite(out["radiance"])
    for name in passes:
        out[name], count = render.repair_nonfinite(out[name])
        repaired += count
    result = {"radiance": torch.from_numpy(radiance.transpose(2, 0, 1).copy()),
              "gbuf": gbuffer_tensor(out, passes) if gbuffer else None, "render_s": out["wall_time_s"]}
    arrays = {"radiance": result["radiance"].numpy()}
    if gbuffer:
        arrays["gbuf"] = result["gbuf"].numpy()
    np.savez(run.dir / "render.npz", **arrays)
    runs.complete(run, {"render_s": out["wall_time_s"], "nonfinite_repaired": repaired})
    return result


def _render_device(variant: str) -> str:
    return "cuda" if variant.startswith("cuda") else "cpu"


def input_sequence(ctx, view, renderer, res, spp, stats) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Radiance and gBuffer of every frame of the view at (res, spp) as (1, T, C, h, w) tensors, and the
    mean render seconds per frame."""
    frames = [cached_render(ctx, view, renderer, i, res, spp, True, stats) for i in range(len(view.frames))]
    x = torch.stack([f["radiance"] for f in frames])[None]
    g = torch.stack([f["gbuf"] for f in frames])[None]
    return x, g, float(np.mean([f["render_s"] for f in frames]))


# ---------------------------------------------------------------- methods

def resolve_method(ctx: Context, method: dict, train_missing: bool):
    """The model ready to run, or None to skip the method: a learned model comes from its recorded
    training run, and is trained here only when `train_missing` (training is the tables' job)."""
    task = get_task(method["task"])
    cfg = model_config(ctx, method["model"], method.get("overrides"))
    ctx = with_training(ctx, None, method["model"])
    seed = ctx.seeds[0]
    if not is_learned(build_model(cfg, task.scale)):
        return build_model(cfg, task.scale)
    whys = untrained(training_records(ctx, cfg, task, seed))  # recorded, with weights, by this code?
    if not train_missing and whys:
        log.warning("time: %s skipped: its %s-task training at preset %s would run here (%s; train it with "
                    "its table, e.g. sota or sr_denoise, or set experiment.train_missing=true)", method["label"],
                    task.name, ctx.preset, "; ".join(whys))
        return None
    model, _ = trained_model(dataclasses.replace(ctx, force=False), cfg, task, seed, method["label"])
    return model.to(ctx.device).eval()


def network_device(ctx: Context, model) -> str:
    """Where and in what precision the method's network runs (OIDN runs in pyoidn, on the CPU)."""
    if getattr(model, "linear_hdr", False):
        return "cpu fp32 (pyoidn)"
    return f"{ctx.device} fp32" + (f", {torch.get_num_threads()} threads" if ctx.device == "cpu" else "")


@torch.no_grad()
def timed_prediction(model, x, g, hdr: str, device: str, repeats: int) -> tuple[torch.Tensor, float]:
    """(last frame of the prediction (3, H, W), median seconds per frame over `repeats` warm runs).
    A recurrent model sees the whole sequence (time per frame = sequence time / T); any other model only
    the last frame, so its time is one frame's latency."""
    if not getattr(model, "recurrent", False):
        x, g = x[:, -1:], g[:, -1:]
    x, g = x.to(device), g.to(device)
    # one untimed call first: first-call allocation is not inference time
    timed = time_call(lambda: predict(model, x, g, hdr), device, repeats=repeats, warmup=1)
    return timed["result"][0, -1].float().cpu(), timed["ms"] / 1000 / x.shape[1]


def scores(pred: torch.Tensor, ref: torch.Tensor) -> dict:
    """The per-image metrics of one frame (a single frame has no temporal one)."""
    out = {name: float(fn(pred[None], ref[None])[0]) for name, fn in METRICS.items()}
    out["MSE"] = float(mse(pred[None], ref[None])[0])
    return out


# ---------------------------------------------------------------- measuring one view

def measure_view(ctx: Context, view: View, variant: str, methods: list, bf_spp: list, spp_lists: dict,
                 repeats: int, stats: dict) -> list[dict]:
    """Rows (method, spp, render s, network s, metrics) of one view."""
    renderer, rows = Renderer(view, variant), []
    last = len(view.frames) - 1
    for spp in bf_spp:
        out = cached_render(ctx, view, renderer, last, "hr", spp, False, stats)
        rows.append({"view": view.sequence, "method": BRUTE_FORCE, "input": "HR", "spp": spp, "render s": out["render_s"],
                     "network s": 0.0, "network on": "-", **scores(out["radiance"], view.ref)})
    for task, res in INPUT_RES.items():
        chosen = [m for m in methods if m["task"] == task]
        for spp in (spp_lists[res] if chosen else []):
            x, g, render_s = input_sequence(ctx, view, renderer, res, spp, stats)
            for m in chosen:
                pred, network_s = timed_prediction(m["net"], x, g, ctx.train.hdr, ctx.device, repeats)
                rows.append({"view": view.sequence, "method": m["label"], "input": res.upper(), "spp": spp,
                             "render s": render_s,
                             "network s": network_s, "network on": network_device(ctx, m["net"]),
                             **scores(pred, view.ref)})
    return rows


# ---------------------------------------------------------------- the experiment


def _move_legacy_render_runs(runs_dir) -> None:
    """Render runs recorded before the run kind took the experiment's name (runs/timing) move to runs/time;
    their identities are unchanged, so they are reused."""
    legacy, current = runs_dir / "timing", runs_dir / RUN_KIND
    if legacy.is_dir() and not current.exists():
        legacy.rename(current)
        log.info("time: moved the recorded renders of %s to %s (the run kind's new name)", legacy, current)


def _methods(ctx: Context, methods: list[dict]) -> list[dict]:
    """Methods with their task (default srd), checked before anything is rendered."""
    out = []
    for m in methods:
        m = {"task": "srd", **m}
        if m["task"] not in INPUT_RES:
            raise UserError(f"time: method {m['label']!r} has task {m['task']!r}; use srd (LR input) or "
                            f"denoise (HR input)")
        model_config(ctx, m["model"], m.get("overrides"))
        out.append(m)
    return out


def _reference_spp(views: list[View]) -> int:
    """The fewest samples among the views' references: brute force stops at half of it, so that no view
    scores a render with as many samples as its reference."""
    return min(int(v.frames[-1]["ref_spp"]) for v in views)


def _data_passes(methods: list[dict], train_missing: bool) -> set[str]:
    """The reference always; the tasks' training buffers only when networks may be trained here."""
    passes = {"hr_ref"}
    if train_missing:
        for m in methods:
            passes.update(get_task(m["task"]).buffers(with_mid=True))
    return passes


def _slope_note(slope: float, flattened: float, ref_spp: int) -> str:
    text = (f"Brute-force MSE vs spp: log-log slope {slope:.2f} (expected about -1; {flattened:.2f} with the "
            f"fewest-sample reference's ({ref_spp} spp) own noise)")
    if not slope_ok(slope):
        text += (f", OUTSIDE [{EXPECTED_SLOPE[0]}, {EXPECTED_SLOPE[1]}]: fireflies or a render mismatch; "
                 f"the curves are suspect")
    return text + "."


def _skipped_note(skipped: list[str]) -> str:
    if not skipped:
        return ""
    return (f"Skipped, no recorded training run at this preset (train them with their tables or set "
            f"experiment.train_missing=true): {', '.join(skipped)}.")


def _host(device: str) -> str:
    """The machine every time here was measured on, its ISA named (bf16 is emulated without AVX512-BF16),
    and the GPU where the networks ran on one (renders and OIDN stay on the CPU)."""
    gpu = f", networks on {gpu_model(device)}" if device.startswith("cuda") else ""
    return f"host {socket.gethostname()} ({cpu_model().strip()}, {cpu_isa()}, {os.cpu_count()} CPUs{gpu})"


def _caption(ctx, caption, views, variant, train_spp) -> str:
    return (f"{caption} Preset {ctx.preset}, {len(views)} val view(s) (last frame of "
            f"{', '.join(v.sequence for v in views)}), {_host(ctx.device)}, Mitsuba {variant}. Seconds per frame, "
            f"averaged over views: render = render_view wall time (radiance + gBuffer in one pass, scene "
            f"loaded, JIT warm), network = median of warm runs. "
            f"{RELMSE_FORMULA}; PSNR/SSIM clamped to [0, 1]; all against the HR reference. Networks trained "
            f"at {train_spp} spp in the {domain_note(ctx.train.hdr, [])}. se: standard error over views. speed-up (M): seconds brute-force HR path "
            f"tracing (PT) needs for the same M on its fitted curve (see speedup.*; extrapolated: outside its "
            f"measured times) / the method's seconds; the paper implies about {PAPER_SPEEDUP}x at LR 8 spp. "
            f"Pareto: no other row is both faster and lower in relMSE.")


def run(ctx: Context, name: str, caption: str, views: int, lr_spp: list, hr_spp: list, max_spp: int | None,
        operating_spp: int, repeats: int, train_missing: bool, methods: list[dict],
        paper_resolution: dict) -> pd.DataFrame:
    """conf/experiment/time.yaml says what each argument is, and its default. Returns the cpu-size table (the
    recorded one with paper_resolution.only=true)."""
    _move_legacy_render_runs(ctx.runs_dir)
    methods = _methods(ctx, methods)
    paper = PaperResolution(**paper_resolution)
    if paper.only:
        table = pd.read_csv(ctx.results_dir / name / "table.csv") if (ctx.results_dir / name / "table.csv").exists() \
            else None
        log.info("time: paper_resolution.only=true: the cpu-size tables are left as recorded")
    else:
        table = cpu_size_tables(ctx, name, caption, views, lr_spp, hr_spp, max_spp, operating_spp, repeats,
                                train_missing, methods)
    if paper.enabled or paper.only:
        run_paper_resolution(ctx, name, views, methods, hr_spp, operating_spp, paper)
    else:
        log.info("time: the paper-resolution time axis is off (experiment.paper_resolution.enabled=false)")
    return table


def cpu_size_tables(ctx: Context, name: str, caption: str, views: int, lr_spp: list, hr_spp: list,
                    max_spp: int | None, operating_spp: int, repeats: int, train_missing: bool,
                    methods: list[dict]) -> pd.DataFrame:
    """Render, score and time at the preset's sizes; write table.*, speedup.*, equal_time.* and the figure."""
    # the views' split, and where a training may run here the splits it reads (its curve's included)
    splits = {"train", "val", working_split(ctx)} if train_missing else {"val"}
    ensure_data(ctx, _data_passes(methods, train_missing), splits)
    chosen = pick_views(ctx, int(views))
    ref_spp = _reference_spp(chosen)
    bf_spp = brute_force_spp(ref_spp, max_spp)
    if len(bf_spp) < 2:
        raise UserError(f"time: the reference has {ref_spp} spp and max_spp={max_spp}: brute force needs at "
                        f"least 1 and 2 spp")
    spp_lists = {"lr": list(lr_spp), "hr": list(hr_spp)}
    nets = {m["label"]: resolve_method(ctx, m, train_missing) for m in methods}
    kept = [{**m, "net": nets[m["label"]]} for m in methods if nets[m["label"]] is not None]
    variant = render.use_variant("cuda_ad_rgb" if ctx.device == "cuda" else None)
    stats, rows = {"renders": 0, "reused": 0}, []
    for view in chosen:
        log.info("time: view %s", view.sequence)
        rows += measure_view(ctx, view, variant, kept, bf_spp, spp_lists, repeats, stats)
    table = add_speedups(average(rows))
    skipped = [label for label, net in nets.items() if net is None]
    report(ctx, name, caption, table, pd.DataFrame(rows), chosen, variant, skipped, operating_spp)
    log.info("time: %d of %d renders reused from the run store; tables and figure in %s",
             stats["reused"], stats["renders"], ctx.results_dir / name)
    return table


def report(ctx: Context, name: str, caption: str, table: pd.DataFrame, per_view: pd.DataFrame, views: list[View],
           variant: str, skipped: list[str], operating_spp: int) -> None:
    """Check path tracing's curve (slope, monotone within noise), write table.*, speedup.*, equal_time.*
    and error_vs_time.png."""
    ref_spp, train_spp = _reference_spp(views), views[0].frames[-1]["spp"]
    bf = table[table["method"] == BRUTE_FORCE]
    slope = loglog_slope(bf["spp"], bf["MSE"])
    if not slope_ok(slope):
        log.warning("time: brute-force MSE falls as spp^%.2f, outside the expected [%g, %g] (about 1/spp)",
                    slope, *EXPECTED_SLOPE)
    rising = rising_steps(per_view[per_view["method"] == BRUTE_FORCE])
    if rising:
        log.warning("time: path tracing scores worse with more samples beyond noise at %s", rising)
    notes = " ".join(filter(None, [_slope_note(slope, reference_noise_slope(bf["spp"], ref_spp), ref_spp),
                                   _monotone_note(rising, len(views)), _skipped_note(skipped)]))
    out = ctx.results_dir / name
    shown = table.drop(columns=["MSE"]).assign(Pareto=table["Pareto"].map({True: "yes", False: ""}))
    write_table(shown, out, caption=f"{_caption(ctx, caption, views, variant, train_spp)} {notes}",
                lower_is_better=LOWER_IS_BETTER, higher_is_better=HIGHER_IS_BETTER)
    curve_text = ("PT's curves: least-squares lines through (log seconds, log relMSE), (log seconds, PSNR) and "
                  "(log seconds, log(1 - SSIM)) over all its points; extrapolated: outside its measured times.")
    write_table(speedup_table(table, operating_spp), out, name="speedup", caption=(
        f"Equal quality and equal time against brute-force HR path tracing (PT) at the operating point "
        f"({operating_spp} spp; the paper's is LR 8 spp, where it implies about {PAPER_SPEEDUP}x), preset "
        f"{ctx.preset}, {len(views)} view(s), {_host(ctx.device)}; seconds per frame; {RELMSE_FORMULA}. "
        f"speed-up at equal M: the seconds PT needs to reach the method's M, over the method's seconds; in "
        f"relMSE alone a blurred image can look fast, so PSNR and SSIM are given too. PT M at equal time: PT's "
        f"M after the method's seconds. {curve_text} {notes}"),
        lower_is_better=("relMSE",), higher_is_better=tuple(c for c in SPEEDUP_COLUMNS if c.startswith("speed-up")))
    write_table(equal_time_table(table, operating_spp), out, name="equal_time", caption=(
        f"Equal time: each SRD method at LR {operating_spp} spp against each denoiser of HR renders given the "
        f"same seconds per frame (preset {ctx.preset}, {len(views)} view(s), {_host(ctx.device)}): the "
        f"denoiser's relMSE, PSNR and FLIP read off its own curve (lines through its HR spp points, as PT's; "
        f"FLIP as relMSE, log against log time) at the SRD method's total time; HDR-FLIP difference: SRD minus "
        f"denoiser (below 0: SRD wins); extrapolated: outside the denoiser's measured times. {RELMSE_FORMULA}."),
        lower_is_better=("HDR-FLIP difference",), higher_is_better=("PSNR difference (dB)",))
    plot(table, out / "error_vs_time.png", f"Error vs time ({ctx.preset}, {len(views)} view(s))")


def _monotone_note(rising: list, views: int) -> str:
    if views < 2:
        return "Monotonicity within noise not checked (one view)."
    if not rising:
        return (f"PT's relMSE never rises with more samples beyond 2 standard errors of the paired per-view "
                f"difference ({views} views).")
    return (f"PT's relMSE RISES with more samples beyond 2 standard errors at spp {rising}: the reference or the "
            f"renders are suspect there.")


# ---------------------------------------------------------------- the paper's resolution (issue 43, item 7)


PAPER_RENDER_S = {"LR": 4.45, "HR": 19.33}  # the paper's render seconds per frame at 540p and 1080p, 8 spp
QUALITY_NOTE = (f"Its quality axis ({', '.join(METRICS)}) is still the cpu preset's, from table.csv at the preset's "
                "image size: only the seconds are the paper resolution's.")


@dataclass
class PlannedView:
    """A val sequence as the data spec plans it: what `Renderer` needs, and the cameras of its frames."""
    sequence: str
    scene: dict
    cameras: list
    gbuf_layers: list
    max_depth: int


def planned_views(spec: dict, count: int, split: str = "val") -> list[PlannedView]:
    """The first `count` sequences of `split` in the loader's order (sorted names), as the time table's views."""
    plan = sorted((p for p in plan_sequences(spec) if p["split"] == split), key=lambda p: p["sequence"])[:count]
    views = []
    for p in plan:
        scene = scenes.make_scene(p["family"], p["scene_seed"])
        features = scenes.scene_features(scene)
        settings = render_settings(spec, features, split, p["sequence"])  # the dataset's own max_depth and left-out layers
        layers = [name for name in ("albedo", "normal", "roughness") if name not in features["left_out"]]
        cameras = scenes.camera_path(p["scene_seed"], p["view"], int(spec["seq_len"]))
        views.append(PlannedView(p["sequence"], scene, cameras, layers, int(settings["max_depth"])))
    return views


def render_threads() -> int:
    """Threads Mitsuba's LLVM backend renders with (Dr.Jit's pool)."""
    import drjit
    return int(drjit.thread_count())


def timed_render(ctx: Context, view: PlannedView, renderer: Renderer, frame: int, size, spp: int,
                 threads: int, stats: dict) -> dict:
    """Wall and CPU seconds of one render at `size` (width, height), from the run store when recorded."""
    width, height = size
    seed = derive_seed(ctx.data_spec["seed"], "timing-paper-size", view.sequence, frame, width, height, spp)
    identity = {"sequence": view.sequence, "frame": frame, "camera": view.cameras[frame], "size": [width, height],
                "spp": spp, "seed": seed, "passes": view.gbuf_layers, "max_depth": view.max_depth,
                "variant": renderer.variant, "host": socket.gethostname(), "image": "not kept (times only)"}
    run = runs.begin(ctx.runs_dir, RUN_KIND, identity, seed=seed, device="cpu", force=ctx.force,
                     label=f"time render {view.sequence}/{frame} {width}x{height} {spp} spp",
                     code=runs.code_fingerprint(["bench.render"]), reuse_stale=ctx.reuse_stale)
    stats["renders"] += 1
    if run.reused:
        stats["reused"] += 1
        return run.metrics
    camera = view.cameras[frame]
    renderer.warm_up(camera, width, height, view.gbuf_layers)
    load = os.getloadavg()[0]
    cpu_start = time.process_time()
    out = renderer(camera, width, height, spp, seed, view.gbuf_layers)
    metrics = {"wall_s": out["wall_time_s"], "cpu_s": time.process_time() - cpu_start, "load_1min": load,
               "render_threads": threads}
    runs.complete(run, metrics)
    return metrics


def render_table(rows: list[dict]) -> pd.DataFrame:
    """Medians over frames per (input, size, spp): wall s, CPU s, CPU s / threads (the axis's render s)."""
    df = pd.DataFrame(rows)
    df["render s"] = df["cpu_s"] / df["render_threads"]
    groups = df.groupby(["input", "size", "spp"], sort=False)
    return pd.DataFrame({"frames": groups.size(), "wall s": groups["wall_s"].median(),
                         "CPU s": groups["cpu_s"].median(), "render s": groups["render s"].median(),
                         "CPU / wall": groups["cpu_s"].median() / groups["wall_s"].median(),
                         "load (1 min)": groups["load_1min"].median()}).reset_index()


def hr_lr_ratio(renders: pd.DataFrame, spp: int, column: str) -> float:
    """HR render seconds over LR render seconds at `spp`."""
    at = renders[renders["spp"] == spp].set_index("input")[column]
    return float(at["HR"] / at["LR"])


# ---------------------------------------------------------------- networks

def speed_ms(speed: pd.DataFrame | None, method: dict, lr_size, hr_size) -> float | None:
    """The speed table's median ms per frame for the method's network at these sizes, or None."""
    if speed is None:
        return None
    lr, hr = "x".join(map(str, lr_size)), "x".join(map(str, hr_size))
    if method["model"] == "oidn_hr":  # OIDN on the HR frame (after a bilinear upsampling for task srd)
        rows = speed[(speed["section"] == "reference") & speed["method"].str.startswith("OIDN") & (speed["size"] == hr)]
    elif method["task"] == "srd" and method["model"] in LABELS:
        rows = speed[(speed["section"] == "inference") & (speed["method"] == LABELS[method["model"]])
                     & (speed["fast path"] == "fp32") & (speed["size"] == f"{lr} -> {hr}") & (speed["per"] == "frame")]
    else:
        return None
    return float(rows["ms"].iloc[0]) if len(rows) else None


def random_inputs(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One frame of radiance in [0, 1) and a plausible gBuffer (unit normals), shaped (1, 1, C, h, w)."""
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(1, 1, 3, height, width, generator=gen)
    normal = torch.nn.functional.normalize(torch.randn(1, 1, 3, height, width, generator=gen), dim=2)
    g = torch.cat([torch.rand(1, 1, 3, height, width, generator=gen), normal,
                   torch.rand(1, 1, 1, height, width, generator=gen)], 2)
    return x, g


@torch.no_grad()
def cpu_seconds_per_frame(model, x, g, hdr: str, repeats: int) -> float:
    """Process CPU seconds of one CPU call on one frame, the mean of `repeats` after an untimed one (first-call
    allocation is not inference time): like the renders' CPU time, robust to other work on the host."""
    predict(model, x, g, hdr)
    start = time.process_time()
    for _ in range(max(1, repeats)):
        predict(model, x, g, hdr)
    return (time.process_time() - start) / max(1, repeats)


def network_seconds(ctx: Context, methods: list[dict], speed: pd.DataFrame | None, speed_path: Path, lr_size,
                    hr_size, repeats: int) -> dict[str, tuple[float, str]]:
    """label -> (seconds per frame at the paper's sizes, where the figure comes from)."""
    out = {}
    for method in methods:
        ms = speed_ms(speed, method, lr_size, hr_size)
        if ms is not None:
            out[method["label"]] = (ms / 1000, f"speed table ({speed_path.parent.name})")
            continue
        task = get_task(method["task"])
        width, height = lr_size if INPUT_RES[method["task"]] == "lr" else hr_size
        net = build_model(model_config(ctx, method["model"], method.get("overrides")), task.scale).eval()
        log.info("time: measuring %s at %dx%d input (not in the speed table)", method["label"], width, height)
        threads = torch.get_num_threads()
        out[method["label"]] = (cpu_seconds_per_frame(net, *random_inputs(width, height), ctx.train.hdr, repeats)
                                / threads, f"measured here: CPU s / {threads} threads, mean of {repeats}")
    return out


# ---------------------------------------------------------------- the axis and its verdicts

def paper_axis(cpu_table: pd.DataFrame, renders: pd.DataFrame, networks: dict) -> pd.DataFrame:
    """The cpu table's rows that were rendered at the paper's sizes, their seconds replaced: render s (CPU
    based) and render wall s from `renders`, network s from `networks`; quality columns unchanged."""
    seconds = renders.set_index(["input", "spp"])
    rows = []
    for _, r in cpu_table.iterrows():
        key = (r["input"], int(r["spp"]))
        if r["method"] == BRUTE_FORCE or r["method"] not in networks or key not in seconds.index:
            continue
        network_s, source = networks[r["method"]]
        render_s, wall_s = seconds.loc[key, "render s"], seconds.loc[key, "wall s"]
        rows.append({"method": r["method"], "input": r["input"], "spp": int(r["spp"]), "render s": render_s,
                     "network s": network_s, "total s": render_s + network_s, "total s (wall)": wall_s + network_s,
                     "network from": source, "cpu-size total s": r["total s"],
                     **{m: r[m] for m in METRICS if m in r.index}})  # every metric the cpu table scored
    return pd.DataFrame(rows)


def paper_equal_time(axis: pd.DataFrame, cpu_table: pd.DataFrame, operating_spp: int) -> pd.DataFrame:
    """The equal-time table on the paper's axis, with the verdict (PSNR difference) on the wall-time axis and
    on the cpu-size axis beside it, and whether its sign differs from the cpu-size one."""
    table = equal_time_table(axis, operating_spp)
    keys = ["SRD method", "HR denoiser"]
    wall = equal_time_table(axis.assign(**{"total s": axis["total s (wall)"]}), operating_spp)
    cpu_size = equal_time_table(cpu_table, operating_spp)
    table = table.merge(wall[keys + ["PSNR difference (dB)"]].rename(
        columns={"PSNR difference (dB)": "PSNR difference, wall axis (dB)"}), on=keys, how="left")
    table = table.merge(cpu_size[keys + ["PSNR difference (dB)"]].rename(
        columns={"PSNR difference (dB)": "PSNR difference, cpu-size axis (dB)"}), on=keys, how="left")
    flipped = np.sign(table["PSNR difference (dB)"]) != np.sign(table["PSNR difference, cpu-size axis (dB)"])
    table["sign differs from cpu-size axis"] = flipped.map({True: "yes", False: ""})
    return table


# ---------------------------------------------------------------- the step of the experiment

@dataclass
class PaperResolution:
    """experiment.paper_resolution (conf/experiment/time.yaml)."""
    enabled: bool
    only: bool
    views: int | None
    lr_size: list
    hr_size: list
    frames: int
    repeats: int


def run_paper_resolution(ctx: Context, name: str, views: int, methods: list[dict], hr_spp: list, operating_spp: int,
                         paper: PaperResolution) -> pd.DataFrame:
    """Render, time, and write render_/axis_/equal_time_<H>p.* beside the cpu-size tables in
    <results_dir>/<name>; returns the equal-time table."""
    out = ctx.results_dir / name
    cpu_table_path = out / "table.csv"
    if not cpu_table_path.exists():
        raise UserError(f"time: the paper-resolution axis takes its quality from {cpu_table_path}, which does not "
                                f"exist: run +experiment=time with experiment.paper_resolution.only=false first")
    cpu_table = pd.read_csv(cpu_table_path)
    lr_size, hr_size, frames, repeats = tuple(paper.lr_size), tuple(paper.hr_size), int(paper.frames), int(paper.repeats)
    chosen = planned_views(ctx.data_spec, int(views if paper.views is None else min(paper.views, views)))
    spp_of = {"LR": [int(operating_spp)], "HR": [int(k) for k in hr_spp]}
    sizes = {"LR": tuple(lr_size), "HR": tuple(hr_size)}
    count = len(chosen) * int(frames) * sum(len(v) for v in spp_of.values())
    log.warning("time: %d renders at %s (LR) and %s (HR) for the paper-resolution time axis (minutes on a CPU; "
                "recorded ones are reused; experiment.paper_resolution.enabled=false skips them)", count,
                "x".join(map(str, lr_size)), "x".join(map(str, hr_size)))
    variant = render.use_variant(None)
    threads, stats, rows = render_threads(), {"renders": 0, "reused": 0}, []
    for view in chosen:
        renderer = Renderer(view, variant)
        for frame in range(len(view.cameras) - int(frames), len(view.cameras)):
            for res, spp_list in spp_of.items():
                for spp in spp_list:
                    timed = timed_render(ctx, view, renderer, frame, sizes[res], spp, threads, stats)
                    rows.append({"view": view.sequence, "frame": frame, "input": res,
                                 "size": "x".join(map(str, sizes[res])), "spp": spp, **timed})
    log.info("time: %d of %d paper-resolution renders reused from the run store", stats["reused"], stats["renders"])
    renders = render_table(rows)
    speed_path = ctx.results_dir / "speed" / device_tag(ctx.device) / "table.csv"
    speed = pd.read_csv(speed_path) if speed_path.exists() else None
    listed = [m for m in methods if m["label"] in set(cpu_table["method"])]
    networks = network_seconds(ctx, listed, speed, speed_path, lr_size, hr_size, repeats)
    axis = paper_axis(cpu_table, renders, networks)
    equal = paper_equal_time(axis, cpu_table, operating_spp)
    write_paper_tables(out, renders, axis, equal, chosen, frames, variant, threads, cpu_table, operating_spp, hr_size,
                       ctx.device)
    return equal


def write_paper_tables(out: Path, renders, axis, equal, views, frames, variant, threads, cpu_table, operating_spp,
                       hr_size, device: str) -> None:
    tag = f"{hr_size[1]}p"
    where = f"{_host(device)}, Mitsuba {variant} on {threads} render threads"
    cpu_rows = cpu_table[cpu_table["spp"] == operating_spp].drop_duplicates("input").set_index("input")["render s"]
    ratio = (f"HR/LR render time at {operating_spp} spp: {hr_lr_ratio(renders, operating_spp, 'CPU s'):.2f} in CPU "
             f"time, {hr_lr_ratio(renders, operating_spp, 'wall s'):.2f} in wall time (the cpu preset's sizes: "
             f"{cpu_rows['HR'] / cpu_rows['LR']:.2f}; the paper's {PAPER_RENDER_S['HR']} s / {PAPER_RENDER_S['LR']} s "
             f"= {PAPER_RENDER_S['HR'] / PAPER_RENDER_S['LR']:.2f}).")
    load = renders["load (1 min)"]
    views_text = (f"the last {frames} frame(s) of each of {len(views)} val view(s) "
                  f"({', '.join(v.sequence for v in views)})")
    write_table(renders, out, name=f"render_{tag}", caption=(
        f"Render times per frame at the paper's resolution, {views_text}; radiance + gBuffer in one pass, scene "
        f"loaded and JIT warm; {where}. Medians over frames: wall s; CPU s, the process CPU time of the render "
        f"(every render thread); render s = CPU s / render threads, the seconds the {tag} time axis uses (other "
        f"work on the shared host stretches wall time, not CPU time); CPU / wall: the threads' share of the "
        f"machine the render got. Load average (1 min) at the renders: {load.min():.1f} to {load.max():.1f}. "
        f"{ratio}"), lower_is_better=(), higher_is_better=())
    write_table(axis, out, name=f"axis_{tag}", caption=(
        f"The time axis at the paper's resolution: each method's seconds per frame with its input rendered at "
        f"the LR or HR size of render_{tag}.csv: render s = the renders' CPU time / render threads; network s at "
        f"the {tag} output (network from): the speed table's wall-clock median (fp32; its caption names the weights) where it "
        f"has the method, else measured here as CPU time / torch threads; total s = render s + network s; total "
        f"s (wall): with the renders' wall seconds; cpu-size total s: the same row in table.csv. {QUALITY_NOTE}"),
        lower_is_better=(), higher_is_better=())
    flips = equal[equal["sign differs from cpu-size axis"] == "yes"]
    flipped = ("; ".join(f"{r['SRD method']} vs {r['HR denoiser']}" for _, r in flips.iterrows()) or "none")
    write_table(equal, out, name=f"equal_time_{tag}", caption=(
        f"Equal time at the paper's resolution: each SRD method at LR {operating_spp} spp against each denoiser "
        f"of HR renders given the same seconds per frame on the {tag} time axis (axis_{tag}.csv, render seconds "
        f"from CPU time; {where}): the denoiser's relMSE, PSNR and FLIP read off its own curve (lines through its "
        f"HR spp points) at the SRD method's total time; HDR-FLIP difference: SRD minus denoiser (below 0: SRD "
        f"wins); extrapolated: outside the denoiser's measured times. "
        f"PSNR difference on the wall-time axis and on the cpu-size axis (equal_time.csv) beside it. Verdicts "
        f"whose sign differs from the cpu-size axis: {flipped}. {QUALITY_NOTE}"),
        lower_is_better=("HDR-FLIP difference",), higher_is_better=("PSNR difference (dB)",))

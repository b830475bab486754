"""Fast paths and tiled inference (bench/infer.py) and the speed experiment, at tiny sizes.

Every fast path must give the reference (fp32) output: to float rounding for inference_mode and
channels_last, within 5% of the output's range for bf16 (bfloat16 keeps ~3 significant digits and
errors add up through a few dozen layers). Tiled inference must equal untiled inference for conv-only
models once the overlap covers the receptive radius, and stream recurrent models tile by tile.
"""
import copy
import dataclasses
import platform
import re
from pathlib import Path
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from baselines.cfm import CFMNet
from baselines.edsr import EDSR
from baselines.kpcn import KPCN
from baselines.rae import RAE
from bench.cli import CONF_DIR, run_experiment
from bench.errors import UserError
from bench.experiments.macs import audit_row
from bench.experiments.speed import PATHS, peak_memory_mib
from bench.machine import device_tag
from bench.infer import (FastPath, frames_channels_last, parse_path, prepare, receptive_radius, tiled_predict)
from bench.models.srd import SRDNet
from conftest import config_recipe, perturbed

TINY = {
    "srd": lambda: SRDNet(channels=4, cond_channels=4),
    "edsr": lambda: EDSR(channels=4, blocks=2),
    "rae": lambda: RAE(width=4),
    "kpcn": lambda: KPCN(channels=3, layers=3, filter_size=5),
    "cfm": lambda: CFMNet(channels=4, blocks=2, cond_channels=4, cond_hidden=4, deformable_blocks=1),
}
CONV_ONLY = ["edsr", "kpcn", "cfm"]


@pytest.fixture(autouse=True)
def one_thread():
    """Small ops on a busy 2-core machine: one thread avoids waiting for the other core."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_model(name, seed=0):
    """A tiny model with noise on every weight: zero-initialised branches (CFM, deformable offsets,
    residual output convs) then compute, so the comparisons see every layer."""
    torch.manual_seed(seed)
    model = TINY[name]()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.02)
    return model.eval()


def inputs(frames=2, h=20, w=28, seed=1):
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(1, frames, 3, h, w, generator=gen), torch.rand(1, frames, 7, h, w, generator=gen)


# ---- fast paths -----------------------------------------------------------------------------------

def test_parse_path_combines_switches_and_rejects_unknown_ones():
    assert parse_path("fp32") == FastPath("fp32") and not parse_path("fp32").inference_mode
    combo = parse_path("channels_last+bf16")
    assert combo.channels_last and combo.bf16 and combo.inference_mode and not combo.compile
    assert parse_path(combo) is combo    # a parsed path passes through
    swapped = parse_path("bf16+channels_last")
    assert swapped.channels_last and swapped.bf16 and swapped.inference_mode
    with pytest.raises(ValueError, match="fp16"):
        parse_path("fp16")


def test_frames_channels_last_keeps_values_and_makes_frames_nhwc():
    x = torch.randn(2, 3, 4, 5, 6)
    y = frames_channels_last(x)
    assert torch.equal(x, y)
    assert y[:, 1].stride(1) == 1 and frames_channels_last(x[:1])[:, 1].is_contiguous(memory_format=torch.channels_last)
    assert y.reshape(6, 4, 5, 6).is_contiguous(memory_format=torch.channels_last)


@pytest.mark.parametrize("name", list(TINY))
@pytest.mark.parametrize("path,tolerance", [("inference_mode", 0.0), ("channels_last", 1e-5),
                                            ("bf16", 0.05), ("channels_last+bf16", 0.05)])
def test_fast_path_equals_reference(name, path, tolerance):
    model = tiny_model(name)
    x, g = inputs()
    reference = prepare(model, "fp32")(x, g)
    out = prepare(model, path)(x, g)
    assert out.keys() == reference.keys()
    for key, ref in reference.items():
        assert out[key].dtype == torch.float32 and out[key].is_contiguous()
        spread = float(ref.max() - ref.min())
        assert float((out[key] - ref).abs().max()) <= tolerance * spread + 1e-6, (key, path)


def test_prepare_leaves_the_model_untouched():
    model = tiny_model("edsr")
    prepare(model, "channels_last")
    assert model.trunk.head.weight.is_contiguous()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["edsr", "srd"])
def test_compiled_path_equals_reference(name):
    """torch.compile takes about a minute per model on 2 CPU cores, hence slow."""
    model = tiny_model(name)
    x, g = inputs(frames=1)
    torch.testing.assert_close(prepare(model, "compile")(x, g)["final"], prepare(model)(x, g)["final"],
                               atol=1e-5, rtol=1e-5)


# ---- tiled inference ------------------------------------------------------------------------------

@pytest.mark.parametrize("name", CONV_ONLY)
def test_tiled_equals_untiled_once_overlap_covers_the_receptive_radius(name):
    model = tiny_model(name)
    radius = receptive_radius(model, *inputs(frames=1, h=48, w=48))
    assert 0 < radius < 24
    x, g = inputs(frames=2, h=40, w=52)
    untiled = prepare(model)(x, g)["final"]
    tiled = tiled_predict(model, x, g, tile=8, overlap=radius, align=1)
    assert tiled.shape == untiled.shape
    assert float((tiled - untiled).abs().max()) < 1e-5
    too_small = tiled_predict(model, x, g, tile=8, overlap=0, align=1)
    assert float((too_small - untiled).abs().max()) > 1e-3  # the check can fail: seams without context


@pytest.mark.parametrize("name", ["srd", "rae"])
def test_tiled_streams_recurrent_models_with_a_state_per_tile(name):
    """With an overlap covering the frame every tile sees the whole frame: the result must be the
    untiled one exactly, across frames (each tile carries its own state). With less context the
    U-Net's global view makes it differ a little, and the difference shrinks with the overlap."""
    model = tiny_model(name)
    x, g = inputs(frames=3, h=40, w=72)
    untiled = prepare(model)(x, g)["final"]
    whole = tiled_predict(model, x, g, tile=32, overlap=96, align=32)
    torch.testing.assert_close(whole, untiled, atol=1e-5, rtol=0)
    errors = [float((tiled_predict(model, x, g, tile=32, overlap=o, align=32) - untiled).abs().max())
              for o in (0, 32)]
    assert errors[0] > 1e-2    # the check can fail: tiles without context have seams, so tiling took place
    assert errors[1] < errors[0]


def test_tiled_runs_a_fast_path():
    model = tiny_model("edsr")
    x, g = inputs(frames=1, h=24, w=24)
    out = tiled_predict(model, x, g, tile=8, overlap=16, align=8, path="channels_last")
    torch.testing.assert_close(out, prepare(model)(x, g)["final"], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="compile"):
        tiled_predict(model, x, g, path="compile")


# ---- the speed experiment -------------------------------------------------------------------------

def test_peak_memory_sees_a_large_allocation():
    assert peak_memory_mib(lambda: torch.ones(64 * 2 ** 20 // 4).add_(1), "cpu") > 48


def test_speed_experiment_writes_every_section(tmp_path):
    overrides = ["preset=smoke", f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}",
                 "device=cpu", "models.srd.channels=4", "models.srd.cond_channels=4", "models.edsr.channels=4",
                 "models.edsr.blocks=2", "models.rae.width=4", "models.kpcn.channels=2", "models.kpcn.layers=3",
                 "models.cfm.channels=4", "models.cfm.blocks=2", "models.cfm.cond_hidden=4",
                 "models.cfm.cond_channels=4", "experiment.input_hw=[24,40]", "experiment.repeats=1",
                 "experiment.threads=1", "experiment.train={batch:1,frames:2,crop:16}",
                 "experiment.deform={channels:4,sizes:[[16,24]]}",
                 "experiment.tiled={tile:16,overlap:32,uhd_input_hw:[40,64]}"]
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=["+experiment=speed", *overrides])
    run_experiment(cfg)
    out = tmp_path / "results" / "speed" / device_tag("cpu")
    for ext in ("csv", "md", "tex"):
        assert (out / f"table.{ext}").stat().st_size > 0
    table = pd.read_csv(out / "table.csv")
    labels = ["Ours", "EDSR", "RAE", "KPCN", "CFM"]
    inference = table[table.section == "inference"]
    assert sorted(zip(inference.method, inference["fast path"])) == sorted((m, p) for m in labels for p in PATHS)
    assert inference[["ms", "GMac", "GMac/s", "time / OIDN", "GMac/s / conv stack"]].notna().all().all()
    assert (inference["max rel diff"] < 0.05).all()
    notes = inference["note"].fillna("")
    assert not notes.str.contains("failed").any()
    # each model's row of the path fast_path=auto picks here says so, and checks it against the table
    # (on its first row when the table has no row of that path: channels_last+bf16 on a bf16 CPU)
    picked = inference[notes.str.contains("fast_path=auto picks")]
    assert sorted(picked.method) == sorted(labels)
    on_its_row = picked[picked["note"].str.contains("fast_path=auto picks this")]
    assert set(on_its_row["fast path"]) <= {"fp32", "channels_last", "bf16"}
    assert on_its_row["note"].str.contains("the fastest in this table of those|faster in this table").all()
    assert picked.drop(on_its_row.index)["note"].str.contains(
        r"fast_path=auto picks channels_last\+bf16 of .*, not timed in this table").all()
    steps = table[table.section == "training step"]
    stack = steps[steps.method.str.startswith("3x3 conv stack")]
    assert sorted(set(steps.method) - set(stack.method)) == sorted(labels) and len(stack) == 1
    assert stack["step / conv stack step"].iloc[0] == 1 and steps["step / conv stack step"].notna().all()
    # models with deformable convs also time the grid_sample training sampler they had before
    before = steps[steps["fast path"] == "fp32, grid_sample sampler"]
    assert sorted(before.method) == ["Ours"]
    tiled = table[table.section == "tiled"]
    assert sorted(tiled.method) == sorted(labels * 2) and set(tiled["size"]) == {"40x24 -> 80x48", "64x40 -> 128x80"}
    oidn_size = table.loc[table.method.str.startswith("OIDN"), "size"].item()
    assert oidn_size == "80x48"                          # OIDN is timed at one size: ratios at that size only
    assert tiled.loc[tiled["size"] == "40x24 -> 80x48", "time / OIDN"].notna().all()
    assert tiled.loc[tiled["size"] == "64x40 -> 128x80", "time / OIDN"].isna().all()
    references = table.loc[table.section == "reference", "method"]
    assert references.str.startswith("OIDN").sum() == 1 and references.str.startswith("3x3 conv stack").sum() == len(PATHS)
    # the conv stack's MACs by formula (depth x h*w*c^2*9), and Ours' as the MAC audit counts them
    stack_rows = table[(table.section == "reference") & table.method.str.startswith("3x3 conv stack")]
    depth, channels = map(int, re.match(r"3x3 conv stack \((\d+) x (\d+) ch\)", stack_rows.method.iloc[0]).groups())
    assert stack_rows["GMac"].tolist() == pytest.approx([depth * 24 * 40 * channels ** 2 * 9 / 1e9] * len(PATHS))
    ours = cfg.models.srd
    audited = audit_row("Ours", OmegaConf.to_container(ours, resolve=True), 1.0, (24, 40))[0]["GMac (analytic)"]
    assert inference.loc[inference.method == "Ours", "GMac"].tolist() == pytest.approx([audited] * len(PATHS))
    deform = table[table.section == "deformable conv"]
    # per path: the conv, the sampler this machine takes and (when that is the compiled one) the eager
    # gather; plus the training sampler once
    from bench.nn import inference_sampler
    per_path = 3 if inference_sampler(torch.zeros(1)) == "columns" else 2
    assert len(deform) == 3 * per_path + 1 and deform["time / plain conv"].notna().all()
    assert set(deform["fast path"]) == {"fp32", "channels_last", "channels_last+bf16"}
    conv = deform[deform.method.str.startswith("nn.Conv2d")]
    assert (conv["time / plain conv"] == 1).all() and len(conv) == 3
    profile = table[table.section == "profile"].set_index("method")
    assert profile.loc["Ours: whole frame", "fast path"] == PATHS[-1]
    # inclusive times: a class's time is within its frame's, and its parts' within its own
    assert (profile["ms"] <= profile.loc["Ours: whole frame", "ms"] * 1.001).all()
    assert profile.loc["Ours: DeformConv2d", "ms"] <= profile.loc["Ours: DecoderBlock", "ms"] * 1.001
    # every MAC of the frame belongs to some module class: the top-level stages add up to the whole
    stages = profile.loc[["Ours: SRStage", "Ours: RecurrentDenoiser", "Ours: ConditionNet"], "GMac"].sum()
    assert stages == pytest.approx(profile.loc["Ours: whole frame", "GMac"], rel=0.02)
    caption = (out / "table.md").read_text().splitlines()[0]
    assert "torch " + torch.__version__ in caption and "1 torch threads" in caption
    assert not caption.startswith("PARTIAL")                # every section is in
    from bench.experiments.results_page import speed_table_label    # what the results page says of the table
    assert speed_table_label(out / "table.md") == "untrained weights"


@pytest.mark.parametrize("override,message", [
    ("experiment.tiled.tile=0", "experiment.tiled.tile=0: expected an integer >= 1"),
    ("experiment.tiled.tile=-40", "experiment.tiled.tile=-40: expected an integer >= 1"),
    ("experiment.tiled.overlap=-1", "experiment.tiled.overlap=-1: expected an integer >= 0"),
    ("experiment.tiled.uhd_input_hw=[4,64]", "experiment.tiled.uhd_input_hw: [4, 64]: expected [height, width]"),
    ("experiment.deform.sizes=[[16]]", "experiment.deform.sizes: [16]: expected [height, width]"),
    ("experiment.deform.sizes=[16,16]", "experiment.deform.sizes: 16: expected [height, width]"),
    ("experiment.deform.sizes=null", "experiment.deform.sizes=None: expected a list of [height, width]"),
    ("experiment.tiled.uhd_input_hw=1080", "experiment.tiled.uhd_input_hw: 1080: expected [height, width]"),
    ("experiment.deform.channels=0", "experiment.deform.channels=0: expected an integer >= 1"),
    ("experiment.conv_stack_channels=-2", "experiment.conv_stack_channels=-2: expected an integer >= 0"),
    ("experiment.perturb=-0.1", "experiment.perturb=-0.1: expected a number >= 0"),
    ("experiment.weights=[]", "experiment.weights=[]: expected {model: weights file}"),   # not taken for "none"
    ("experiment.profile.fast_path=compile", "experiment.profile.fast_path=compile: hooks do not see inside"),
    ("experiment.profile.fast_path=fp16", "experiment.profile.fast_path: 'fp16': unknown fast path switch"),
    ("experiment.models=[srd,bilinear]", "experiment.models: 'bilinear' has nothing to train; the speed table"),
    ("experiment.models=[oidn_lr]", "experiment.models: 'oidn_lr' has nothing to train; the speed table"),
    ("experiment.models=[srdd]", "experiment.models: no model 'srdd'; models: srd, "),
    ("experiment.models=[edsr,rae,edsr]", "experiment.models: 'edsr' is listed twice"),
])
def test_a_bad_section_value_is_one_line_before_anything_is_timed(tmp_path, override, message):
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=["+experiment=speed", "preset=smoke", f"results_dir={tmp_path}", override])
    with pytest.raises(UserError, match=re.escape(message)):
        run_experiment(cfg)
    assert not any(tmp_path.iterdir())   # nothing timed, no table written


def test_keep_freed_memory_applies_once_on_glibc():
    """The CLI's allocator setting: applies on glibc (Linux CI), is idempotent and reported."""
    from bench.infer import freed_memory_kept, keep_freed_memory
    applied = keep_freed_memory()
    assert keep_freed_memory() == applied == freed_memory_kept()
    if platform.libc_ver()[0] == "glibc":
        assert applied


def test_the_caption_names_the_cpu_isa():
    from bench.experiments.speed import machine_caption
    from bench.machine import cpu_isa
    isa = cpu_isa()
    assert any(name in isa for name in ("AVX512-BF16", "AMX-BF16", "AVX-512", "AVX2", "no AVX2", "ISA unknown"))
    assert isa in machine_caption("cpu")


def test_the_caption_tells_two_cpus_of_one_model_name_apart():
    """One cloud model name ("AMD EPYC") covered two hosts 1.4-2.2x apart: the caption names what
    differs (x86 family, model, stepping, clock, L3)."""
    from bench.experiments.speed import machine_caption
    from bench.machine import cpu_identity
    if cpu_identity():                     # where /proc can be read, the caption carries it
        assert f"({cpu_identity()})" in machine_caption("cpu")


def test_a_gpu_caption_names_the_gpu_and_its_host_cpu_isa(monkeypatch):
    from bench.experiments.speed import machine_caption
    from bench.machine import cpu_isa
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H200")
    caption = machine_caption("cuda")
    assert caption.startswith("NVIDIA H200 (CUDA ") and cpu_isa() in caption


def test_auto_choice_notes_a_path_the_table_did_not_time_and_survives_a_machine_with_no_path(monkeypatch):
    import bench.experiments.speed as speed
    rows = [{"fast path": "fp32", "ms": 2.0}, {"fast path": "channels_last", "ms": float("nan"), "note": "failed: X"}]
    monkeypatch.setattr(speed, "candidate_paths", lambda device: ["fp32", "channels_last"])
    monkeypatch.setattr(speed, "choose_fast_path", lambda *a, **k: ("channels_last", {}))
    assert speed.note_auto_choice(rows, None, None, None, "cpu", 1) == "channels_last"
    assert rows[1]["note"] == "failed: X; fast_path=auto picks this of ['fp32', 'channels_last'], not timed in this table"
    # a path the table has no row of: said on the model's first row
    rows = [{"fast path": "fp32", "ms": 2.0}, {"fast path": "channels_last", "ms": 1.0}]
    monkeypatch.setattr(speed, "candidate_paths", lambda device: ["fp32", "channels_last", "channels_last+bf16"])
    monkeypatch.setattr(speed, "choose_fast_path", lambda *a, **k: ("channels_last+bf16", {}))
    assert speed.note_auto_choice(rows, None, None, None, "cpu", 1) == "channels_last+bf16"
    assert rows[0]["note"] == ("fast_path=auto picks channels_last+bf16 of ['fp32', 'channels_last', "
                               "'channels_last+bf16'], not timed in this table") and "note" not in rows[1]

    def nothing_runs(*args, **kwargs):
        raise RuntimeError("no fast path runs this model here: {}")
    monkeypatch.setattr(speed, "choose_fast_path", nothing_runs)
    assert speed.note_auto_choice(rows, torch.nn.Identity(), None, None, "cpu", 1) is None


def test_auto_choice_names_a_faster_path_its_accuracy_check_refused(monkeypatch):
    """bf16 timed faster but refused by the chooser's accuracy check is not reported as auto's mistake:
    the note names the refused path, its speed-up and the reason; a faster accepted path still is."""
    import bench.experiments.speed as speed
    monkeypatch.setattr(speed, "candidate_paths", lambda device: ["fp32", "channels_last", "channels_last+bf16"])
    measured = {"fp32": 8.0, "channels_last": 5.0, "channels_last+bf16": "off by 0.06 of the output range"}
    monkeypatch.setattr(speed, "choose_fast_path", lambda *a, **k: ("channels_last", measured))
    rows = [{"fast path": "fp32", "ms": 8.5}, {"fast path": "channels_last", "ms": 5.5},
            {"fast path": "channels_last+bf16", "ms": 2.2}]
    assert speed.note_auto_choice(rows, None, None, None, "cpu", 1) == "channels_last"
    assert rows[1]["note"] == ("fast_path=auto picks this of ['fp32', 'channels_last', 'channels_last+bf16'], "
                               "the fastest in this table of those its accuracy check accepted; channels_last+bf16 ran 2.50x "
                               "faster here, "
                               "refused: off by 0.06 of the output range")
    # an accepted path the table measured faster is still auto's miss
    rows = [{"fast path": "fp32", "ms": 4.0}, {"fast path": "channels_last", "ms": 5.0},
            {"fast path": "channels_last+bf16", "ms": 6.0}]
    speed.note_auto_choice(rows, None, None, None, "cpu", 1)
    assert rows[1]["note"].endswith("but fp32 was 1.25x faster in this table")


def _exported(path, cfg, seed=3, scale=2):
    """A weights file as `srd-bench export` writes it (no sidecar), of the model `cfg` builds."""
    from bench.models.factory import build_model
    from bench.weights import FORMAT
    torch.manual_seed(seed)
    model = build_model(cfg, scale)
    torch.save({"format": FORMAT, "model": cfg, "scale": scale, "hdr": "pu", "task": "srd" if scale == 2 else "denoise",
                "run": "0123abcd", "state_dict": model.state_dict()}, path)
    return model.state_dict()


def two_tiny_models(results_dir, *overrides):
    """The speed experiment on a tiny EDSR and RAE, fp32 only, without the reference sections."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        return compose("config", overrides=[
            "+experiment=speed", "preset=smoke", f"results_dir={results_dir}", "device=cpu", "models.edsr.channels=4",
            "models.edsr.blocks=2", "models.rae.width=4", "experiment.models=[edsr,rae]", "experiment.input_hw=[16,24]",
            "experiment.fast_paths=[fp32]", "experiment.repeats=1", "experiment.oidn=false",
            "experiment.conv_stack_channels=0", "+experiment.deform.enabled=false", "+experiment.tiled.enabled=false",
            *overrides])


def test_weights_give_a_model_its_trained_weights_in_every_row_and_the_caption_names_them(tmp_path, monkeypatch):
    """experiment.weights: the rows of that model run the file's weights (unperturbed), the others untrained
    ones, and the caption says which; auto's note says a refusal on untrained weights is on them."""
    import bench.experiments.speed as speed
    cfg = two_tiny_models(tmp_path, "experiment.train={batch:1,frames:2,crop:8}", "experiment.profile.models=[edsr]",
                          f"experiment.weights={{edsr:{tmp_path / 'edsr.pt'}}}")      # as on the command line
    edsr = OmegaConf.to_container(cfg.models.edsr, resolve=True)
    saved = _exported(tmp_path / "edsr.pt", edsr)
    timed, stepped, profiled, on_untrained = {}, {}, {}, {}
    monkeypatch.setattr(speed, "inference_rows", lambda label, model, *a: timed.setdefault(label, model) and [])
    monkeypatch.setattr(speed, "training_steps", lambda label, model, *a: stepped.setdefault(label, model) and [])
    monkeypatch.setattr(speed, "profile_rows", lambda label, model, *a: profiled.setdefault(label, model) and [])
    monkeypatch.setattr(speed, "note_auto_choice", lambda rows, model, *a, untrained: on_untrained.setdefault(
        type(model).__name__, untrained))
    run_experiment(cfg)
    for section in (timed, stepped, profiled):              # every section of it, unperturbed
        assert section["EDSR"].state_dict().keys() == saved.keys()
        assert all(torch.equal(v, section["EDSR"].state_dict()[k]) for k, v in saved.items())
    assert set(stepped) == {"EDSR", "RAE"} and set(profiled) == {"EDSR"}
    assert on_untrained == {"EDSR": False, "RAE": True}
    caption = (tmp_path / "speed" / device_tag("cpu") / "table.md").read_text().splitlines()[0]
    assert f"trained weights (EDSR {tmp_path / 'edsr.pt'}, training run 0123abcd, pu domain), untrained for RAE" in caption
    from bench.experiments.results_page import speed_table_label    # what the results page says of the table
    assert speed_table_label(tmp_path / "speed" / device_tag("cpu") / "table.md") == "trained weights for some models"


def test_the_training_rows_take_the_tables_batch_and_a_null_takes_the_default(tmp_path, monkeypatch):
    """experiment.train's batch, frames and crop replace the trainer's recipe's for every training row, and
    a null value is the default: rows on (enabled), no compiled row (compile, compiled)."""
    import bench.experiments.speed as speed
    cfg = two_tiny_models(tmp_path, "experiment.train={batch:1,frames:null,crop:8,compile:null,compiled:null}",
                          "+experiment.train.enabled=null", "experiment.profile.models=[]")
    stepped = {}
    monkeypatch.setattr(speed, "inference_rows", lambda *a: [])
    monkeypatch.setattr(speed, "note_auto_choice", lambda *a, untrained: None)
    monkeypatch.setattr(speed, "training_steps", lambda label, model, recipe, mode, *a: stepped.setdefault(
        label, (recipe.batch_size, recipe.seq_len, recipe.crop, recipe.lr, mode)) and [])
    run_experiment(cfg)
    trainer = OmegaConf.to_container(cfg.train, resolve=True)
    lr, frames = trainer["lr"], trainer["seq_len"]
    assert stepped == {"EDSR": (1, frames, 8, lr, None), "RAE": (1, frames, 8, lr, None)}


@pytest.mark.parametrize("weights,message", [
    ("W", "experiment.weights='W': expected {model: weights file}"),
    ({"edsr": None}, "experiment.weights.edsr=None: expected the path of a weights file"),
    ({"edsr": "W1"}, "experiment.weights.edsr: W1 holds a model of scale 1 (task denoise); this table times scale 2"),
    ({"srd": "W"}, "experiment.weights.srd: 'srd' is not one of experiment.models ['edsr']"),
    ({"edsr": "W"}, "experiment.weights.edsr: W holds another configuration than this preset's edsr (channels 4, here 64)"),
    ({"edsr": "missing.pt"}, "weights file missing.pt does not exist"),
    ({"edsr": "~/no-such-srd-weights.pt"}, f"weights file {Path.home() / 'no-such-srd-weights.pt'} does not exist"),
])
def test_weights_of_another_model_or_width_are_one_line_before_anything_is_timed(tmp_path, weights, message):
    from bench.experiments.speed import trained_models
    edsr = {"_target_": "baselines.edsr.EDSR", "channels": 64, "blocks": 2}
    _exported(tmp_path / "W", {**edsr, "channels": 4})
    _exported(tmp_path / "W1", edsr, scale=1)
    if isinstance(weights, dict):
        weights = {name: str(tmp_path / path) if path in ("W", "W1") else path for name, path in weights.items()}
    message = message.replace("W holds", f"{tmp_path / 'W'} holds").replace("W1 holds", f"{tmp_path / 'W1'} holds")
    with pytest.raises(UserError, match=re.escape(message)):
        trained_models(weights, ["edsr"], {"edsr": edsr})


def test_auto_choice_says_a_refusal_on_untrained_weights_is_on_them(monkeypatch):
    import bench.experiments.speed as speed
    monkeypatch.setattr(speed, "candidate_paths", lambda device: ["fp32", "bf16"])
    monkeypatch.setattr(speed, "choose_fast_path", lambda *a, **k: ("fp32", {"fp32": 4.0, "bf16": "off by 0.06"}))
    rows = [{"fast path": "fp32", "ms": 4.0}, {"fast path": "bf16", "ms": 2.0}]
    speed.note_auto_choice(rows, None, None, None, "cpu", 1, untrained=True)
    assert rows[0]["note"].endswith("; bf16 ran 2.00x faster here, refused on these untrained weights: off by 0.06")
    # a path that failed to run failed whatever the weights
    monkeypatch.setattr(speed, "choose_fast_path", lambda *a, **k: ("fp32", {"fp32": 4.0, "bf16": "failed: X"}))
    rows = [{"fast path": "fp32", "ms": 4.0}, {"fast path": "bf16", "ms": 2.0}]
    speed.note_auto_choice(rows, None, None, None, "cpu", 1, untrained=True)
    assert rows[0]["note"].endswith("; bf16 ran 2.00x faster here, refused: failed: X")


def test_the_results_page_says_a_table_of_trained_weights_for_every_model_ran_trained_weights(tmp_path):
    from bench.experiments.results_page import speed_table_label
    from bench.experiments.speed import weights_caption
    caption = weights_caption({"srd": (None, "ours.pt, training run 1, pu domain")}, ["srd"])
    assert caption == "trained weights (Ours ours.pt, training run 1, pu domain)"
    (tmp_path / "table.md").write_text(f"Speed on x CPU; preset cpu widths, {caption}. ms: wall clock\n")
    assert speed_table_label(tmp_path / "table.md") == "trained weights"


def test_a_run_stopped_before_its_last_section_leaves_a_table_that_says_partial_and_the_next_goes_on(tmp_path,
                                                                                                     monkeypatch):
    """The table is rewritten after every section (a model's inference, each of its training steps, ...):
    one stopped part way (a GPU job's step at its limit) keeps what it timed under a caption opening with
    PARTIAL, which the results page repeats and scripts/gpu_job.sh reads to run the step again. The next
    run of the same settings and code times only the sections not in yet (a speed table too long for one
    call is finished by the next), and says so in the caption without PARTIAL; a run of other settings,
    or with the fused kernels switched on since, times every section again."""
    import bench.experiments.speed as speed
    from bench.experiments.results_page import speed_table_label
    cfg = two_tiny_models(tmp_path, "experiment.train={batch:1,frames:2,crop:8}", "experiment.profile.models=[]")
    table_md = tmp_path / "speed" / device_tag("cpu") / "table.md"
    kept = table_md.parent / speed.PARTIAL_SECTIONS
    timed, seen = speed.training_row, []

    def stops_at_rae(label, *args, **options):
        if label == "RAE":
            raise KeyboardInterrupt  # as SIGINT, or the trainer's SIGTERM handler, would stop it
        return timed(label, *args, **options)

    def counted(label, *args, **options):
        seen.append(label)
        return timed(label, *args, **options)

    def stopped_at_raes_training_step():
        monkeypatch.setattr(speed, "training_row", stops_at_rae)
        with pytest.raises(KeyboardInterrupt):
            run_experiment(cfg)
        monkeypatch.setattr(speed, "training_row", counted)
        seen.clear()
    stopped_at_raes_training_step()
    assert table_md.read_text().startswith("PARTIAL: ")
    first = pd.read_csv(table_md.with_suffix(".csv"))
    assert sorted(zip(first.section, first.method)) == [("inference", "EDSR"), ("inference", "RAE"),
                                                        ("training step", "EDSR")] and kept.exists()
    assert speed_table_label(table_md) == "untrained weights, PARTIAL (not every section timed)"
    run_experiment(cfg)
    assert seen == ["RAE"]                                       # the sections in were kept, not timed again
    assert not table_md.read_text().startswith("PARTIAL") and speed_table_label(table_md) == "untrained weights"
    assert table_md.read_text().split("\n")[0].endswith(
        "Resumed: EDSR inference; EDSR training step (fp32); RAE inference timed by an earlier run of these settings "
        "and code, which was interrupted.")
    whole = pd.read_csv(table_md.with_suffix(".csv"))
    assert len(whole) == len(first) + 1 and not kept.exists()
    assert whole.iloc[:len(first)]["ms"].tolist() == first["ms"].tolist()   # as they were timed
    stopped_at_raes_training_step()
    run_experiment(two_tiny_models(tmp_path, "experiment.train={batch:1,frames:2,crop:8}",
                                   "experiment.profile.models=[]", "experiment.repeats=2"))   # other settings
    assert seen == ["EDSR", "RAE"] and "Resumed" not in table_md.read_text() and not kept.exists()
    stopped_at_raes_training_step()
    monkeypatch.setenv("SRD_BENCH_FUSED_GPU", "1")       # the GPU job's kernels switched on since: nothing kept
    run_experiment(cfg)
    assert seen == ["EDSR", "RAE"] and "Resumed" not in table_md.read_text()


def test_the_profile_takes_the_last_path_hooks_can_see_into():
    from bench.experiments.speed import profiled_path
    assert profiled_path({"models": ["srd"]}, ["fp32", "channels_last", "compile"]) == "channels_last"  # "+ compile"
    assert profiled_path({"models": ["srd"], "fast_path": None}, ["compile"]) == "fp32"
    assert profiled_path({"models": ["srd"], "fast_path": "bf16"}, ["fp32", "compile"]) == "bf16"
    assert profiled_path({"models": [], "fast_path": "compile"}, ["fp32"]) == "compile"   # nothing profiled


def test_a_training_step_that_fails_is_a_row_saying_why_and_the_table_goes_on(monkeypatch):
    """A compiled step that does not trace on this machine (the speed step of scripts/gpu_job.sh runs
    train.compile=reduce-overhead where it never ran before) is its row's note, not the end of the run."""
    from bench.experiments import speed

    def broken(*args, **kwargs):
        raise RuntimeError("graph capture failed\nsecond line")
    monkeypatch.setattr(speed, "timed_training_row", broken)
    row = speed.training_row("Ours", TINY["edsr"](), config_recipe(batch_size=2, seq_len=3, crop=8), "cpu", 1, 0,
                             path="fp32, compiled (reduce-overhead)", compile="reduce-overhead")
    assert row["note"] == "failed: RuntimeError: graph capture failed"
    assert (row["section"], row["fast path"], row["size"]) == (
        "training step", "fp32, compiled (reduce-overhead)", "2x3 frames of 8x8 LR")
    assert "ms" not in row
    stack = {"section": "training step", "method": "3x3 conv stack (4 x 8 ch)", "fast path": row["fast path"], "ms": 14.7}
    table = speed._ratios(pd.DataFrame([stack, row], columns=speed.COLUMNS))  # a row without a time has no ratio
    assert table["step / conv stack step"].tolist()[0] == 1.0 and pd.isna(table["step / conv stack step"].tolist()[1])


def test_the_speed_tables_training_step_is_the_trainers_step(tmp_path, monkeypatch):
    """What a training row times is one step of bench.train.train: on the same batch, one step of
    speed.training_step leaves the weights one step of the trainer leaves (HDR encode, the loss, a gradient
    clip that bites, Adam), and it updates an EMA as the trainer does. The conv stack's step takes the
    same update after its L1 loss."""
    import bench.train
    from bench.experiments import speed
    from bench.tasks import get_task
    task = get_task("srd")
    recipe = config_recipe(steps=1, batch_size=2, seq_len=2, crop=8, schedule="constant", clip_grad_norm=1e-9,
                           emitters=0.0, fireflies=0.0, colour_permute=False)
    recipe = dataclasses.replace(recipe, loss={h: {**w, "perceptual": 0} for h, w in recipe.loss.items()})
    assert recipe.ema and recipe.hdr != "clamp"   # the config's EMA and HDR domain are what is compared
    x, g = speed.random_frames(2, 2, (8, 8), "cpu", seed=1)   # the batch training_step draws
    y = torch.rand(2, 2, 3, 16, 16, generator=torch.Generator().manual_seed(2))

    class OneBatch:
        def __len__(self):
            return 1

        def item(self, index, draw):   # draw: the item's slot in the batch, at step 0
            return {task.x: x[draw], task.g: g[draw], task.y: y[draw], task.mid: y[draw]}

    torch.manual_seed(0)
    initial = TINY["edsr"]()
    perturbed(initial)   # its zero output conv would leave every other weight without a gradient
    trained = copy.deepcopy(initial)
    bench.train.train(trained, OneBatch(), task, tmp_path, recipe, progress=False)
    by_trainer = torch.load(tmp_path / bench.train.CHECKPOINT, weights_only=False)["model"]
    emas = []
    monkeypatch.setattr(bench.train, "update_ema", lambda *args: emas.append(args[-1]))
    stepped = copy.deepcopy(initial)
    speed.training_step(stepped, recipe, "cpu")()
    for name, value in stepped.state_dict().items():
        torch.testing.assert_close(value, by_trainer[name], rtol=1e-5, atol=1e-7, msg=name)
    assert all(not torch.equal(value, initial.state_dict()[name]) for name, value in by_trainer.items())
    unclipped = copy.deepcopy(initial)   # the clip bites: without it, the step is another
    speed.training_step(unclipped, dataclasses.replace(recipe, clip_grad_norm=None), "cpu")()
    assert any(not torch.allclose(value, by_trainer[name]) for name, value in unclipped.state_dict().items())
    assert emas == [0, 0]
    step = speed.training_step(speed.ConvStack(4, 2), recipe, "cpu", stack_channels=4)
    assert step().ndim == 0 and step().item() >= 0 and emas == [0, 0, 0, 1]
    batches = []   # with train.channels_last, every buffer of the batch is laid out as the trainer lays it
    real_step_loss = speed.step_loss
    monkeypatch.setattr(speed, "step_loss", lambda loss_fn, net, batch, *a: batches.append(batch)
                        or real_step_loss(loss_fn, net, batch, *a))
    speed.training_step(copy.deepcopy(initial), dataclasses.replace(recipe, channels_last=True), "cpu")()
    assert sorted(batches[0]) == sorted(task.buffers()) and all(
        frames_channels_last(v).stride() == v.stride() and not v.is_contiguous() for v in batches[0].values())


def test_a_training_row_times_the_step_its_path_names_and_its_note_says_what_the_step_does(monkeypatch):
    """timed_training_row hands the path's precision, memory layout and compile mode to the step it times
    (the trainer's recipe otherwise), and the row's note names the update the recipe takes."""
    from bench.experiments import speed
    asked = []

    def recorded(model, recipe, device, stack_channels=None):
        asked.append((recipe.precision, recipe.channels_last, recipe.compile, recipe.lr, stack_channels))
        return lambda: None
    monkeypatch.setattr(speed, "training_step", recorded)
    resets = []   # a compiled row compiles afresh: Dynamo stops compiling one function after 8 settings
    monkeypatch.setattr(torch._dynamo, "reset", lambda: resets.append(len(asked)))
    recipe = config_recipe(batch_size=2, seq_len=3, crop=8)
    row = speed.timed_training_row("Ours", TINY["edsr"](), recipe, "cpu", 1, 0, path="p", bf16=True,
                                   channels_last=True, compile="default")
    plain = speed.timed_training_row("stack", TINY["edsr"](), dataclasses.replace(recipe, ema=None), "cpu", 1, 0,
                                     stack_channels=4)
    assert asked == [("bf16", True, "default", recipe.lr, None), ("fp32", False, None, recipe.lr, 4)]
    assert resets == [0]                                   # before the compiled row's step, not the eager one's
    assert row["note"].startswith("the trainer's step: HDR encode, loss without perceptual, clip, Adam, EMA; "
                                  "first call (compile) ")
    assert plain["note"] == "L1 loss, then the trainer's clip, Adam"


def test_the_results_page_gives_the_compiled_step_beside_the_eager_one_and_the_conv_stacks(tmp_path):
    """A speed table with the trainer's train.compile rows: the page's column names the mode, models not
    compiled read '-', and the conv stack's steps (the 2x target of issue #62 is against it) follow."""
    from bench.experiments.results_page import speed_section
    from bench.experiments import speed
    stack = "3x3 conv stack (4 x 8 ch)"
    rows = [{"section": "inference", "method": m, "fast path": "fp32", "ms": ms} for m, ms in (("Ours", 28.4), ("EDSR", 26.8))]
    rows += [{"section": "training step", "method": m, "fast path": p, "ms": ms} for m, p, ms in (
        (stack, "fp32", 19.44), (stack, "fp32, compiled (reduce-overhead)", 14.68), ("Ours", "fp32", 140.9),
        ("Ours", "bf16+channels_last, fused sampler, compiled (reduce-overhead)", 29.4),  # CUDA's bf16 graphed step
        ("Ours", "fp32, compiled (reduce-overhead)", 37.48), ("EDSR", "fp32", 28.2),
        ("Ours", "fp32, grid_sample sampler", 150.0))]
    out = tmp_path / "speed" / "cuda-x"
    out.mkdir(parents=True)
    table = speed._ratios(pd.DataFrame(rows, columns=speed.COLUMNS))
    # against the stack's step on its own path, else its fp32 step compiled the same way, else its eager one
    assert table["step / conv stack step"].dropna().round(3).tolist() == [
        1.0, 1.0, round(140.9 / 19.44, 3), round(29.4 / 14.68, 3), round(37.48 / 14.68, 3), round(28.2 / 19.44, 3),
        round(150.0 / 19.44, 3)]
    table.to_csv(out / "table.csv", index=False)
    text = "\n".join(speed_section(tmp_path))   # its graphed column: the fp32 graphed step, not bf16's
    assert "| model | fp32 ms/frame | auto (ms/frame) | training step ms | step ms, compiled (reduce-overhead) |" in text
    assert "| Ours | 28.4 | - | 140.9 | 37.5 |" in text and "| EDSR | 26.8 | - | 28.2 | - |" in text
    assert f"The {stack}, of Ours' MACs per pixel, for scale: a training step of 19.4 ms (fp32), 14.7 ms " \
           "(fp32, compiled (reduce-overhead))." in text

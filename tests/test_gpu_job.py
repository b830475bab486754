"""scripts/gpu_job.sh, the GPU work as one resumable command, dry-run on this CPU at the smoke preset on
tiny frames, in a copy of the project (it writes results/gpu and runs/ where it runs): what a GPU machine
would run, but for the device."""
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

from conftest import python_process

REPO = Path(__file__).resolve().parent.parent
# The tests marked slow run the job's steps on this CPU (training, rendering, spawned workers: about 130
# test-seconds of make test's ~1000 on a 2-core AVX2 host). The scripts run only on a lent GPU, so make
# test leaves them out; `make test-gpu-job` runs them, and CI (.ci/run, after make test) and
# scripts/gpu_prepare.sh (before a GPU call) run that: a change that breaks the job fails CI and stops
# before it costs device time. make test keeps the checks that need no step run: the job's records and
# tries, the speed step's overrides, the profile script, the carried wheels' pins.
TINY = ("data.lr_width=8 data.lr_height=6 data.spp=1 data.ref_spp=4 data.seq_len=2 data.max_depth=4 "
        "data.splits.train.sequences=1 data.splits.val.sequences=1 ~data.splits.generalization train.steps=2 "
        "train.crop=4 train.seq_len=2 train.batch_size=1 train.val_sequences=1 workers=1 progress=false")


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("gpu_job") / "project"
    for part in ("bench", "baselines", "conf", "scripts"):
        shutil.copytree(REPO / part, root / part, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    (root / "tests").mkdir()
    shutil.copy(REPO / "tests" / "conftest.py", root / "tests" / "conftest.py")
    for name in ("test_cuda.py", "test_fused_gpu.py"):  # what they check is the GPU's (and this suite runs them on
        (root / "tests" / name).write_text("def test_ran():\n    pass\n")  # the CPU); here: that the job runs them
    return root


def job(project: Path, *steps: str, out: Path, **env) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHON=sys.executable, DEVICE="cpu", PRESET="smoke", JOB_S="400", STEP_S="300",
               OUT=str(out), SOTA_ARGS=TINY, **env)
    return subprocess.run(["bash", "scripts/gpu_job.sh", *steps], cwd=project, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def first(project, tmp_path_factory):
    """The job's first call on a bare project: the kernel tests, then Table 5, on a machine without pyoidn
    as the GPU image is (its wheel, 88 MB, does not fit a call)."""
    out = tmp_path_factory.mktemp("first")
    shim = tmp_path_factory.mktemp("no_pyoidn")
    (shim / "pyoidn.py").write_text('raise ModuleNotFoundError("No module named pyoidn here", name="pyoidn")\n')
    done = job(project, "tests", "sota", out=out, PYTHONPATH=str(shim))
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    return out


@pytest.mark.slow  # a step of the job run on this CPU: make test-gpu-job (the note at the top)
def test_the_job_tests_renders_trains_scores_and_packs_then_a_second_call_skips_what_is_done(project, first, tmp_path):
    record = next((project / "results" / "gpu" / "cuda_tests").glob("*.txt")).read_text()
    assert record.startswith("failed (no CUDA GPU")                      # never "passed" without a GPU
    table = (project / "results" / "gpu" / "sota" / "table.md").read_text()
    assert "| Ours |" in table and "| Input bilinear |" in table
    # OIDN's rows are left out where pyoidn does not import, and the caption says so (it failed at its first row)
    assert "| OIDN" not in table
    assert ("Left out because their model does not import on the machine that wrote this table "
            "(experiment.leave_out_unavailable): OIDN at LR then bilinear (ModuleNotFoundError: No module named "
            "pyoidn here); OIDN at HR after bilinear (ModuleNotFoundError: No module named pyoidn here).") in table
    back = sorted(p.name for p in first.iterdir())
    assert {"log.txt", "results.tar.gz"} <= set(back)  # every training finished: in the archive, no runs part
    assert not any(n.startswith("runs.tar.gz.part-") for n in back)
    assert len(back) <= 8 and all((first / n).stat().st_size <= 16 * 2**20 for n in back)
    with tarfile.open(first / "results.tar.gz") as packed:
        assert any(n.startswith("results/gpu/runs/train/") and n.endswith("run.json") for n in packed.getnames())
    unfinished = project / "runs" / "train" / "0123456789abcdef"   # a training stopped at its limit
    unfinished.mkdir(parents=True)
    (unfinished / "run.json").write_text('{"status": "interrupted"}')
    (unfinished / "checkpoint.pt").write_bytes(b"weights")
    second = job(project, "sota", out=tmp_path / "second")
    assert second.returncode == 0 and "gpu_job: sota table already there" in second.stdout, second.stdout[-3000:]
    parts = sorted((tmp_path / "second").glob("runs.tar.gz.part-*"))
    with tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in parts))) as packed:
        folder = f"runs/train/{unfinished.name}"
        assert sorted(packed.getnames()) == [folder, f"{folder}/checkpoint.pt", f"{folder}/run.json"]


@pytest.mark.slow  # a step of the job run on this CPU: make test-gpu-job (the note at the top)
def test_the_kernel_tests_run_again_for_a_code_change_not_for_a_comment(project, first, tmp_path):
    """A record that the kernel tests passed counts for the kernels' code it names (their syntax trees):
    a comment added to a kernel file keeps it, a statement makes the job test them again."""
    project = shutil.copytree(project, tmp_path / "project", ignore=shutil.ignore_patterns("runs"))  # none to pack
    (record,) = (project / "results" / "gpu" / "cuda_tests").glob("*.txt")   # the first call's (failed: no GPU)
    kernels_line = next(line for line in record.read_text().splitlines() if line.startswith("kernels: "))
    record.write_text(f"passed\n{kernels_line}\n")                     # as a GPU machine would have left it
    kernels = project / "bench" / "nn" / "triton_kernels.py"
    kernels.write_text(kernels.read_text() + "\n# a comment changes no kernel\n")
    kept = job(project, "tests", out=tmp_path / "kept")
    assert "gpu_job: tests already passed with these kernels" in kept.stdout, kept.stdout[-2000:]
    kernels.write_text(kernels.read_text() + "\nKERNELS_EDITED = True\n")
    record.write_text(f"passed\n{kernels_line}\n")
    again = job(project, "tests", out=tmp_path / "again")
    assert "already passed" not in again.stdout and record.read_text().startswith("failed (no CUDA GPU")


def test_a_speed_table_or_sweep_stopped_at_its_limit_is_timed_again(tmp_path):
    """A step is skipped when its record is there and finished: the speed table's caption and the sweep's
    record say PARTIAL until their last section is in (tests/test_speed.py), and the next call runs
    the step again instead of bringing back a table that lacks models."""
    script = (REPO / "scripts" / "gpu_job.sh").read_text()
    start = script.index("finished() {")
    functions = script[start:script.index("\n", script.index("tried() "))]     # the two, whole
    # the speed table goes on from its last section (tests/test_speed.py): it gets 4 tries, the others 2
    assert 'finished "results/gpu/speed/$tag/table.md" 4;' in script and 'tried "results/gpu/speed/$tag/table.md"' in script
    for step in ("step_sweep", "step_render", "step_concurrency"):   # the records of the sweep and the probes
        body = script[script.index(f"{step}() {{"):script.index("\n}\n", script.index(f"{step}() {{"))]
        assert 'if finished "$record"' in body and 'tried "$record"' in body, step
    (tmp_path / "partial.md").write_text("PARTIAL: not every section is timed yet. Speed on x\n")
    (tmp_path / "sweep.md").write_text("# sweep\n\n## fp32 (TF32 dots)\n\nPARTIAL: stopped before bf16 was timed.\n")
    (tmp_path / "done.md").write_text("Speed on x CPU; preset gpu widths, untrained weights.\n\n| a |\n")

    def finished(name, tries=0, *cap):
        for _ in range(tries):   # a step started (and stopped at its limit) this many times
            subprocess.run(["bash", "-c", f'{functions}\ntried "$1"', "-", str(tmp_path / name)], check=True)
        return subprocess.run(["bash", "-c", f'{functions}\nfinished "$@"', "-", str(tmp_path / name), *cap],
                              capture_output=True, text=True).returncode
    assert {name: finished(name) for name in ("missing.md", "partial.md", "sweep.md", "done.md")} == \
        {"missing.md": 1, "partial.md": 1, "sweep.md": 1, "done.md": 0}
    assert finished("partial.md", tries=1) == 1          # stopped once: run again
    assert finished("partial.md", tries=1) == 0          # stopped twice: kept as it is, not a third time
    assert finished("partial.md", 0, "4") == 1           # with 4 tries (the speed table's): two more
    assert finished("partial.md", 2, "4") == 0


def test_the_speed_step_times_the_graphed_training_step_at_the_presets_batch(project, tmp_path):
    """The speed step's overrides, as the job passes them, compose to a training section with the preset's
    batch, frames and crop AND train.compile=reduce-overhead: its default SPEED_ARGS once nulled
    experiment.train after the compile was set, and no graphed step was ever timed."""
    from hydra import compose, initialize_config_dir
    calls = tmp_path / "calls.txt"
    wrapper = tmp_path / "python"   # python itself, but for `-m bench`, whose arguments it writes down
    wrapper.write_text(f'#!/bin/bash\nif [ "$1 $2" = "-m bench" ]; then shift 2; echo "$@" >> {calls}; exit 0; fi\n'
                       f'exec {sys.executable} "$@"\n')
    wrapper.chmod(0o755)
    env = dict(os.environ, PYTHON=str(wrapper), DEVICE="cpu", PRESET="gpu", OUT=str(tmp_path / "out"))
    project = shutil.copytree(project, tmp_path / "project", ignore=shutil.ignore_patterns("runs", "results"))
    done = subprocess.run(["bash", "scripts/gpu_job.sh", "speed"], cwd=project, env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:]
    overrides = calls.read_text().split()
    assert overrides[0] == "+experiment=speed"
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose("config", overrides=overrides)
    train = cfg.experiment.train
    assert train.compile == "reduce-overhead" and list(train.compiled) == ["Ours", "EDSR", "RAE", "KPCN", "CFM"]
    assert (train.batch, train.frames, train.crop) == (None, None, None)   # the preset's: 4 x 7 x 64
    assert (cfg.train.batch_size, cfg.train.seq_len, cfg.train.crop) == (4, 7, 64) and cfg.experiment.tiled.uhd is False
    assert cfg.results_dir == "results/gpu"          # where the job looks for it and packs it, at any preset


@pytest.mark.slow  # a step of the job run on this CPU: make test-gpu-job (the note at the top)
def test_the_plan_step_projects_table_5_from_this_machines_records_once(project, tmp_path):
    """`plan` reads the render probe and speed table recorded under the machine's own tag (here the
    committed H200 records, named for this CPU) and writes its projection; a second call keeps it."""
    from bench.machine import device_tag
    project = shutil.copytree(project, tmp_path / "project", ignore=shutil.ignore_patterns("runs", "results"))
    shutil.copytree(REPO / "results" / "cpu" / "claims", project / "results" / "cpu" / "claims")
    tag = device_tag("cpu")
    data, speed = project / "results" / "gpu" / "data", project / "results" / "gpu" / "speed" / tag
    data.mkdir(parents=True)
    speed.mkdir(parents=True)
    shutil.copy(REPO / "results/gpu/data/cuda-nvidia-h200-render-probe.md", data / f"{tag}-render-probe.md")
    for name in ("table.csv", "table.md"):
        shutil.copy(REPO / "results/gpu/speed/cuda-nvidia-h200" / name, speed / name)
    env = dict(os.environ, PYTHON=sys.executable, DEVICE="cpu", PRESET="gpu", OUT=str(tmp_path / "out"),
               SOTA_ARGS="data.lr_width=32 data.lr_height=16 train.steps=400")   # small frames: quick scoring
    done = subprocess.run(["bash", "scripts/gpu_job.sh", "plan"], cwd=project, env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0 and "gpu_job: plan exit 0" in done.stdout, done.stdout[-2000:] + done.stderr[-2000:]
    record = project / "results" / "gpu" / "profile" / f"{tag}-speedrun-plan.md"
    text = record.read_text()
    assert text.startswith(f"# sota at preset gpu on {tag}, projected") and "| render | train: " in text
    assert "| train | Ours: 3 x (400 steps x 136.3 ms" in text and "total: " in text and "power at 0.1 dB" in text
    again = subprocess.run(["bash", "scripts/gpu_job.sh", "plan"], cwd=project, env=env, capture_output=True,
                           text=True, timeout=300)
    assert "gpu_job: plan already there" in again.stdout and record.read_text() == text


@pytest.mark.slow  # a step of the job run on this CPU: make test-gpu-job (the note at the top)
def test_the_render_step_measures_the_variant_twice_and_keeps_the_digests(project, tmp_path):
    """`render` (scripts/gpu_render_probe.py): on a CPU the LLVM variant stands in for cuda_ad_rgb; two
    renders of the same frames in one process are compared layer by layer, then by two processes at once
    and against another variant (here the same one: no difference); the digests are kept and a later
    run compares its own with them (a second call skips the step: finished(), tested below). A variant
    that cannot start is a PARTIAL record (tried again once)."""
    project = shutil.copytree(project, tmp_path / "project", ignore=shutil.ignore_patterns("runs", "results"))
    env = dict(os.environ, PYTHON=sys.executable, DEVICE="cpu", PRESET="smoke", OUT=str(tmp_path / "out"),
               RENDER_ARGS="--families 1 --workers 2 --compare llvm_ad_rgb --compare-frames 1")
    done = subprocess.run(["bash", "scripts/gpu_job.sh", "render"], cwd=project, env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0 and "gpu_job: render exit 0" in done.stdout, done.stdout[-3000:]
    (record,) = (project / "results" / "gpu" / "data").glob("*-render-probe.md")
    text = record.read_text()
    assert text.startswith("# Rendering `smoke` with llvm_ad_rgb")                   # whole: no PARTIAL line
    assert "- pass 1 against pass 2: 30 of 30 decoded layers bit-identical" in text   # 3 frames x 10 layers
    assert "- pass 3: the same 3 frames by 2 processes at once" in text   # one sequence: rendered in this process
    assert "from the host's kernel cache (one sequence, rendered in this process)" in text
    assert "- train: 32 sequences, 96 frames at ref 256 spp: about" in text
    assert "relative L2 difference per layer: hr.albedo 0, " in text                   # llvm against llvm
    digests = json.loads(record.with_suffix(".digests.json").read_text())
    assert digests["variant"] == "llvm_ad_rgb" and len(digests["frames"]) == 3
    later = python_process("scripts/gpu_render_probe.py", "--data", "smoke", "--families", "1", "--variant",
                           "llvm_ad_rgb", "--out", record, cwd=project, timeout=300)
    assert "as committed (written on cpu): 3 of 3 frames' digests equal" in later.stdout, later.stdout[-2000:]
    import torch
    if not torch.cuda.is_available():
        failed = python_process("scripts/gpu_render_probe.py", "--data", "smoke", "--variant", "cuda_ad_rgb",
                                "--out", tmp_path / "cuda.md", cwd=project, timeout=300)
        said = (tmp_path / "cuda.md").read_text()
        assert failed.returncode == 1 and said.startswith("PARTIAL: the variant did not start"), said


@pytest.mark.slow  # a step of the job run on this CPU: make test-gpu-job (the note at the top)
def test_the_concurrency_probe_goes_on_from_a_partial_record_and_a_dead_worker_is_its_row(tmp_path, capsys,
                                                                                           monkeypatch):
    """scripts/gpu_step_concurrency.py (the job's `concurrency` step): a worker that dies without a word
    after warming up releases the others at the barrier and is its configuration's row, not a hang; a
    PARTIAL record of another machine, or of other settings, is timed again. The configurations a PARTIAL
    record of the same machine and settings already holds are kept (a step stopped at its limit goes on),
    two processes at once take training steps, each on its share of the cores, against the kept
    one-process row; the record is whole once every configuration is in."""
    monkeypatch.syspath_prepend(str(REPO / "scripts"))
    from gpu_step_concurrency import done_rows
    from bench.scheduler import threads_per_job
    command = ["scripts/gpu_step_concurrency.py", "--device", "cpu", "--preset", "smoke", "--models", "edsr",
               "--steps", "2", "--warmup", "1", "--timeout", "120"]
    kept_row = "| EDSR | none | 1 | 2 | 50.0 | 20.00 | 1.00 |"   # as if an earlier call, stopped, had timed it
    dies = tmp_path / "dies.md"   # a PARTIAL record of another machine and settings: not kept
    dies.write_text("PARTIAL: 1 of 2 configurations timed\n# Training steps of several processes at once on "
                    f"cuda-another-gpu\n\n`...`: other settings ms/step\n\n{kept_row}\n")
    died = python_process(*command, "--processes", "1", "--out", dies, timeout=300,
                          env=dict(os.environ, SRD_BENCH_TEST_WORKER_EXIT="1:0"))
    assert died.returncode == 0, died.stdout[-2000:] + died.stderr[-2000:]
    assert "a PARTIAL record of another machine or other settings" in died.stdout
    text = dies.read_text()
    assert "| EDSR | none | 1 | - | - | - | failed: a process exited with code 3 without a word |" in text
    assert kept_row not in text
    header = text.split("\n| EDSR | none | 1 |")[0]          # this machine's title and settings
    title, settings = header.splitlines()[0], re.search(r"`: (.+) ms/step: ", header).group(1)
    other = tmp_path / "other.md"  # the same machine, other settings (20 timed steps); then the other way round
    for other_header in (header.replace("then 2 timed", "then 20 timed"), header.replace(title, f"{title}-another")):
        assert other_header != header
        other.write_text(f"PARTIAL: 1 of 2 configurations timed\n{other_header}\n{kept_row}\n")
        capsys.readouterr()
        assert done_rows(other, title, settings) == {}
        assert "a PARTIAL record of another machine or other settings" in capsys.readouterr().out
    out = tmp_path / "concurrency.md"
    out.write_text(f"PARTIAL: 1 of 2 configurations timed\n{header}\n{kept_row}\n")
    assert done_rows(out, title, settings) == {("EDSR", "none", "1"): kept_row}
    done = python_process(*command, "--processes", "1", "2", "--out", out, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    text = out.read_text()
    assert text.startswith("# Training steps of several processes at once on cpu-")      # whole: no PARTIAL
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in text.splitlines() if line.startswith("| EDSR |")]
    assert rows[0] == ["EDSR", "none", "1", "2", "50.0", "20.00", "1.00"]                  # kept, not timed again
    assert rows[1][:4] == ["EDSR", "none", "2", str(threads_per_job(2))] and float(rows[1][4]) > 0
    assert float(rows[1][6]) == pytest.approx(float(rows[1][5]) / 20.0, abs=0.01)        # against the kept row


def test_the_profile_script_profiles_the_trainers_step_at_the_presets_recipe(tmp_path):
    """scripts/gpu_profile_step.py profiles bench.experiments.speed.training_step (the trainer's step, as
    the speed table times it), at the preset's recipe unless told otherwise; no CUDA here: CPU columns."""
    out = tmp_path / "profile.md"
    done = python_process("scripts/gpu_profile_step.py", "--device", "cpu", "--preset", "smoke", "--frames", "2",
                          "--crop", "16", "--channels", "8", "--steps", "1", "--warmup", "1", "--no-compile",
                          "--out", out, timeout=300, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert done.returncode == 0, done.stderr[-2000:]
    from hydra import compose, initialize_config_dir
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        batch = compose("config", overrides=["preset=smoke"]).train.batch_size
    text = out.read_text()
    assert (f"batch {batch} x 2 frames of 16x16 LR at preset smoke, the trainer's step: HDR encode, loss without "
            "perceptual, clip, Adam, EMA, fp32") in text and "No CUDA here" in text
    assert "\n| eager | " in text and "\n| torch.compile |" not in text


def test_the_carried_wheels_are_the_projects_pins_and_scoring_without_flip_is_said_before_training(project, tmp_path):
    """The GPU image lacks flip_evaluator (every evaluation's FLIP scores) as it lacks mitsuba: gpu_prepare
    carries both at pyproject's pins, and without them the sota step says so before it trains anything."""
    import tomllib
    pins = dict(dep.split("==") for dep in tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"])
    prepare = (REPO / "scripts" / "gpu_prepare.sh").read_text()
    downloaded = re.search(r"^download \.whl (.*)$", prepare, re.M).group(1).split()
    assert "flip-evaluator==1.7" in downloaded and "mitsuba==3.9.1" in downloaded
    assert all(pins[name] == version for name, version in (d.split("==") for d in downloaded))
    shim = tmp_path / "no_flip"
    shim.mkdir()
    (shim / "flip_evaluator.py").write_text('raise ModuleNotFoundError("No module named flip_evaluator", name="flip_evaluator")\n')
    (shim / "mitsuba.py").write_text("")   # mitsuba there: only flip_evaluator is missing
    copy = shutil.copytree(project, tmp_path / "project", ignore=shutil.ignore_patterns("runs", "results"))
    done = job(copy, "sota", "plan", out=tmp_path / "out", PYTHONPATH=str(shim))
    assert done.returncode == 0, done.stdout[-2000:]
    assert "gpu_job: no flip_evaluator here (carry .whl): sota skipped" in done.stdout   # the one missing
    assert "gpu_job: no flip_evaluator here (carry .whl): plan skipped" in done.stdout
    assert not (copy / "results" / "gpu" / "sota").exists() and not (copy / "runs").exists()

"""bench.measure: the fast-path chooser never times an emulated path, never picks an incorrect one,
picks the fastest of the rest, and measures once per machine and model."""
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from bench import machine, measure

AVX2 = {"avx2", "fma"}
AVX512_BF16 = {"avx2", "avx512f", "avx512_bf16"}


def test_bf16_is_a_candidate_only_where_it_is_native():
    assert measure.candidate_paths("cpu", AVX2) == ["fp32", "channels_last"]
    assert "channels_last+bf16" in measure.candidate_paths("cpu", AVX512_BF16)
    assert "bf16" in measure.candidate_paths("cpu", {"amx_bf16"}) and "bf16" in measure.candidate_paths("cuda:0", AVX2)


def fake_paths(monkeypatch, behaviour):
    """prepare(model, name) -> a forward that sleeps and returns what `behaviour[name]` says."""
    def prepare(model, name):
        delay, offset = behaviour[name]
        def run(x, g):
            time.sleep(delay)
            return {"final": x + offset}
        return run
    monkeypatch.setattr(measure, "prepare", prepare)
    monkeypatch.setattr(measure, "candidate_paths", lambda device: list(behaviour))


def test_the_fastest_correct_path_wins_and_a_wrong_one_is_refused(monkeypatch, tmp_path):
    model = torch.nn.Conv2d(1, 1, 1)
    x = torch.ones(1, 1, 3, 4, 4)
    fake_paths(monkeypatch, {"fp32": (0.03, 0.0), "channels_last": (0.001, 0.5), "bf16": (0.01, 0.001)})
    chosen, times = measure.choose_fast_path(model, x, None, "cpu", tmp_path / "cache.json", {"model": "m"})
    assert chosen == "bf16"                                  # fastest of those within the tolerance
    assert isinstance(times["channels_last"], str) and "off by" in times["channels_last"]
    assert times["bf16"] < times["fp32"]

    calls = []
    fake = measure.prepare
    monkeypatch.setattr(measure, "prepare", lambda model, name: calls.append(name) or fake(model, name))
    again, _ = measure.choose_fast_path(model, x, None, "cpu", tmp_path / "cache.json", {"model": "m"})
    assert again == "bf16" and calls == []                   # from the cache
    measure.choose_fast_path(model, x, None, "cpu", tmp_path / "cache.json", {"model": "other"})
    assert calls == ["fp32", "channels_last", "bf16"]        # another model is measured
    with torch.no_grad():
        model.weight.add_(1.0)                               # the same model with other (say trained) weights
    measure.choose_fast_path(model, x, None, "cpu", tmp_path / "cache.json", {"model": "m"})
    assert calls == ["fp32", "channels_last", "bf16"] * 2    # is judged on its own weights


def test_a_model_without_parameters_runs_its_own_way():
    class Bilinear(torch.nn.Module):
        def forward(self, x, g):
            return {"final": x}
    assert measure.choose_fast_path(Bilinear(), torch.ones(1, 1, 3, 4, 4), None, "cpu", None, {}) == ("fp32", {})


def test_a_path_that_fails_is_recorded_and_skipped_and_none_running_is_an_error(monkeypatch):
    model = torch.nn.Conv2d(1, 1, 1)
    x = torch.ones(1, 1, 3, 4, 4)
    fake_paths(monkeypatch, {"fp32": (0.02, 0.0), "channels_last": (0.001, 0.0)})
    fake = measure.prepare

    def compile_fails(model, name):
        if name == "channels_last":
            raise RuntimeError("no C++ compiler\nsecond line")
        return fake(model, name)
    monkeypatch.setattr(measure, "prepare", compile_fails)
    chosen, times = measure.choose_fast_path(model, x, None, "cpu", None, {})
    assert chosen == "fp32" and times["channels_last"] == "failed: RuntimeError: no C++ compiler"

    monkeypatch.setattr(measure, "prepare", lambda model, name: (_ for _ in ()).throw(OSError("nope")))
    with pytest.raises(RuntimeError, match="no fast path runs this model"):
        measure.choose_fast_path(model, x, None, "cpu", None, {})


def test_the_fused_kernels_are_the_cuda_default_unless_switched_off(monkeypatch):
    """CUDA commands take the fused kernels (tested on an H200: results/gpu/cuda_tests/) unless
    SRD_BENCH_FUSED_GPU says 0/false/off or the GPU is older than compute capability 8.0; without CUDA
    nothing changes. The variable is set for spawned workers and restored after. The GPU itself is
    checked by tests/test_cuda.py."""
    from bench.nn import fused
    monkeypatch.setenv(measure.FUSED_GPU, "placeholder")  # recorded, so the test leaves it as it found it
    monkeypatch.delenv(measure.FUSED_GPU)
    monkeypatch.setattr(fused, "_on_cuda", False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with measure.fused_kernels_on_cuda():
        assert not fused._on_cuda and measure.FUSED_GPU not in os.environ
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda: (9, 0))
    with measure.fused_kernels_on_cuda():
        assert fused._on_cuda and os.environ[measure.FUSED_GPU] == "1"  # spawned workers inherit it
    assert not fused._on_cuda and measure.FUSED_GPU not in os.environ
    for off in ("0", "false", "OFF"):
        monkeypatch.setenv(measure.FUSED_GPU, off)
        with measure.fused_kernels_on_cuda():
            assert not fused._on_cuda
    monkeypatch.delenv(measure.FUSED_GPU)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda: (7, 5))  # no bf16 tensor cores
    with measure.fused_kernels_on_cuda():
        assert not fused._on_cuda


def test_a_run_records_the_fused_kernels_it_took_by_their_digest(monkeypatch):
    """Training and evaluation records name the Triton kernels' file digest where a CUDA run took them,
    and None elsewhere: the kernels are tested to tolerances, not bit for bit, so a record says which."""
    import hashlib
    from bench.nn import fused
    monkeypatch.setattr(fused, "kernels", lambda: object())
    monkeypatch.setenv(measure.FUSED_GPU, "1")
    digest = hashlib.sha256((Path(fused.__file__).parent / "triton_kernels.py").read_bytes()).hexdigest()[:16]
    assert measure.fused_kernels_used("cuda") == digest and measure.fused_kernels_used("cuda:1") == digest
    assert measure.fused_kernels_used("cpu") is None
    monkeypatch.setenv(measure.FUSED_GPU, "0")
    assert measure.fused_kernels_used("cuda") is None
    monkeypatch.setenv(measure.FUSED_GPU, "1")
    monkeypatch.setattr(fused, "kernels", lambda: None)                 # no Triton
    assert measure.fused_kernels_used("cuda") is None


def test_training_and_evaluation_records_keep_what_fused_kernels_used_says(monkeypatch, tmp_path):
    """What measure.fused_kernels_used says for the run's device is in each training's and evaluation's
    record (a stand-in digest here: a CPU run took no Triton kernels)."""
    from bench.experiments import evaluation, training
    from conftest import bench_here
    from test_faults import TINY_CLI
    asked = []
    monkeypatch.setattr(training, "fused_kernels_used", lambda device: asked.append(device) or "digest-stand-in")
    monkeypatch.setattr(evaluation, "fused_kernels_used", lambda device: asked.append(device) or "digest-stand-in")
    done = bench_here(*TINY_CLI, f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}",
                      f"data_dir={tmp_path / 'data'}", "experiment.rows=[{label:a,model:edsr}]")
    assert done.returncode == 0, done.stderr[-2000:]
    records = {kind: [json.loads(f.read_text()) for f in (tmp_path / "runs" / kind).glob("*/run.json")]
               for kind in ("train", "eval")}
    assert len(records["train"]) == 1 and len(records["eval"]) == 1, records
    assert all(r["metrics"]["fused_kernels"] == "digest-stand-in" for rs in records.values() for r in rs)
    assert set(asked) == {"cpu"}


def test_both_entry_points_enter_the_fused_kernels_default(monkeypatch, tmp_path):
    """python -m bench and srd-bench predict do their work inside measure.fused_kernels_on_cuda: a stand-in
    that records sees the command's error (bench) or its output file (predict) appear while it is entered."""
    import contextlib
    from bench import predict
    from conftest import bench_here, srd_bench_here
    from test_predict_folders import write_lr, write_weights
    seen = []

    @contextlib.contextmanager
    def recording(out=tmp_path / "out"):
        seen.append(("enter", len(list(out.glob("**/*.exr")))))
        try:
            yield
        except Exception as err:
            seen.append(("raised", type(err).__name__))
            raise
        seen.append(("exit", len(list(out.glob("**/*.exr")))))

    monkeypatch.setattr(measure, "fused_kernels_on_cuda", recording)   # bench.cli imports it at each call
    monkeypatch.setattr(predict, "fused_kernels_on_cuda", recording)   # bench.predict, at its import
    done = bench_here("+experiment=smoke", "preset=smoke", "experiment.rows=[{label:a,model:sdr}]",
                      f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}",
                      f"data_dir={tmp_path / 'data'}")
    assert done.returncode == 2 and "unknown model 'sdr'" in done.stderr, done.stderr[-2000:]
    assert seen == [("enter", 0), ("raised", "UserError")]
    seen.clear()
    weights = write_weights(tmp_path / "rae.pt")
    frame = write_lr(tmp_path / "in" / "0000_lr.exr")
    done = srd_bench_here("predict", "--fast-path", "fp32", "--weights", weights, "--output-dir", tmp_path / "out",
                          frame)
    assert done.returncode == 0, done.stderr[-2000:]
    assert seen == [("enter", 0), ("exit", 1)]


def test_scripts_as_avx2_runs_a_command_as_on_a_cpu_with_avx2_only(tmp_path):
    """scripts/as_avx2.sh, with which docs/testing.md's AVX2 figure for `make test` was timed on an AVX-512 host:
    the suite's ISA check, Inductor's vector ISA and every -march=native C++ build see AVX2 only, and the
    compiler wrapper still reads as gcc to Inductor (named otherwise, Inductor compiles another way and
    the suite took 25% longer)."""
    if "avx512f" not in machine.cpu_flags():
        pytest.skip("this CPU has no AVX-512 to hide: the script has nothing to emulate here")
    if os.environ.get("CXX") or not shutil.which("g++"):
        pytest.skip("the march check below reads gcc's -Q --help=target")
    script = Path(__file__).resolve().parent.parent / "scripts" / "as_avx2.sh"
    probe = ("import os, subprocess; from bench import machine; "
             "from torch._inductor.cpu_vec_isa import pick_vec_isa; from torch._inductor.cpp_builder import _is_gcc; "
             "cxx = os.environ['CXX']; print(machine.cpu_isa()); print(pick_vec_isa()); print(_is_gcc(cxx)); "
             "print(subprocess.run([cxx, '-march=native', '-Q', '--help=target'], capture_output=True, text=True).stdout)")
    done = subprocess.run(["bash", str(script), sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=180, env={**os.environ, "SRD_BENCH_CACHE": str(tmp_path)})
    if done.returncode == 3:
        pytest.skip(done.stderr.strip()[:300])    # no private mount namespace, or no mount over /proc/cpuinfo
    assert done.returncode == 0, done.stderr[-2000:]
    isa, vec_isa, gcc, target = done.stdout.split("\n", 3)
    assert (isa, vec_isa, gcc) == ("AVX2 only (bf16 emulated)", "avx2", "True")
    march = re.search(r"^\s*-march=\s*(\S+)", target, re.MULTILINE)
    assert march and march.group(1) == "haswell", target[:2000]
    assert (tmp_path / "as_avx2" / "g++").exists()   # where the next run finds it: its builds stay cached


def test_the_fast_path_cache_keeps_every_process_s_choice(tmp_path):
    """jobs=N shards choose paths at once: a process writes the cache under a lock, reading it again there,
    so a choice another process wrote meanwhile is kept (and no reader sees half a file). Here the test
    holds the lock while a process measures, writes a choice of its own, then lets the process write."""
    import contextlib
    import select
    from bench.runs import acquire
    repo = Path(__file__).resolve().parent.parent
    cache = tmp_path / "fast_paths.json"
    script = ("import sys, torch; from bench import measure; from baselines.edsr import EDSR\n"
              "torch.manual_seed(0); torch.set_num_threads(1); model = EDSR(channels=4, blocks=1)\n"
              "x, g = torch.rand(1, 1, 3, 8, 8), torch.rand(1, 1, 7, 8, 8)\n"
              "measure.choose_fast_path(model, x, g, 'cpu', sys.argv[1], {'model': 'the process'}, repeats=1)\n")
    with contextlib.closing(acquire(Path(f"{cache}.lock"), "a test")):
        proc = subprocess.Popen([sys.executable, "-c", script, str(cache)], cwd=repo, stdout=subprocess.PIPE,
                                text=True, env={**os.environ, "PYTHONPATH": str(repo)})
        ready, _, _ = select.select([proc.stdout], [], [], 120)
        assert ready and "waiting for another process writing the fast-path cache" in proc.stdout.readline()
        cache.write_text(json.dumps({"another process's choice": {"path": "fp32", "ms": {}}}))
    assert proc.wait(timeout=120) == 0
    kept = json.loads(cache.read_text())
    assert "another process's choice" in kept and len(kept) == 2

"""bench.machine: a machine named from /proc/cpuinfo without torch; the ISA in words and as a tag."""
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench import machine

AVX2 = {"avx2", "fma"}
AVX512_BF16 = {"avx2", "avx512f", "avx512_bf16"}


def test_the_isa_in_words_says_whether_bf16_is_native():
    assert machine.cpu_isa(AVX2) == "AVX2 only (bf16 emulated)"
    assert machine.cpu_isa(AVX512_BF16) == "AVX512-BF16 (bf16 native)"
    assert machine.cpu_isa({"avx512_bf16", "amx_bf16"}) == "AVX512-BF16 + AMX-BF16 (bf16 native)"
    assert machine.cpu_isa({"avx2", "avx512f"}) == "AVX-512 without BF16 (bf16 emulated)"
    assert machine.cpu_isa({"sse2"}) == "no AVX2 (bf16 emulated)" and machine.cpu_isa(set()).startswith("ISA unknown")


def test_the_isa_tag_names_the_widest_vector_extension():
    assert machine.isa_tag(AVX512_BF16) == "avx512-bf16" and machine.isa_tag({"avx512_bf16", "amx_bf16"}) == "amx"
    assert machine.isa_tag({"avx2", "avx512f"}) == "avx512" and machine.isa_tag({"sse2", "avx2"}) == "avx2"
    assert machine.isa_tag({"sse2"}) == "no-avx2" and machine.isa_tag(set()) == "isa-unknown"


def test_the_device_tag_is_a_directory_name_that_names_the_isa():
    tag = machine.device_tag("cpu")
    assert tag.startswith("cpu-") and tag == tag.lower() and "/" not in tag and " " not in tag
    assert tag.endswith("-" + machine.isa_tag())


def test_a_gpu_tag_is_its_model_name(monkeypatch):
    monkeypatch.setattr(machine, "gpu_model", lambda device: "NVIDIA H200 (TM)")
    assert machine.device_tag("cuda:0") == "cuda-nvidia-h200"


def test_cpu_identity_tells_two_cpus_of_one_model_name_apart():
    info = "processor\t: 0\ncpu family\t: 25\nmodel\t\t: 17\nmodel name\t: AMD EPYC\nstepping\t: 1\ncpu MHz\t\t: 2596.132\n"
    assert machine.cpu_identity(info, "32768K") == "x86 family 25 model 17 stepping 1, 2596 MHz, L3 32768K"
    assert machine.cpu_identity("", "") == ""


def test_naming_the_machine_imports_no_torch():
    """What the GPU scripts and the render probe call to name a machine starts in a fraction of a second."""
    code = ("import sys; from bench.machine import cpu_isa, device_tag; device_tag('cpu'); cpu_isa(); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'numpy', 'pandas')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr[-2000:]


@pytest.mark.parametrize("flags", [AVX2, AVX512_BF16])
def test_bf16_is_native_for_the_chooser_where_the_isa_in_words_says_so(flags):
    from bench import measure
    assert measure.native_bf16("cpu", flags) == ("native" in machine.cpu_isa(flags))


def test_time_make_test_times_a_clean_clone_at_the_commit_and_names_the_machine(tmp_path):
    """scripts/time_make_test.sh, which measures the README's `make test` figure: it runs `make test` in a
    fresh clone at the commit asked for, with an empty Inductor cache, and reports pytest's summary, make's
    status and this machine. Here `make` is a stand-in that says where it ran and fails one test."""
    repo = Path(__file__).resolve().parent.parent
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "make").write_text(
        '#!/bin/bash\necho "target $1 at $(git rev-parse --short HEAD) in $PWD"\n'
        'echo "inductor cache $TORCHINDUCTOR_CACHE_DIR holds $(ls -A "$TORCHINDUCTOR_CACHE_DIR" 2>/dev/null | wc -l)"\n'
        'echo "====== 1 failed, 2 passed, 3 skipped in 0.50s ======"\nexit 2\n')  # make's status for a failed recipe
    (bin_dir / "make").chmod(0o755)
    root = subprocess.run(["git", "rev-list", "--max-parents=0", "HEAD"], cwd=repo, capture_output=True, text=True,
                          check=True).stdout.split()[0]
    first = subprocess.run(["git", "rev-parse", "--short", root], cwd=repo, capture_output=True, text=True,
                           check=True).stdout.strip()
    done = subprocess.run(["bash", str(repo / "scripts" / "time_make_test.sh"), root], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}",
                                            "TMPDIR": str(tmp_path)})
    assert done.returncode == 2, done.stdout + done.stderr                    # make's status
    lines = done.stdout.splitlines()
    assert re.fullmatch(rf"make test at {first}: \d+ s wall, rc 2; pytest: 1 failed, 2 passed, 3 skipped in 0.50s",
                        lines[0]), lines
    assert lines[1].startswith(f"on {machine.cpu_model().strip()} (") and machine.cpu_isa() in lines[1]
    assert "load average before: " in lines[1]
    (log,) = tmp_path.glob("srd-bench-make-test.*/make-test.log")
    ran = log.read_text()
    assert f"target test at {first} in {log.parent / 'clone'}" in ran and "holds 0" in ran
    assert sorted(p.name for p in log.parent.iterdir()) == ["make-test.log"]  # the clone is gone
    bad = subprocess.run(["bash", str(repo / "scripts" / "time_make_test.sh"), "no-such-commit"], capture_output=True,
                         text=True, timeout=60, env={**os.environ, "TMPDIR": str(tmp_path / "bad")})
    assert bad.returncode == 3 and "time_make_test: no commit no-such-commit" in bad.stderr   # not make's 2

"""bench.machine: a machine named from /proc/cpuinfo without torch; the ISA in words and as a tag."""
import subprocess
import sys

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
def test_the_fast_path_chooser_reads_the_same_flags(flags):
    from bench import measure
    assert measure.native_bf16("cpu", flags) == ("native" in machine.cpu_isa(flags))

"""This machine, named: the CPU's model, feature flags and vector ISA, and a directory tag for what
describes one machine (speed tables, the GPU records). Python's standard library only (torch is imported
to name a GPU, where one is asked for), so the speed experiment, the fast-path chooser and the GPU scripts
name a machine one way, and a script that only needs the name loads nothing heavy. (bench/nn/native.py keys
its -march=native builds on the model name and flags itself: bench/nn may not import this module.)"""
from __future__ import annotations

import contextlib
import platform
import re
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")


def cpu_flags() -> set[str]:
    """The CPU's feature flags (/proc/cpuinfo); empty where that cannot be read."""
    try:
        found = re.search(r"^flags\s*:\s*(.+)$", CPUINFO.read_text(), re.MULTILINE)
    except OSError:
        return set()
    return set(found.group(1).split()) if found else set()


def cpu_isa(flags: set[str] | None = None) -> str:
    """The vector ISA that decides the fast paths, in words: whether bf16 runs natively (AVX512-BF16 or
    AMX) or is emulated (AVX2 only, where it is several times slower than fp32)."""
    flags = cpu_flags() if flags is None else flags
    if not flags:
        return f"ISA unknown ({platform.machine()})"
    native = [name for flag, name in (("avx512_bf16", "AVX512-BF16"), ("amx_bf16", "AMX-BF16")) if flag in flags]
    if native:
        return " + ".join(native) + " (bf16 native)"
    if "avx512f" in flags:
        return "AVX-512 without BF16 (bf16 emulated)"
    return "AVX2 only (bf16 emulated)" if "avx2" in flags else "no AVX2 (bf16 emulated)"


def isa_tag(flags: set[str] | None = None) -> str:
    """The CPU's vector ISA as a name part: amx, avx512-bf16, avx512, avx2 or no-avx2 (the speed of
    every path, bf16 above all, depends on it more than on the model name)."""
    flags = cpu_flags() if flags is None else flags
    for flag, tag in (("amx_bf16", "amx"), ("avx512_bf16", "avx512-bf16"), ("avx512f", "avx512"), ("avx2", "avx2")):
        if flag in flags:
            return tag
    return "no-avx2" if flags else "isa-unknown"


def cpu_model() -> str:
    """This CPU's model name, as /proc/cpuinfo gives it."""
    name = platform.processor() or "unknown"
    with contextlib.suppress(OSError):
        found = re.search(r"model name\s*:\s*(.+)", CPUINFO.read_text())
        name = found.group(1) if found else name
    return name


def cpu_identity(cpuinfo: str | None = None, l3: str | None = None) -> str:
    """What tells two CPUs of one model name apart (/proc/cpuinfo: x86 family, model, stepping, clock; the
    L3 cache): a cloud model name such as "AMD EPYC" covers hosts 1.4-2.2x apart in these tables. '' where
    /proc cannot be read."""
    with contextlib.suppress(OSError):
        cpuinfo = CPUINFO.read_text() if cpuinfo is None else cpuinfo
        l3 = Path("/sys/devices/system/cpu/cpu0/cache/index3/size").read_text().strip() if l3 is None else l3
    fields = {key: re.search(rf"^{key}\s*:\s*(.+)$", cpuinfo or "", re.MULTILINE) for key in
              ("cpu family", "model", "stepping", "cpu MHz")}
    said = {key: found.group(1).strip() for key, found in fields.items() if found}
    parts = ([f"x86 family {said['cpu family']} model {said['model']} stepping {said.get('stepping', '?')}"]
             if "cpu family" in said and "model" in said else [])
    parts += [f"{float(said['cpu MHz']):.0f} MHz"] if "cpu MHz" in said else []
    parts += [f"L3 {l3}"] if l3 else []
    return ", ".join(parts)


def gpu_model(device: str) -> str:
    """The GPU's model name, as CUDA gives it."""
    import torch  # here, not above: naming a CPU needs no torch
    return torch.cuda.get_device_name(torch.device(device))


def device_tag(device: str) -> str:
    """A directory name for the machine: cpu-<cpu model>-<ISA> or cuda-<gpu model>, lower case (one
    cloud CPU model name covers AVX2-only and AVX512-BF16 hosts)."""
    cuda = str(device).startswith("cuda")
    slug = re.sub(r"\(r\)|\(tm\)|cpu|processor|@.*|\d+-core", " ", (gpu_model(device) if cuda else cpu_model()).lower())
    slug = re.sub(r"[^a-z0-9]+", "-", slug).strip("-")
    return f"cuda-{slug or 'unknown'}" if cuda else f"cpu-{slug or 'unknown'}-{isa_tag()}"

"""Trims a mitsuba wheel in place to what the suite loads, so that it travels to a lent GPU machine with
the working tree (64 MiB a call; scripts/gpu_prepare.sh):
  - the variants the suite sets (bench.render: cuda_ad_rgb, llvm_ad_rgb, scalar_rgb), no headers;
  - the plugins that rendering every scene family loads (scripts/mitsuba_plugins.py, llvm_ad_rgb,
    14 families x 4 seeds, mitsuba 3.9.1: 23 plugins) and a margin of the next likely ones;
  - no srgb.coeff (the RGB-to-spectrum table of the spectral variants, 8.9 MB);
and recompresses it with LZMA (pip installs such wheels: Python's zipfile reads them): mitsuba 3.9.1
cp311 59.8 MiB -> 26.4 trimmed -> 16.3 with LZMA. Other wheels given (drjit) are only recompressed.
A trimmed cp311 wheel installed with --target renders every family: see scripts/mitsuba_plugins.py.
Usage: python scripts/trim_mitsuba_wheel.py WHEEL ...
"""
import os
import re
import sys
import zipfile

VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
LOADED = ("area", "box", "checkerboard", "constant", "cube", "dielectric", "diffuse", "directional", "disk",
          "hdrfilm", "independent", "merge", "path", "perspective", "ply", "principled", "rectangle",
          "roughconductor", "roughplastic", "sphere", "srgb", "twosided", "uniform")
MARGIN = ("bitmap", "conductor", "plastic", "roughdielectric", "thindielectric", "gaussian", "point", "spot",
          "envmap", "obj", "direct", "aov", "mask", "blendbsdf", "stratified", "regular")
KEEP_PLUGINS = set(LOADED + MARGIN)


def dropped(name: str) -> bool:
    """A file of the wheel the suite never loads."""
    if name.startswith("mitsuba/include/") or name == "mitsuba/data/srgb.coeff":
        return True
    variant = re.match(r"mitsuba/((scalar|llvm_ad|cuda_ad)_\w+)\.cpython", name)
    if variant:
        return variant.group(1) not in VARIANTS
    plugin = re.match(r"mitsuba/plugins/(\w+)\.so$", name)
    return bool(plugin) and plugin.group(1) not in KEEP_PLUGINS


def trim(path: str) -> None:
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(path + ".tmp", "w", zipfile.ZIP_LZMA) as dst:
        for item in src.infolist():
            if dropped(item.filename):
                continue
            data = src.read(item)
            if item.filename.endswith(".dist-info/RECORD"):
                data = "".join(line for line in data.decode().splitlines(True)
                               if not dropped(line.split(",")[0])).encode()
            dst.writestr(item, data, compress_type=zipfile.ZIP_LZMA)
    before = os.path.getsize(path)
    os.replace(path + ".tmp", path)
    print(f"trim_mitsuba_wheel: {os.path.basename(path)} {before / 2**20:.1f} -> {os.path.getsize(path) / 2**20:.1f} MiB")


if __name__ == "__main__":
    if {"-h", "--help"} & set(sys.argv[1:]):
        print(__doc__)
        sys.exit(0)
    if not sys.argv[1:]:
        sys.exit(__doc__)
    for wheel in sys.argv[1:]:
        if not zipfile.is_zipfile(wheel):
            sys.exit(f"error: trim_mitsuba_wheel: {wheel} is not a wheel (a zip file)")
        trim(wheel)

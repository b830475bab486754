"""Renders every scene family (bench.scenes.FAMILIES) at a tiny size in the given Mitsuba variants and
prints the plugins (mitsuba/plugins/*.so) this process loaded, one name a line: what
scripts/gpu_prepare.sh keeps of the mitsuba wheel. Exits 1 when a render fails or is not finite.
    python scripts/mitsuba_plugins.py [--seeds N] [VARIANT ...]     (default: llvm_ad_rgb; the
    srd_gbuffer integrator does not run in scalar_rgb, whose bsdf.sample takes a bool mask)
"""
import argparse
import os
import re
import sys

import numpy as np

from bench import render, scenes


def loaded_plugins() -> set[str]:
    """Names of the mitsuba plugin libraries mapped into this process."""
    with open("/proc/self/maps") as maps:
        return set(re.findall(r"/mitsuba/plugins/(\w+)\.so$", maps.read(), re.M))


def render_every_family(variant: str, seeds: int) -> None:
    """Each family at `seeds` scene seeds (its materials are drawn per seed), 16x12 pixels, 2 spp."""
    for family in scenes.FAMILIES:
        for seed in range(seeds):
            camera = scenes.camera_path(seed, 0, 1)[0]
            out = render.render_view(scenes.make_scene(family, seed), camera, 16, 12, 2, seed, variant=variant)
            if not np.isfinite(out["radiance"]).any():
                sys.exit(f"mitsuba_plugins: {variant} {family} seed {seed}: no finite pixel")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("variants", nargs="*", default=["llvm_ad_rgb"])
    parser.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args()
    render.pick_variant()   # sets DRJIT_LIBLLVM_PATH for the LLVM backend
    for variant in args.variants:
        render_every_family(variant, args.seeds)
        print(f"mitsuba_plugins: {variant} rendered {len(scenes.FAMILIES)} families x {args.seeds} seeds "
              f"from {os.path.dirname(render._mi.__file__)}", file=sys.stderr)
    print("\n".join(sorted(loaded_plugins())))


if __name__ == "__main__":
    main()

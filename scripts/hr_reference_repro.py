"""Two renders of one HR frame (192 x 128, the cpu preset's HR size) from one loaded scene, compared bit for bit
at 170 samples per call (the cpu preset's references: pixels straddle the LLVM backend's 32768-sample blocks)
and at 128 (which divides 32768). Prints the differing pixels and their largest relative difference
(docs/data.md, "Reproducibility"). Usage: PYTHONPATH=$PWD python scripts/hr_reference_repro.py [family]"""
import sys

import numpy as np

from bench import render, scenes


def compare(scene, camera, spp):
    first, second = (render.render_view(scene, camera, 192, 128, spp, seed=5, passes=())["radiance"]
                     for _ in range(2))
    differs = first != second
    pixels = differs.any(axis=2)
    relative = np.abs(first - second)[differs] / np.maximum(np.abs(first[differs]), 1e-30)
    print(f"{spp} spp per call: {int(pixels.sum())} of {pixels.size} pixels differ, "
          f"largest relative difference {relative.max() if differs.any() else 0.0:.2e}, "
          f"first pixels {np.flatnonzero(pixels)[:8].tolist()}", flush=True)


def main():
    family = sys.argv[1] if len(sys.argv) > 1 else "statue_room"
    if family in ("-h", "--help"):
        print(__doc__)
        sys.exit(0)
    if family not in scenes.FAMILIES:
        sys.exit(f"error: hr_reference_repro: no scene family {family!r}; families: {', '.join(scenes.FAMILIES)}")
    render.pick_variant()
    scene = render.load_scene(scenes.make_scene(family, 3))
    camera = scenes.camera_path(3, 0, 1)[0]
    for spp in (170, 128):
        compare(scene, camera, spp)


if __name__ == "__main__":
    main()

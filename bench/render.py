"""Mitsuba 3 rendering: variant choice, a path tracer that also writes first-hit gBuffers, and one view.

The integrator ``srd_gbuffer`` wraps Mitsuba's own ``path`` integrator for radiance and, in the same
``sample()`` call, intersects the camera ray once more to write the first-hit gBuffer AOVs. Every AOV is
averaged over the pixel's samples with a box filter (no blur across pixels), so gBuffers are anti-aliased
exactly like the radiance.

gBuffer rules (all zero where the camera ray escapes):

- albedo: for BSDFs with a diffuse lobe, ``eval_diffuse_reflectance`` (the diffuse colour, texture
  included). For BSDFs without one (conductors, glass) the directional albedo estimated from one BSDF
  sample per camera sample (``bsdf.sample`` weight; 1 for clear glass, the Fresnel colour for metals),
  as Intel OIDN recommends for specular surfaces.
- normal: shading normal flipped to face the camera, unit length, then expressed in CAMERA space:
  x = image right, y = image up, z = towards the viewer (OpenGL view space). Camera space makes flips and
  rotations of the image well defined (see bench.dataset). ``normal_space='world'`` keeps world space.
- roughness in [0, 1], describing the sharpest lobe of the BSDF: 1 for purely diffuse BSDFs, 0 for smooth
  (delta) specular ones (conductor, dielectric, smooth plastic), sqrt(alpha) for microfacet BSDFs with a
  GGX/Beckmann ``alpha`` (the perceptual roughness convention, so ``principled``'s ``roughness`` maps to
  itself), clipped to [0, 1]; glossy BSDFs exposing neither attribute get 0.5.
- depth: distance along the camera ray to the first hit, measured from the ray origin, which Mitsuba
  places on the near-clip plane (NEAR_CLIP = 0.01 m in front of the camera).
"""
import glob
import hashlib
import os
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

LLVM_ENV = "DRJIT_LIBLLVM_PATH"
LLVM_DEFAULT = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
GBUFFER_PASSES = ("albedo", "normal", "roughness", "depth")
PASS_CHANNELS = {"radiance": 3, "albedo": 3, "normal": 3, "roughness": 1, "depth": 1}
# Lanes (pixels x spp) per Mitsuba render call; larger spp are split into passes with derived seeds so
# memory stays bounded at paper resolution (1920x1080 x 2048 spp would be 4e9 lanes at once).
MAX_LANES = 1 << 22
NEAR_CLIP = 0.01

_mi = None  # the mitsuba module, imported lazily so that floor-1 users never pay for it


def _find_libllvm():
    """Path to a usable libLLVM for Dr.Jit's LLVM backend, or None."""
    if os.environ.get(LLVM_ENV):
        return os.environ[LLVM_ENV]
    if os.path.exists(LLVM_DEFAULT):
        return LLVM_DEFAULT
    found = sorted(glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM.so.1[6-9]*")
                   + glob.glob("/usr/lib/llvm-1[6-9]/lib/libLLVM*.so*"))
    return found[-1] if found else None


def _variant_works(variant):
    """Run a tiny Dr.Jit op under ``variant`` in a subprocess (a broken backend can abort the process)."""
    code = ("import mitsuba as mi, drjit as dr; mi.set_variant(%r); "
            "x = dr.sum(dr.arange(mi.Float, 8)); assert float(x[0] if hasattr(x, '__len__') else x) == 28"
            % variant)
    try:
        done = subprocess.run([sys.executable, "-c", code], env=dict(os.environ), timeout=120,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return False
    return done.returncode == 0


def pick_variant(prefer_gpu=False):
    """Choose and set the Mitsuba variant: cuda_ad_rgb (if asked and working), llvm_ad_rgb, else scalar_rgb.

    Sets DRJIT_LIBLLVM_PATH when unset so the LLVM backend can find libLLVM. Falls back to scalar_rgb
    with one warning (about 3x slower, and Python integrators are called per sample there).
    Returns the variant name.
    """
    global _mi
    import mitsuba as mi
    _mi = mi
    if mi.variant() is not None and mi.variant() in ("cuda_ad_rgb", "llvm_ad_rgb") and not prefer_gpu:
        _register()
        return mi.variant()
    candidates = []
    if prefer_gpu and "cuda_ad_rgb" in mi.variants():
        candidates.append("cuda_ad_rgb")
    lib = _find_libllvm()
    if lib and not os.environ.get(LLVM_ENV):
        os.environ[LLVM_ENV] = lib
    if lib and "llvm_ad_rgb" in mi.variants():
        candidates.append("llvm_ad_rgb")
    for variant in candidates:
        if _variant_works(variant):
            mi.set_variant(variant)
            _register()
            return variant
    warnings.warn("Mitsuba: no working cuda/llvm variant (set DRJIT_LIBLLVM_PATH to a libLLVM.so); "
                  "falling back to scalar_rgb, which is much slower", RuntimeWarning, stacklevel=2)
    mi.set_variant("scalar_rgb")
    _register()
    return "scalar_rgb"


def use_variant(variant=None):
    """Set ``variant`` (or the pick_variant() choice when None) in this process; returns its name."""
    return _ensure_variant(variant).variant()


def _ensure_variant(variant=None):
    """Make sure a variant is set (the given one, or pick_variant()); returns the mitsuba module."""
    global _mi
    import mitsuba as mi
    _mi = mi
    if variant is not None and mi.variant() != variant:
        mi.set_variant(variant)
        _register()
    elif mi.variant() is None:
        pick_variant()
    else:
        _register()
    return mi


_registered_for = set()


def _register():
    """Register the srd_gbuffer integrator for the current variant (once per variant)."""
    mi = _mi
    if mi.variant() in _registered_for:
        return
    integrator_class = _make_integrator_class()
    mi.register_integrator("srd_gbuffer", lambda props: integrator_class(props))
    _registered_for.add(mi.variant())


def _make_integrator_class():
    """Build the integrator class against the current variant's mi.SamplingIntegrator."""
    mi = _mi
    import drjit as dr

    class GBufferPathIntegrator(mi.SamplingIntegrator):
        """Mitsuba 'path' radiance plus first-hit albedo/normal/roughness/depth AOVs in one pass."""

        def __init__(self, props):
            super().__init__(props)
            self.max_depth = int(props.get("max_depth", 8))
            names = str(props.get("passes", "albedo,normal,roughness"))
            self.passes = [p for p in names.split(",") if p]
            self.path = mi.load_dict({"type": "path", "max_depth": self.max_depth,
                                      "rr_depth": int(props.get("rr_depth", 5))})

        def aov_names(self):
            names = []
            for p in self.passes:
                n = PASS_CHANNELS[p]
                names += [f"{p}.{s}" for s in ("XYZ"[:n] if n == 3 else "Y")]
            return names

        def sample(self, scene, sampler, ray, medium=None, active=True):
            radiance, valid, _ = self.path.sample(scene, sampler, ray, medium, active)
            if not self.passes:
                return radiance, valid, []
            si = scene.ray_intersect(mi.Ray3f(ray), active)
            hit = active & si.is_valid()
            bsdf = si.bsdf(ray)
            flags = dr.select(hit, bsdf.flags(), 0)
            aovs = []
            for p in self.passes:
                if p == "albedo":
                    aovs += self._albedo(si, bsdf, flags, sampler, hit)
                elif p == "normal":
                    n = si.sh_frame.n
                    n = dr.select(dr.dot(n, -ray.d) < 0, -n, n)
                    aovs += [dr.select(hit, n.x, 0.0), dr.select(hit, n.y, 0.0), dr.select(hit, n.z, 0.0)]
                elif p == "roughness":
                    aovs.append(self._roughness(si, bsdf, flags, hit))
                elif p == "depth":
                    aovs.append(dr.select(hit, si.t, 0.0))
            return radiance, valid, aovs

        def _albedo(self, si, bsdf, flags, sampler, hit):
            has_diffuse = hit & mi.has_flag(flags, mi.BSDFFlags.Diffuse)
            diffuse = bsdf.eval_diffuse_reflectance(si, has_diffuse)
            # Importance mode: no 1/eta^2 radiance scaling on refraction, so clear glass has albedo 1.
            ctx = mi.BSDFContext(mi.TransportMode.Importance)
            # select, not `hit & ~has_diffuse`: in scalar_rgb the masks are Python bools, and ~True is -2
            specular = dr.select(has_diffuse, False, hit)
            _, weight = bsdf.sample(ctx, si, sampler.next_1d(hit), sampler.next_2d(hit), specular)
            value = dr.select(has_diffuse, mi.Color3f(diffuse), mi.Color3f(weight))
            value = dr.select(hit, value, 0.0)
            return [value[0], value[1], value[2]]

        def _roughness(self, si, bsdf, flags, hit):
            alpha, perceptual = (self._attribute(bsdf, name, si, hit) for name in ("alpha", "roughness"))
            glossy = mi.has_flag(flags, mi.BSDFFlags.Glossy)
            delta = mi.has_flag(flags, mi.BSDFFlags.Delta)
            rough = dr.select(alpha > 0, dr.sqrt(alpha), dr.select(perceptual > 0, perceptual, 0.5))
            rough = dr.select(glossy, dr.clip(rough, 0.0, 1.0), dr.select(delta, 0.0, 1.0))
            return dr.select(hit, rough, 0.0)

        @staticmethod
        def _attribute(bsdf, name, si, hit):
            """A BSDF attribute, 0 where the BSDF has none (as vectorized variants give; scalar_rgb's
            single BSDF raises instead)."""
            if isinstance(bsdf, mi.BSDF) and not bsdf.has_attribute(name):
                return 0.0
            return bsdf.eval_attribute_1(name, si, hit)

        def to_string(self):
            return f"GBufferPathIntegrator[max_depth={self.max_depth}, passes={self.passes}]"

    return GBufferPathIntegrator


# ----------------------------------------------------------------------------------------------------------
# Scene and camera conversion


def camera_basis(camera):
    """(right, up, forward) unit vectors of a camera dict {'origin', 'target', 'up', 'fov'}."""
    origin, target = np.asarray(camera["origin"], float), np.asarray(camera["target"], float)
    forward = target - origin
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(camera.get("up", (0, 0, 1)), float))
    right /= np.linalg.norm(right)
    return right, np.cross(right, forward), forward


def _sensor_dict(camera, width, height, spp):
    """Mitsuba perspective sensor (box filter, independent sampler) for a camera dict."""
    mi = _mi
    return {
        "type": "perspective",
        "fov": float(camera.get("fov", 60.0)),
        "fov_axis": "x",
        "near_clip": NEAR_CLIP,
        "far_clip": 1000.0,
        "to_world": mi.ScalarTransform4f().look_at(origin=list(map(float, camera["origin"])),
                                                   target=list(map(float, camera["target"])),
                                                   up=list(map(float, camera.get("up", (0, 0, 1))))),
        # 'independent' (not stratified) so the error of a k-spp image falls exactly as 1/k.
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
    }


def _camera_from_sensor(sensor):
    """Camera dict of a loaded Mitsuba sensor (used for user XML scenes rendered from their own camera)."""
    mi = _mi
    m = np.array(sensor.world_transform().matrix, dtype=float).reshape(4, 4)
    origin, forward, up = m[:3, 3], m[:3, 2], m[:3, 1]
    params = mi.traverse(sensor)
    fov = float(np.ravel(params["x_fov"])[0]) if "x_fov" in params else 45.0
    return {"origin": origin.tolist(), "target": (origin + forward).tolist(), "up": up.tolist(), "fov": fov}


def _write_ply(path, vertices, faces):
    """Binary little-endian PLY of a triangle mesh (Mitsuba computes smooth vertex normals on load)."""
    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    faces = np.asarray(faces, np.int32).reshape(-1, 3)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    face_rec = np.zeros(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face_rec["n"], face_rec["idx"] = 3, faces
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertices.astype("<f4").tobytes())
        f.write(face_rec.tobytes())
    os.replace(tmp, path)


def _mesh_cache_dir():
    path = os.path.join(tempfile.gettempdir(), f"srd_bench_meshes_{os.getuid()}")
    os.makedirs(path, exist_ok=True)
    return path


def to_mitsuba_dict(value):
    """Convert a plain scene description (bench.scenes) into a dict mi.load_dict accepts.

    - keys starting with 'srd_' are metadata and are dropped;
    - 'to_world' / 'to_uv' given as 4x4 nested lists become mi.ScalarTransform4f;
    - {'type': 'srd_mesh', 'vertices', 'faces', ...} becomes a 'ply' shape backed by a cached file.
    """
    mi = _mi
    if not isinstance(value, dict):
        return value
    if value.get("type") == "srd_mesh":
        vertices = np.asarray(value["vertices"], np.float32)
        faces = np.asarray(value["faces"], np.int32)
        digest = hashlib.sha1(vertices.tobytes() + faces.tobytes()).hexdigest()[:16]
        path = os.path.join(_mesh_cache_dir(), f"{digest}.ply")
        if not os.path.exists(path):
            _write_ply(path, vertices, faces)
        rest = {k: v for k, v in value.items() if k not in ("type", "vertices", "faces")}
        return {"type": "ply", "filename": path, **to_mitsuba_dict(rest)}
    out = {}
    for key, item in value.items():
        if key.startswith("srd_"):
            continue
        if key in ("to_world", "to_uv") and not isinstance(item, dict) and not hasattr(item, "matrix"):
            out[key] = mi.ScalarTransform4f(np.asarray(item, dtype=float).tolist())
        else:
            out[key] = to_mitsuba_dict(item)
    return out


def load_scene(scene, variant=None):
    """A mi.Scene from a plain scene dict (bench.scenes), a Mitsuba XML path, or an existing mi.Scene.

    Loaded so that every load of one scene renders the same bits (docs/data.md, "Reproducibility"):
    - Mitsuba's mesh merging (``optimize``) only for a scene with at most one area light: the ``merge``
      shape groups meshes in a hash map keyed by memory addresses, so with two or more area lights each
      load ordered the lights differently, and light sampling drew other noise. Unmerged, the lights keep
      the scene's order. Scenes with fewer lights keep merging, so they render the bits they always did
      (merging also shapes the bounds that sky and sun emitters sample from). An XML scene is not merged;
    - on one Dr.Jit thread: a mesh's vertex normals are sums scattered with atomics, whose order (and
      last bit) varies between loads on several threads. Rendering keeps every thread.
    """
    mi = _ensure_variant(variant)
    if not isinstance(scene, (str, os.PathLike, dict)):
        return scene
    import drjit as dr
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        if isinstance(scene, dict):
            mitsuba_dict = to_mitsuba_dict(scene)
            return mi.load_dict(mitsuba_dict, optimize=_area_lights(mitsuba_dict) < 2)
        return mi.load_file(os.fspath(scene), optimize=False)
    finally:
        dr.set_thread_count(threads)


def _area_lights(mitsuba_dict) -> int:
    """Shapes of a Mitsuba scene dict that carry an area emitter."""
    return sum(isinstance(v, dict) and isinstance(v.get("emitter"), dict) and v["emitter"].get("type") == "area"
               for v in mitsuba_dict.values())


# ----------------------------------------------------------------------------------------------------------
# Rendering


def _split_spp(width, height, spp, max_lanes):
    """Samples per Mitsuba call so that width*height*spp_call <= max_lanes (at least 1 spp per call)."""
    per_call = max(1, max_lanes // max(1, width * height))
    chunks = [per_call] * (spp // per_call)
    if spp % per_call:
        chunks.append(spp % per_call)
    return chunks


def render_view(scene, camera, width, height, spp, seed, passes=("albedo", "normal", "roughness"),
                max_depth=8, normal_space="camera", variant=None, max_lanes=MAX_LANES):
    """Path-trace one view; returns float32 HxWxC arrays and the wall time.

    scene: plain dict from bench.scenes.make_scene, a Mitsuba XML path, or a loaded mi.Scene (reuse it when
        rendering many views of one scene). camera: {'origin', 'target', 'up', 'fov' (degrees, horizontal)},
        or None to use the XML scene's first sensor.
    passes: gBuffer passes among GBUFFER_PASSES written in the same pass as the radiance.
    Returns {'radiance': HxWx3, <pass>: HxWxC for each pass, 'wall_time_s': float}. Non-finite samples are
    returned as they are (bench.render.repair_nonfinite fixes them).
    """
    mi = _ensure_variant(variant)
    passes = [p for p in passes if p]
    for p in passes:
        if p not in GBUFFER_PASSES:
            raise ValueError(f"unknown gBuffer pass {p!r}; known: {GBUFFER_PASSES}")
    start = time.perf_counter()
    loaded = load_scene(scene)
    if camera is None:
        camera = _camera_from_sensor(loaded.sensors()[0])
    integrator = mi.load_dict({"type": "srd_gbuffer", "max_depth": int(max_depth),
                               "passes": ",".join(passes)})
    total = None
    chunks = _split_spp(width, height, int(spp), max_lanes)
    for i, chunk_spp in enumerate(chunks):
        sensor = mi.load_dict(_sensor_dict(camera, width, height, chunk_spp))
        # Each extra chunk gets its own seed; chunk 0 uses `seed` itself so small renders match
        # a single call exactly.
        chunk_seed = (int(seed) + 0x9E3779B1 * i) % (1 << 31)
        image = np.array(mi.render(loaded, sensor=sensor, integrator=integrator, seed=chunk_seed,
                                   spp=chunk_spp), dtype=np.float64)
        total = image * chunk_spp if total is None else total + image * chunk_spp
    image = (total / float(spp)).astype(np.float32)
    out = {"radiance": image[..., :3]}
    channel = 3
    for p in passes:
        n = PASS_CHANNELS[p]
        out[p] = image[..., channel:channel + n]
        channel += n
    if "normal" in out and normal_space == "camera":
        out["normal"] = world_to_camera_normals(out["normal"], camera)
    out["wall_time_s"] = time.perf_counter() - start
    return out


def world_to_camera_normals(normals, camera):
    """Rotate HxWx3 world-space normals into camera space (x right, y up, z towards the viewer)."""
    right, up, forward = camera_basis(camera)
    basis = np.stack([right, up, -forward]).astype(np.float32)  # rows: camera axes in world coordinates
    return np.einsum("hwc,kc->hwk", normals, basis).astype(np.float32)


def repair_nonfinite(image):
    """Replace NaN/Inf values by the mean of the finite values in their 3x3 neighbourhood (same channel).

    Rule: a value with no finite neighbour becomes 0. Returns (repaired float32 copy, number of values
    replaced). Fireflies that are finite are kept: they are part of the Monte Carlo estimate.
    """
    image = np.array(image, dtype=np.float32, copy=True)
    bad = ~np.isfinite(image)
    count = int(bad.sum())
    if count == 0:
        return image, 0
    finite = np.where(bad, 0.0, image).astype(np.float64)
    weight = (~bad).astype(np.float64)
    pad = [(1, 1), (1, 1)] + [(0, 0)] * (image.ndim - 2)
    finite_p, weight_p = np.pad(finite, pad), np.pad(weight, pad)
    h, w = image.shape[:2]
    sums = sum(finite_p[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
    counts = sum(weight_p[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3))
    fill = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
    image[bad] = fill[bad]
    return image, count

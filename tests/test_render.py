"""bench.render / bench.scenes / bench.datagen: gBuffer AOVs against analytic answers, noise vs spp,
determinism, resumable builds, and disjoint object kinds between training and generalization scenes."""
import json
import os

import numpy as np
import pytest

from bench import datagen, render, scenes

CAM = {"origin": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0], "fov": 40}


@pytest.fixture(scope="module", autouse=True)
def variant():
    return render.pick_variant()


def _plane_scene(bsdf, env=1.0, extra=None):
    """A 20 x 20 rectangle in the z=0 plane facing +z (the camera), lit by a constant environment."""
    scene = {"type": "scene", "plane": {"type": "rectangle", "to_world": (np.diag([10, 10, 1, 1])).tolist(),
                                        "bsdf": bsdf},
             "env": {"type": "constant", "radiance": {"type": "rgb", "value": [env] * 3}}}
    scene.update(extra or {})
    return scene


def test_diffuse_plane_gbuffer_and_radiance_are_analytic():
    rho = [0.2, 0.4, 0.6]
    scene = _plane_scene({"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}, env=2.0)
    out = render.render_view(scene, CAM, 16, 12, 32, seed=3, passes=("albedo", "normal", "roughness", "depth"))
    assert out["radiance"].shape == (12, 16, 3) and out["albedo"].shape == (12, 16, 3)
    np.testing.assert_allclose(out["albedo"], np.broadcast_to(rho, (12, 16, 3)), atol=1e-5)
    np.testing.assert_allclose(out["normal"], np.broadcast_to([0, 0, 1], (12, 16, 3)), atol=1e-5)
    np.testing.assert_allclose(out["roughness"], 1.0)
    # Depth is measured from the near-clip plane: 3 m to the plane minus NEAR_CLIP along the ray.
    assert out["depth"].min() >= 3.0 - render.NEAR_CLIP * 1.1 and abs(out["depth"][6, 8, 0] - 2.99) < 0.02
    # A diffuse plane seeing only a constant sky L reflects exactly rho * L.
    np.testing.assert_allclose(out["radiance"].mean(axis=(0, 1)), 2.0 * np.array(rho), rtol=0.02)


def test_normals_are_in_camera_space_right_up_towards_viewer():
    scene = {"type": "scene", "ball": {"type": "sphere", "center": [0, 0, 0], "radius": 0.8,
                                       "bsdf": {"type": "diffuse"}},
             "env": {"type": "constant"}}
    # Camera on +x looking at the origin with z up: image right is world +y (forward x up), image up +z.
    cam = {"origin": [3, 0, 0], "target": [0, 0, 0], "up": [0, 0, 1], "fov": 40}
    n = render.render_view(scene, cam, 33, 33, 4, seed=0, passes=("normal",))["normal"]
    centre, right_limb, top_limb = n[16, 16], n[16, 16 + 12], n[16 - 12, 16]
    assert centre[2] > 0.99
    assert right_limb[0] > 0.7 and abs(right_limb[1]) < 0.1
    assert top_limb[1] > 0.7 and abs(top_limb[0]) < 0.1
    world = render.render_view(scene, cam, 33, 33, 4, seed=0, passes=("normal",), normal_space="world")["normal"]
    assert world[16, 16, 0] > 0.99 and world[16, 28, 1] > 0.7   # right limb faces world +y


@pytest.mark.parametrize("bsdf, expected", [
    ({"type": "roughconductor", "alpha": 0.25}, 0.5),           # sqrt(alpha)
    ({"type": "principled", "roughness": 0.3}, 0.3),            # already perceptual
    ({"type": "dielectric"}, 0.0),                              # smooth specular
    ({"type": "twosided", "bsdf": {"type": "roughplastic", "alpha": 0.09}}, 0.3),
])
def test_roughness_rule(bsdf, expected):
    out = render.render_view(_plane_scene(bsdf), CAM, 8, 6, 2, seed=0, passes=("roughness", "albedo"))
    np.testing.assert_allclose(out["roughness"], expected, atol=1e-5)
    if bsdf["type"] == "dielectric":
        np.testing.assert_allclose(out["albedo"], 1.0, atol=1e-5)   # clear glass: albedo 1


def test_render_is_deterministic_and_seed_dependent():
    scene = scenes.make_scene("living_room", 5)
    cam = scenes.camera_path(5, 0, 1)[0]
    a = render.render_view(scene, cam, 16, 12, 4, seed=7)
    b = render.render_view(scene, cam, 16, 12, 4, seed=7)
    c = render.render_view(scene, cam, 16, 12, 4, seed=8)
    for key in ("radiance", "albedo", "normal", "roughness"):
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["radiance"], c["radiance"])


def test_mse_falls_as_one_over_spp():
    light = {"type": "rectangle", "to_world": [[0.3, 0, 0, 0.5], [0, 0.3, 0, 0.5], [0, 0, -1, 1.5], [0, 0, 0, 1]],
             "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [20, 20, 20]}}}
    scene = _plane_scene({"type": "diffuse"}, env=0.2, extra={"light": light})
    loaded = render.load_scene(scene)
    ref = render.render_view(loaded, CAM, 32, 24, 256, seed=100, passes=())["radiance"]
    mse = {k: np.mean((render.render_view(loaded, CAM, 32, 24, k, seed=k, passes=())["radiance"] - ref) ** 2)
           for k in (2, 8)}
    # Independent sampling: variance sigma^2/k, plus the reference's own sigma^2/256 -> ratio ~3.9.
    assert 2.8 < mse[2] / mse[8] < 5.2


def test_spp_split_into_chunks_keeps_the_estimate():
    scene = _plane_scene({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5] * 3}})
    out = render.render_view(scene, CAM, 8, 6, 12, seed=1, passes=("albedo",), max_lanes=8 * 6 * 5)
    assert render._split_spp(8, 6, 12, 8 * 6 * 5) == [5, 5, 2]
    np.testing.assert_allclose(out["albedo"], 0.5, atol=1e-6)
    np.testing.assert_allclose(out["radiance"].mean(), 0.5, rtol=0.03)


def test_repair_nonfinite_uses_finite_neighbour_mean():
    image = np.arange(25, dtype=np.float32).reshape(5, 5, 1)
    image[2, 2, 0], image[0, 0, 0] = np.nan, np.inf
    fixed, count = render.repair_nonfinite(image)
    assert count == 2 and np.isfinite(fixed).all()
    assert fixed[2, 2, 0] == pytest.approx(np.mean([6, 7, 8, 11, 13, 16, 17, 18]))
    assert fixed[0, 0, 0] == pytest.approx(np.mean([1, 5, 6]))


def test_generalization_families_share_no_object_kind_with_training():
    train = {k for f in scenes.TRAIN_FAMILIES for s in (0, 1) for k in scenes.object_kinds(scenes.make_scene(f, s))}
    gen = {k for f in scenes.GENERALIZATION_FAMILIES for s in (0, 1)
           for k in scenes.object_kinds(scenes.make_scene(f, s))}
    assert train and gen and not train & gen
    assert len(scenes.TRAIN_FAMILIES) == 10


def test_scenes_and_cameras_are_deterministic_and_cameras_stay_inside():
    a, b = scenes.make_scene("kitchen", 3), scenes.make_scene("kitchen", 3)
    assert repr(a) == repr(b) and repr(a) != repr(scenes.make_scene("kitchen", 4))
    w, d, h = scenes.room_size(3)
    cams = scenes.camera_path(3, 2, 7)
    origins = np.array([c["origin"] for c in cams])
    assert (origins > 0).all() and (origins < [w, d, h]).all()
    steps = np.linalg.norm(np.diff(origins, axis=0), axis=1)
    assert steps.max() < 0.1   # smooth motion
    bedroom = scenes.scene_features(scenes.make_scene("bedroom", 1))
    assert bedroom["bsdf_types"] == ["diffuse", "principled"] and bedroom["left_out"] == {}  # its roughness varies
    diffuse_only = {"type": "scene", "obj_cube_0": {"type": "cube", "bsdf": {"type": "diffuse"}}}
    assert "roughness" in scenes.scene_features(diffuse_only)["left_out"]


TINY_SPEC = {"name": "tiny", "seed": 1, "lr_width": 8, "lr_height": 6, "scale": 2, "spp": 1, "ref_spp": 4,
             "seq_len": 2, "max_depth": 4,
             "splits": {"train": {"families": ["living_room"], "sequences": 2}}}


def test_build_resumes_after_interruption_rendering_only_missing_frames(tmp_path, monkeypatch):
    calls = []
    real = datagen.render_resolution

    def interrupted(*args, **kwargs):
        if len(calls) == 5:   # frames have two resolutions: dies while rendering frame 3 (of 4)
            raise KeyboardInterrupt
        calls.append(args[7])
        return real(*args, **kwargs)

    monkeypatch.setattr(datagen, "render_resolution", interrupted)
    with pytest.raises(KeyboardInterrupt):
        datagen.build_dataset(tmp_path / "a", TINY_SPEC, progress=False)
    assert not (tmp_path / "a" / "manifest.json").exists()
    calls.clear()
    monkeypatch.setattr(datagen, "render_resolution", lambda *a, **k: (calls.append(a[7]), real(*a, **k))[1])
    df = datagen.build_dataset(tmp_path / "a", TINY_SPEC, progress=False)
    assert len(df) == 4 and df["resumed"].sum() == 2 and len(calls) == 4   # 2 frames x (LR, HR)
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert len(manifest["frames"]) == 4 and all(r["settings_hash"] for r in manifest["frames"])
    # Same spec, fresh directory: identical pixels (every buffer has its own derived seed).
    datagen.build_dataset(tmp_path / "b", TINY_SPEC, progress=False)
    from bench.exrio import read_exr
    for rec in manifest["frames"]:
        rel = os.path.join(rec["split"], rec["sequence"], f"{rec['frame']:04d}_hr.exr")
        a, b = read_exr(tmp_path / "a" / rel), read_exr(tmp_path / "b" / rel)
        for layer in a:
            np.testing.assert_array_equal(a[layer], b[layer])


def test_later_build_with_more_buffers_renders_only_those(tmp_path, monkeypatch):
    spec = {**TINY_SPEC, "splits": {"val": {"families": ["gallery"], "sequences": 1}}}
    datagen.build_dataset(tmp_path, spec, passes=["lr_noisy", "hr_ref"], progress=False)
    hr_file = tmp_path / "val" / datagen.plan_sequences(spec)[0]["sequence"] / "0001_hr.exr"
    before = hr_file.read_bytes()
    calls = []
    real = datagen.render_resolution
    monkeypatch.setattr(datagen, "render_resolution", lambda *a, **k: (calls.append(a[7]), real(*a, **k))[1])
    df = datagen.build_dataset(tmp_path, spec, passes=["lr_noisy", "hr_ref", "lr_ref", "lr_gbuf"], progress=False)
    assert calls == [["lr_ref", "lr_gbuf"]] * 2 and not df["resumed"].any()
    assert hr_file.read_bytes() == before                     # HR file untouched
    from bench.dataset import SequenceDataset
    item = SequenceDataset(tmp_path, "val", ["lr_noisy", "lr_ref", "lr_gbuf", "hr_ref"])[0]
    assert item["lr_gbuf"].shape == (2, 7, 6, 8) and item["hr_ref"].shape == (2, 3, 12, 16)
    df = datagen.build_dataset(tmp_path, spec, passes=["lr_ref"], progress=False)
    assert df["resumed"].all() and len(calls) == 2


def test_a_re_rendered_buffer_counts_its_repaired_values_once(tmp_path, monkeypatch):
    real = render.render_view

    def one_nan_per_radiance(*args, **kwargs):   # every render of radiance has exactly one NaN
        out = real(*args, **kwargs)
        out["radiance"] = out["radiance"].copy()
        out["radiance"][0, 0, 0] = np.nan
        return out

    monkeypatch.setattr(render, "render_view", one_nan_per_radiance)
    spec = {**TINY_SPEC, "splits": {"val": {"families": ["gallery"], "sequences": 1}}}
    passes = ["lr_noisy", "hr_ref"]
    first = datagen.build_dataset(tmp_path, spec, passes=passes, progress=False)
    assert (first["nonfinite_repaired"] == 2).all()   # one NaN in LR noisy, one in the HR reference
    assert (first["nonfinite_repaired_by_buffer.lr_noisy"] == 1).all()
    hr_file = tmp_path / "val" / datagen.plan_sequences(spec)[0]["sequence"] / "0000_hr.exr"
    hr_file.write_bytes(hr_file.read_bytes()[:100])    # damaged: frame 0's HR buffers are rendered again
    again = datagen.build_dataset(tmp_path, spec, passes=passes, progress=False)
    assert list(again["resumed"]) == [False, True]
    assert (again["nonfinite_repaired"] == 2).all()

def test_a_split_with_its_own_ref_spp_gets_half_sample_references_and_their_error(tmp_path, monkeypatch):
    """Converged references where frames are scored: the val split's own ref_spp re-renders only its
    frames, each reference as two independent halves whose difference estimates its error (1/spp)."""
    train = {"families": ["living_room"], "sequences": 1}
    val = {"families": ["gallery"], "sequences": 1}
    plain = {**TINY_SPEC, "splits": {"train": train, "val": val}}
    datagen.build_dataset(tmp_path / "a", plain, progress=False)
    before = {(r["split"], r["frame"]): r for r in datagen.load_manifest(tmp_path / "a")["frames"]}
    calls = []
    real = datagen.render_resolution
    monkeypatch.setattr(datagen, "render_resolution", lambda *a, **k: (calls.append(a[7]), real(*a, **k))[1])
    errors = {}
    for spp in (8, 128):
        spec = {**plain, "splits": {"train": train, "val": {**val, "ref_spp": spp}}}
        datagen.build_dataset(tmp_path / "a", spec, progress=False)
        frames = datagen.load_manifest(tmp_path / "a")["frames"]
        for rec in frames:
            if rec["split"] == "train":                       # untouched: same settings, no estimate
                assert rec["settings_hash"] == before[("train", rec["frame"])]["settings_hash"]
                assert "ref_error" not in rec
            else:
                assert rec["ref_spp"] == spp and set(rec["ref_error"]) == {"lr", "hr"}
        errors[spp] = np.mean([rec["ref_error"]["hr"] for rec in frames if rec["split"] == "val"])
    assert len(calls) == 2 * 2 * 2                            # 2 val frames x (LR, HR), twice; no train frame
    assert errors[8] > 4 * errors[128] > 0                    # ~16x expected: the error falls as 1/spp


def test_render_user_xml_scene_loads_as_a_dataset(tmp_path):
    xml = tmp_path / "mine.xml"
    xml.write_text("""<scene version="3.0.0">
      <sensor type="perspective"><float name="fov" value="45"/>
        <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
      </sensor>
      <shape type="rectangle"><transform name="to_world"><scale value="10"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.5, 0.7"/></bsdf></shape>
      <emitter type="constant"/>
    </scene>""")
    df = datagen.render_user_scene(xml, tmp_path / "user", 8, 6, spp=2, ref_spp=8)
    assert len(df) == 1
    from bench.dataset import SequenceDataset
    item = SequenceDataset(tmp_path / "user", "user", ["lr_noisy", "lr_gbuf", "hr_ref"], seq_len=1)[0]
    torch = pytest.importorskip("torch")
    assert torch.allclose(item["lr_gbuf"][0, :3, 3, 4], torch.tensor([0.3, 0.5, 0.7]), atol=1e-5)
    assert torch.allclose(item["lr_gbuf"][0, 3:6, 3, 4], torch.tensor([0.0, 0.0, 1.0]), atol=1e-5)
    assert item["hr_ref"].shape == (1, 3, 12, 16)


def test_floor_one_modules_do_not_import_mitsuba():
    import subprocess
    import sys
    code = "import sys, bench.scenes, bench.exrio; assert 'mitsuba' not in sys.modules and 'drjit' not in sys.modules"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


# sha256 (first 16 hex) of make_scene(family, seed) for seeds 0 and 7: the dataset's content. Recorded
# frames are re-rendered from (family, seed) (damaged-frame repair, the time experiment), so a change here
# changes data the run store believes it has: deliberate only, with the data re-rendered.
SCENE_DIGESTS = {
    "living_room": ("260a5b39b0d34f0e", "e6d1ef7ef3c68151"),
    "kitchen": ("861818e83c37d834", "d88892128c3999bc"),
    "bathroom": ("3ba465814cdb891b", "80f8958d43284a94"),
    "bedroom": ("8725e1d24ad6af1e", "51e861e73c514f3d"),
    "office": ("9045e3bd9dd589c5", "ddc3ce7ff182fa27"),
    "gallery": ("b6db77d9a50b6be0", "a6eba974944b9405"),
    "dining": ("5901bcc2c0ccf2d1", "b1b2866b697d1e55"),
    "studio": ("112bd65dc824db77", "032bfefb42277dc4"),
    "library": ("c7bc697a19c67d12", "7b68cb497c48e7b5"),
    "atrium": ("dcc71d9928f78f56", "f5858eb92ce03f58"),
    "torus_hall": ("1d6f44702c8d9078", "15cb47663098b8a8"),
    "knot_room": ("62876d7a8d580282", "b472201e7c8760b8"),
    "statue_room": ("a1a3da436821554c", "1f69512c1e61a5d7"),
    "disk_room": ("e3505b18ccccd741", "ec4fba23382729a9"),
}


def _digest(obj):
    """Of the scene with every number rounded to 6 decimals: numpy's vectorised sin/cos may differ in the
    last bit between CPUs (AVX2, AVX-512), which must not read as a changed scene."""
    import hashlib

    def rounded(v):
        if isinstance(v, dict):
            return {k: rounded(x) for k, x in v.items()}
        if isinstance(v, (list, tuple, np.ndarray)):
            return [rounded(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
        return round(float(v), 6) + 0.0 if isinstance(v, (float, np.floating)) else v
    return hashlib.sha256(json.dumps(rounded(obj), sort_keys=True).encode()).hexdigest()[:16]


def test_every_family_is_one_table_entry_and_its_scenes_are_unchanged():
    assert set(scenes.FAMILY_CONTENT) == set(scenes.FAMILIES) == set(SCENE_DIGESTS)
    assert {f: (_digest(scenes.make_scene(f, 0)), _digest(scenes.make_scene(f, 7))) for f in scenes.FAMILIES} \
        == SCENE_DIGESTS


def test_rendering_without_a_terminal_logs_progress_lines(tmp_path, monkeypatch, caplog):
    """Logs, sweeps, clusters: no progress bar, so a line with frames, rate and time left (every
    PROGRESS_LOG_S; here after every sequence)."""
    monkeypatch.setattr(datagen, "PROGRESS_LOG_S", 0.0)
    with caplog.at_level("INFO", logger="bench"):
        datagen.build_dataset(tmp_path / "a", TINY_SPEC, progress=True)   # pytest's output is not a terminal
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("render: ")]
    assert lines and "frames/s" in lines[-1] and "min left" in lines[-1]
    assert lines[-1].startswith("render: 4/4 frames")


def test_a_build_of_some_splits_renders_only_them_and_its_manifest_holds_whole_splits(tmp_path, monkeypatch):
    """A table whose trainings are all recorded renders only the split it scores (the frozen test split on
    a fresh clone): the manifest lists the splits whose every frame is there, and nothing else."""
    spec = {**TINY_SPEC, "splits": {"train": {"families": ["living_room"], "sequences": 1},
                                    "test": {"families": ["gallery"], "sequences": 1}}}
    calls = []
    real = datagen.render_resolution
    monkeypatch.setattr(datagen, "render_resolution", lambda *a, **k: (calls.append(a[7]), real(*a, **k))[1])
    df = datagen.build_dataset(tmp_path, spec, progress=False, splits=["test"])
    assert set(df["split"]) == {"test"} and not (tmp_path / "train").exists() and len(calls) == 4
    assert {f["split"] for f in datagen.load_manifest(tmp_path)["frames"]} == {"test"}
    df = datagen.build_dataset(tmp_path, spec, progress=False, splits=["train"])
    assert len(calls) == 8                                          # train's two frames; test not again
    assert [f["split"] for f in datagen.load_manifest(tmp_path)["frames"]] == ["test", "test", "train", "train"]
    test_frame = tmp_path / "test" / datagen.plan_sequences(spec)[1]["sequence"] / "0001.json"
    test_frame.unlink()                                             # a split missing a frame's record ...
    (tmp_path / "manifest.json").write_text("{")                    # ... is left out of a rebuilt manifest
    assert [f["split"] for f in datagen.rebuild_manifest(tmp_path, spec)["frames"]] == ["train", "train"]


def test_the_render_progress_counts_samples_not_frames():
    """The progress line's time left counts each sequence's samples (input and reference): a split's
    sequences differ by up to 16x in their references (sequence_ref_spp), so a count of frames misleads."""
    spec = {"seed": 0, "seq_len": 7, "spp": 8, "ref_spp": 256,
            "splits": {"train": {"families": ["living_room"], "sequences": 1},
                       "test": {"families": ["kitchen"], "sequences": 2, "ref_spp": 1024}}}
    train, first, second = datagen.plan_sequences(spec)
    spec["splits"]["test"]["sequence_ref_spp"] = {second["sequence"]: 16384}
    assert [datagen.sequence_samples(spec, job) for job in (train, first, second)] == \
        [7 * (8 + 256), 7 * (8 + 1024), 7 * (8 + 16384)]

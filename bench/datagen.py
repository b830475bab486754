"""Build a dataset directory of rendered sequences: one multi-layer EXR per frame and resolution + manifest.

Layout (``root`` = e.g. ``data/smoke``)::

    root/manifest.json                              spec, passes, variant and one record per frame
    root/<split>/<sequence>/<frame:04d>_lr.exr      layers noisy, ref, albedo, normal, roughness (LR)
    root/<split>/<sequence>/<frame:04d>_hr.exr      the same at HR (2x)
    root/<split>/<sequence>/<frame:04d>.json        the frame's record; written last, marks it complete

A sequence is T consecutive frames of one camera path through one procedural scene. Only the buffers in
``passes`` are rendered (keys of the data contract: lr_noisy, lr_gbuf, lr_ref, hr_noisy, hr_gbuf, hr_ref),
and gBuffer passes a scene does not need are left out (roughness of an all-diffuse scene; the loader
supplies the constant) with the reason recorded.

Seeds: every (scene, view, frame, buffer) gets its own seed derived with numpy's SeedSequence from the
spec seed, so inputs and references are independent, and the same spec gives the same pixels whatever the
number of workers or the order of work. Non-finite samples are counted and repaired with
``bench.render.repair_nonfinite`` (mean of finite 3x3 neighbours, else 0).

Resumable and cumulative: a frame whose record (same render settings) and EXRs holding every requested
layer exist is skipped; buffers it lacks (a later build asking for more) are rendered alone and merged
into its EXRs. All files are written atomically, records last, so an interrupted build leaves only
complete frames behind.
"""
import contextlib
import dataclasses
import hashlib
import json
import logging
import multiprocessing
import os
import signal
import socket
import sys
import tempfile
import time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np
from tqdm import tqdm

from bench import exrio, render, scenes
from bench.atomic import write_atomic
from bench.errors import UserError
from bench.tasks import BUFFERS, GBUF_LAYERS

log = logging.getLogger("bench")
PROGRESS_LOG_S = 60.0  # without a terminal (logs, clusters), rendering progress is a log line this often

SUFFIXES = {"noisy": ("R", "G", "B"), "ref": ("R", "G", "B"), "albedo": ("R", "G", "B"),
            "normal": ("X", "Y", "Z"), "roughness": ("Y",)}
_BUFFER_CODES = {"noisy": 1, "ref": 2}


def derive_seed(*parts):
    """A 31-bit seed from integers/strings (strings hashed with crc32), stable across runs and machines."""
    ints = [zlib.crc32(p.encode()) if isinstance(p, str) else int(p) for p in parts]
    return int(np.random.SeedSequence(ints).generate_state(1)[0] % (1 << 31))


def plan_sequences(spec):
    """One dict per sequence to render: split, family, scene_seed, view, sequence id.

    spec['splits'][split] = {'families': [...], 'sequences': n, 'views_per_scene': v (default 1)}:
    sequence i is the k-th (k = i // len(families)) of family i mod len(families); every v consecutive
    sequences of a family share one scene (a room seed), seen along different camera paths.
    """
    plan = []
    for split, part in spec["splits"].items():
        families = list(part["families"])
        per_scene = int(part.get("views_per_scene", 1))
        for i in range(int(part["sequences"])):
            family, k = families[i % len(families)], i // len(families)
            scene_seed = derive_seed(spec["seed"], split, family, k // per_scene)
            view = k % per_scene
            plan.append({"split": split, "family": family, "scene_seed": scene_seed, "view": view,
                         "sequence": f"{family}-{scene_seed}-v{view}"})
        unknown = sorted(set(part.get("sequence_ref_spp") or {}) - {p["sequence"] for p in plan if p["split"] == split})
        if part.get("sequence_ref_spp") and not part.get("ref_spp"):
            raise UserError(f"data.splits.{split}.sequence_ref_spp needs the split's own ref_spp (two-half references)")
        if unknown:
            raise UserError(f"data.splits.{split}.sequence_ref_spp: {unknown[0]!r} is no sequence of split {split!r}")
        for sequence, count in (part.get("sequence_ref_spp") or {}).items():
            if not _on_chain(part["ref_spp"], count):
                raise UserError(f"data.splits.{split}.sequence_ref_spp.{sequence}={count!r}: expected the split's "
                                f"ref_spp ({part['ref_spp']}) times a power of two, e.g. {2 * int(part['ref_spp'])}")
    return plan


def sequence_samples(spec, job):
    """Samples per pixel a sequence of `plan_sequences` renders over its frames (input and reference): the
    measure of its cost that the progress line's time left counts in (a split's sequences differ by up
    to 16x in their references, so frames are not)."""
    part = spec["splits"][job["split"]]
    reference = (part.get("sequence_ref_spp") or {}).get(job["sequence"]) or part.get("ref_spp") or spec["ref_spp"]
    return int(spec["seq_len"]) * (int(spec["spp"]) + int(reference))


def _on_chain(base, count):
    """Whether `count` samples are `base` doubled zero or more times."""
    try:
        base, count = int(base), int(count)
    except (TypeError, ValueError):
        return False
    return base > 0 and count >= base and count % base == 0 and not (count // base) & (count // base - 1)


def render_settings(spec, features, split=None, sequence=None):
    """Everything that determines a frame's pixels (hashed into the record so stale frames re-render).

    The buffer list is not part of it: every buffer has its own seed, so buffers added by a later build
    (another table needing another task) are rendered alone and merged into the existing EXRs.
    A split with its own `ref_spp` (the scored ones: converged references) renders its references as
    two independent halves (`ref_halves`), whose difference estimates each reference's error; its
    `sequence_ref_spp` gives sequences whose references need more samples their own count, the split's
    `ref_spp` times a power of two (`+experiment=references` proposes them). Such a reference is the
    split's two-half reference refined by doublings (`refine_reference`), so a frame already rendered
    renders only the samples it lacks; `ref_base_spp` names where the doublings start.
    """
    max_depth = features["max_depth"]
    if spec.get("max_depth"):
        max_depth = min(max_depth, int(spec["max_depth"]))
    settings = {"lr_width": int(spec["lr_width"]), "lr_height": int(spec["lr_height"]),
                "scale": int(spec.get("scale", 2)), "spp": int(spec["spp"]), "ref_spp": int(spec["ref_spp"]),
                "seed": int(spec["seed"]), "max_depth": int(max_depth),
                "half_gbuffer": bool(spec.get("half_gbuffer", False)), "left_out": sorted(features["left_out"])}
    part = (spec["splits"].get(split) or {}) if split else {}
    if part.get("ref_spp"):  # only then: the settings (and hashes) of other splits' frames stay as they were
        ref_spp = int((part.get("sequence_ref_spp") or {}).get(sequence, part["ref_spp"]))
        settings.update(ref_spp=ref_spp, ref_halves=True)
        if ref_spp != int(part["ref_spp"]):  # only then: the split's other frames keep their hashes
            settings["ref_base_spp"] = int(part["ref_spp"])
    return settings


def _settings_at(settings, ref_spp):
    """`settings` with the reference at `ref_spp` samples on the same doubling chain (a frame rendered
    before its sequence was given more samples, or part way there)."""
    base = settings.get("ref_base_spp", settings["ref_spp"])
    earlier = {**settings, "ref_spp": int(ref_spp), "ref_base_spp": base}
    if int(ref_spp) == base:
        del earlier["ref_base_spp"]
    return earlier


def _settings_hash(settings):
    return hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]


def planned_settings(spec):
    """(sequence plan, settings hash) of every sequence `spec` plans: the `settings_hash` each of its
    frame records holds once rendered, known without rendering (the scene is built, not loaded)."""
    for job in plan_sequences(spec):
        features = scenes.scene_features(scenes.make_scene(job["family"], job["scene_seed"]))
        yield job, _settings_hash(render_settings(spec, features, job["split"], job["sequence"]))


def frame_paths(root, split, sequence, frame):
    base = os.path.join(root, split, sequence, f"{frame:04d}")
    return base + "_lr.exr", base + "_hr.exr", base + ".json"


def buffer_layers(buffer, gbuf_layers=GBUF_LAYERS):
    """EXR layers holding ``buffer`` (e.g. 'lr_gbuf' -> albedo, normal, roughness in the _lr file)."""
    kind = buffer.split("_")[1]
    return list(gbuf_layers) if kind == "gbuf" else [kind]


MAX_NONFINITE = 0.01  # share of a frame's pixels that may be non-finite (any channel) and be repaired (sanitize)


def damaged_frames(root, frames, passes, decode=False, stamps=True, max_nonfinite=0.0):
    """(path, what is wrong) for every frame file that is missing, unreadable, lacks a layer its
    record's buffers need, has another size than its record's `lr_size`/`hr_size`, or (with `stamps`:
    rendered data) was changed since it was rendered (its size or bytes differ from the stamp its
    record took when it was written). Reads headers and file stats only, unless `decode` (every pixel:
    also finds a file cut inside its pixel data, and NaN/Inf values, at the cost of reading the whole
    dataset; `max_nonfinite`: the share of a layer's pixels that may be NaN/Inf, which the evaluator
    repairs). A record that names no buffers (your own data without `buffers` or `passes`) has its
    files checked for whatever layers they hold."""
    problems = []
    for rec in frames:
        left_out = rec.get("left_out") or {}
        gbuf_layers = [g for g in GBUF_LAYERS if g not in left_out]
        paths = frame_paths(root, rec["split"], rec["sequence"], rec["frame"])
        for res, path in zip(("lr", "hr"), paths[:2]):
            wanted = {layer for b in (rec.get("buffers") or passes) if b.startswith(res)
                      for layer in buffer_layers(b, gbuf_layers)}
            if not wanted and not (rec.get("buffers") or passes) and os.path.exists(path):
                wanted = None  # nothing named: check the layers the file has
            elif not wanted:
                continue
            if not os.path.exists(path):
                problems.append((path, "missing"))
                continue
            try:
                names, actual = exrio.exr_header(path)
            except exrio.ExrError:
                problems.append((path, "unreadable"))
                continue
            layers = set(names)
            lacking = (wanted or set()) - layers
            size = rec.get(f"{res}_size")
            if lacking:
                problems.append((path, f"lacks layers {sorted(lacking)}"))
            elif size and actual != tuple(size):
                problems.append((path, "{}x{} pixels; its record says {}x{}".format(*actual, *size)))
            elif stamps and not (as_written(rec, res, path) or _rendered_again(paths[2], rec, res, path)):
                problems.append((path, "changed since it was rendered (size or bytes differ from its record)"))
            elif decode and (why := _decode_problem(path, sorted(wanted or layers), max_nonfinite)):
                problems.append((path, why))
    return problems


def _rendered_again(rec_path, record, res, path):
    """True when the frame's own record (`rec_path`, beside it) holds a stamp of `path` that matches and the
    settings of `record` (the manifest's): a render with those settings wrote the file again after the
    manifest was written, and stopped before writing the next one (an interrupted render's frames)."""
    own = _load_record(rec_path, record.get("settings_hash"))
    return bool(own) and (own.get("files") or {}).get(res) is not None and as_written(own, res, path)


def file_stamp(path):
    """What a frame file was when written: size, mtime and a CRC-32 of its bytes. The CRC is read only
    when the mtime differs, so copying a dataset without keeping mtimes (plain `cp`) costs one read of
    each file per command, not a render."""
    st = os.stat(path)
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "crc32": _crc32(path)}


def _crc32(path):
    crc = 0
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            crc = zlib.crc32(chunk, crc)
    return crc


def as_written(record, res, path):
    """False when the frame file `path` ("lr" or "hr" file of `record`) differs from the stamp taken
    when it was written; True when it matches or there is no stamp (frames rendered before stamps,
    and your own renders, are checked by headers and, with verify=true, by decoding)."""
    stamp = (record.get("files") or {}).get(res)
    if stamp is None or not os.path.exists(path):
        return True
    st = os.stat(path)
    return st.st_size == stamp["size"] and (st.st_mtime_ns == stamp["mtime_ns"] or _crc32(path) == stamp["crc32"])


def _decode_problem(path, layers, max_nonfinite=0.0):
    """Why the pixels of `layers` in `path` are damaged (does not decode, or holds NaN/Inf on more than
    `max_nonfinite` of a layer's pixels), or None. Rendered frames never hold NaN/Inf: the renderer
    repairs them before writing (repair_nonfinite)."""
    try:
        with _stderr_to_log():
            pixels = exrio.read_exr(path, layers)
    except exrio.ExrError:
        return "does not decode (truncated or corrupt)"
    shares = {name: float((~np.isfinite(a)).reshape(a.shape[0], a.shape[1], -1).any(axis=2).mean())
              for name, a in pixels.items()}
    bad = {name: f"{share:.2%}" for name, share in shares.items() if share > max_nonfinite}
    return f"non-finite pixel values (NaN/Inf) on {bad} of the pixels" if bad else None


@contextlib.contextmanager
def _stderr_to_log():
    """OpenEXR's C++ library prints its own lines to the process's stderr when a file does not decode;
    the caller names the file once, in its words, so those lines go to the debug log instead."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            said = caught.read().decode(errors="replace").strip()
            if said:
                log.debug("OpenEXR: %s", said)


def stamp_frames(root):
    """Record the file stamps of the frames that have none (rendered before stamps existed), and the
    new mtime of stamped files whose bytes still match (a copy that did not keep mtimes: else every
    command reads their bytes again). Called after `verify=true` decoded every frame, so a stamp
    vouches for pixels that were checked; rendered data only (your own files are never written).
    Rewrites the changed frame records and the manifest atomically; the data fingerprint does not read
    stamps, so no run becomes stale. Returns how many frames were stamped."""
    manifest = load_manifest(root)
    stamped = 0
    for rec in manifest["frames"]:
        paths = frame_paths(root, rec["split"], rec["sequence"], rec["frame"])
        old = rec.get("files") or {}
        files = {res: file_stamp(path) if old.get(res) is None or old[res]["mtime_ns"] != os.stat(path).st_mtime_ns
                 else old[res] for res, path in zip(("lr", "hr"), paths[:2]) if os.path.exists(path)}
        if files == old:
            continue
        rec["files"] = files
        if os.path.exists(paths[2]):
            with open(paths[2]) as f:
                _write_json(paths[2], {**json.load(f), "files": files})
        stamped += 1
    if stamped:
        _write_json(os.path.join(root, "manifest.json"), manifest)
    return stamped


# What the suite reads from a frame record of your own dataset: key -> (check, what it must be).
FRAME_KEYS = {
    "split": (lambda v: isinstance(v, str) and v, "a split name (train, val, ...; the folder under the root)"),
    "sequence": (lambda v: isinstance(v, str) and v, "the sequence's folder name"),
    "frame": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "the frame index, an integer >= 0"),
    "scene": (lambda v: isinstance(v, str) and v, "a scene name (per-image results are grouped by it)"),
}
OPTIONAL_FRAME_KEYS = {
    "lr_size": (lambda v: isinstance(v, list) and len(v) == 2 and all(isinstance(n, int) and n > 0 for n in v),
                "[width, height] of the LR frame (training crops need it)"),
    "left_out": (lambda v: isinstance(v, dict) and set(v) <= {"roughness"},
                 'layers the frame has none of, with the reason: only {"roughness": "why"} (read as 1.0)'),
}


def manifest_problems(root, shown=8):
    """What is wrong with a dataset directory you bring (render_data=false): the manifest, every frame
    record key the suite reads (FRAME_KEYS, OPTIONAL_FRAME_KEYS) and the frame sizes (HR = scale x LR,
    from the EXR headers). One line per problem, naming the file and what it must be; at most `shown`
    lines, then a count."""
    path = os.path.join(root, "manifest.json")
    try:
        with open(path) as f:
            manifest = json.load(f)
    except FileNotFoundError:
        return [f"{root} has no manifest.json: point data_dir at a dataset in the documented layout "
                "(docs/data.md)"]
    except ValueError as err:
        return [f"{path}: not JSON ({err}): damaged; restore it from your copy of the dataset or write it again "
                "(README, 'Dataset layout'); with render_data=false the suite never rewrites your files"]
    if not isinstance(manifest, dict) or not isinstance(manifest.get("frames"), list) or not manifest["frames"]:
        return [f'{path}: expected an object with "frames": a non-empty list of frame records']
    spec = manifest.get("spec", {})
    scale = spec.get("scale", 2) if isinstance(spec, dict) else None
    if not isinstance(scale, int) or scale < 1:
        return [f'{path}: "spec" must be an object whose "scale" (HR/LR, default 2) is an integer >= 1']
    problems = []
    for i, rec in enumerate(manifest["frames"]):
        where = f"{path}: frames[{i}]"
        if not isinstance(rec, dict):
            problems.append(f"{where}: expected an object (a frame record)")
            continue
        for key, (ok, what) in FRAME_KEYS.items():
            if not ok(rec.get(key)):
                problems.append(f"{where}: {key!r} is {rec.get(key)!r}; expected {what}")
        for key, (ok, what) in OPTIONAL_FRAME_KEYS.items():
            if key in rec and not ok(rec[key]):
                problems.append(f"{where}: {key!r} is {rec[key]!r}; expected {what}")
        if all(ok(rec.get(key)) for key, (ok, _) in FRAME_KEYS.items()):
            problems += _size_problems(root, rec, scale)
    if len(problems) > shown:
        problems = problems[:shown] + [f"... and {len(problems) - shown} more"]
    return problems


def _size_problems(root, rec, scale):
    lr_path, hr_path, _ = frame_paths(root, rec["split"], rec["sequence"], rec["frame"])
    lr, hr = _exr_size(lr_path), _exr_size(hr_path)
    out = []
    if lr and rec.get("lr_size") and list(lr) != list(rec["lr_size"]):
        out.append(f"{lr_path}: {lr[0]}x{lr[1]} pixels, but its record's lr_size is {rec['lr_size']}")
    if lr and hr and (hr[0], hr[1]) != (scale * lr[0], scale * lr[1]):
        out.append(f"{hr_path} is {hr[0]}x{hr[1]} pixels and {os.path.basename(lr_path)} beside it {lr[0]}x{lr[1]}: HR must be "
                   f"{scale}x LR (spec.scale={scale}); one of the two is not of this frame's size")
    return out


def _exr_size(path):
    """(width, height) from an EXR's header; None when missing or unreadable (damaged_frames says which)."""
    try:
        return exrio.exr_header(path)[1]
    except exrio.ExrError:  # reported by damaged_frames, with the file named
        return None


def _read_record(rec_path):
    """The frame's record as written, or None when it is missing or does not parse."""
    try:
        with open(rec_path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def _load_record(rec_path, settings_hash):
    """The frame's record if it exists and was rendered with the same settings, else None."""
    record = _read_record(rec_path)
    return record if record and record.get("settings_hash") == settings_hash else None


def _earlier_on_chain(rec_path, settings):
    """The frame's record if it was rendered with these settings but fewer reference samples on the
    same doubling chain (datagen.refine_reference), else None."""
    record = _read_record(rec_path)
    try:
        spp = int(record["ref_spp"])
    except (KeyError, TypeError, ValueError):
        return None
    if spp >= settings["ref_spp"] or not _on_chain(settings.get("ref_base_spp", settings["ref_spp"]), spp):
        return None
    return record if record.get("settings_hash") == _settings_hash(_settings_at(settings, spp)) else None


def _present_layers(path):
    """Layers of an EXR that decodes completely (empty if missing or broken)."""
    return set(exrio.exr_layers(path)) if exrio.is_valid_exr(path) else set()


@dataclasses.dataclass(frozen=True)
class ReferencePlan:
    """How a frame's reference is rendered: `spp` samples in all. With `halves`, as the mean of two
    independent renders of half the samples, whose difference estimates its error. With `base_spp`, the
    halves have base_spp samples together and `refine_reference` doubles them up to spp; `stored` (image,
    its spp) is a reference already rendered on that chain, which is refined instead."""
    spp: int
    halves: bool = False
    base_spp: int | None = None
    stored: tuple | None = dataclasses.field(default=None, compare=False)  # holds an image: not compared

    @classmethod
    def of(cls, settings: dict, stored: tuple | None = None) -> "ReferencePlan":
        """The plan `render_settings` describes."""
        return cls(settings["ref_spp"], settings.get("ref_halves", False), settings.get("ref_base_spp"), stored)


def render_resolution(scene, camera, width, height, spp, reference: ReferencePlan, seeds, passes, res,
                      gbuf_layers, max_depth):
    """Render the layers of one resolution of one frame; returns (layers, wall times, non-finite values
    repaired per buffer (e.g. {"lr_noisy": 3}), reference error): its estimated relMSE against the
    converged image (bench.metrics.reference_error) when the plan renders halves or refines by doublings,
    else None."""
    layers, times, repaired, ref_error = {}, {}, {}, None
    if f"{res}_noisy" in passes or f"{res}_gbuf" in passes:
        gbuf = list(gbuf_layers) if f"{res}_gbuf" in passes else []
        out = render.render_view(scene, camera, width, height, spp, seeds["noisy"], passes=gbuf,
                                 max_depth=max_depth)
        times[f"{res}_noisy_s"] = out["wall_time_s"]
        if f"{res}_noisy" in passes:
            layers["noisy"] = out["radiance"]
        for name in gbuf:
            layers[name] = out[name]
    if f"{res}_ref" in passes:
        seconds, count = 0.0, 0
        if reference.stored is None:
            start_spp = reference.base_spp or reference.spp
            halves_seeds = [seeds["ref"], derive_seed(seeds["ref"], "second half")] if reference.halves \
                else [seeds["ref"]]
            halves = []
            for seed in halves_seeds:
                out = render.render_view(scene, camera, width, height, start_spp // len(halves_seeds), seed,
                                         passes=(), max_depth=max_depth)
                half, repairs = render.repair_nonfinite(out["radiance"])
                halves.append(half)
                seconds, count = seconds + out["wall_time_s"], count + repairs
            if reference.halves:
                ref_error = _error_of_mean(*halves)
            ref = sum(halves) / len(halves)
        else:
            ref, start_spp = reference.stored
        ref, error, more_seconds, more_repairs = refine_reference(scene, camera, width, height, ref, start_spp,
                                                                  reference.spp, seeds["ref"], max_depth)
        layers["ref"], ref_error = ref, (error if error is not None else ref_error)
        times[f"{res}_ref_s"] = seconds + more_seconds
        repaired[f"{res}_ref"] = count + more_repairs
    for name in list(layers):
        layers[name], count = render.repair_nonfinite(layers[name])
        buffer = f"{res}_{name}" if name in ("noisy", "ref") else f"{res}_gbuf"
        repaired[buffer] = repaired.get(buffer, 0) + count
    return layers, times, repaired, ref_error


def refine_reference(scene, camera, width, height, ref, spp_now, target_spp, seed, max_depth):
    """Double `ref` (a reference of spp_now samples) until it has target_spp. Each doubling renders as
    many samples again with a seed of its own and averages the two: independent halves of the new
    reference, whose difference estimates its error as two halves' does. So more samples for a frame
    already rendered cost only the samples it lacks, and give the same image as rendering them at once.
    Returns (reference, estimated error after the last doubling or None, seconds, values repaired)."""
    error, seconds, repaired = None, 0.0, 0
    while spp_now < target_spp:
        out = render.render_view(scene, camera, width, height, spp_now, derive_seed(seed, "doubling", spp_now),
                                 passes=(), max_depth=max_depth)
        more, count = render.repair_nonfinite(out["radiance"])
        error, ref = _error_of_mean(ref, more), (ref + more) / 2
        spp_now, seconds, repaired = 2 * spp_now, seconds + out["wall_time_s"], repaired + count
    return ref, error, seconds, repaired


def _error_of_mean(a, b):
    """bench.metrics.reference_error of two HxWx3 renders with as many samples each."""
    import torch  # here, not at the top: a render worker that renders no halves starts without torch (~1.5 s)
    from bench import metrics
    a, b = (torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1) for x in (a, b))
    return float(metrics.reference_error(a, b))


def _count_repaired(record, repaired):
    """Record the per-buffer repair counts of a render; a re-rendered buffer's count replaces its earlier
    one, so the frame's total counts each buffer once. Records written before per-buffer counts keep
    their old total as "earlier renders"."""
    by_buffer = record.get("nonfinite_repaired_by_buffer")
    if by_buffer is None:
        by_buffer = {"earlier renders": record["nonfinite_repaired"]} if record.get("nonfinite_repaired") else {}
    by_buffer.update(repaired)
    record["nonfinite_repaired_by_buffer"] = by_buffer
    record["nonfinite_repaired"] = sum(by_buffer.values())


def render_sequence(root, job, spec, passes, variant=None):
    """Render the missing buffers of every frame of one planned sequence; returns its frame records.

    A frame whose record matches the render settings and whose EXRs hold every layer of ``passes`` is
    skipped ('resumed'); one that lacks some buffers gets only those rendered and merged in.
    Runs in a worker process: sets the Mitsuba variant itself and loads the scene once for all frames.
    """
    variant = render.use_variant(variant)
    scene_dict = scenes.make_scene(job["family"], job["scene_seed"])
    features = scenes.scene_features(scene_dict)
    settings = render_settings(spec, features, job["split"], job["sequence"])
    digest = _settings_hash(settings)
    gbuf_layers = [g for g in GBUF_LAYERS if g not in features["left_out"]]
    cameras = scenes.camera_path(job["scene_seed"], job["view"], int(spec["seq_len"]))
    lr_w, lr_h, scale = settings["lr_width"], settings["lr_height"], settings["scale"]
    sizes = {"lr": (lr_w, lr_h), "hr": (lr_w * scale, lr_h * scale)}
    loaded, records = None, []
    for frame, camera in enumerate(cameras):
        lr_path, hr_path, rec_path = frame_paths(root, job["split"], job["sequence"], frame)
        paths = {"lr": lr_path, "hr": hr_path}
        todo = _frame_todo(rec_path, paths, sizes, settings, digest, passes, gbuf_layers)
        record = todo.record
        if not todo.missing:
            if todo.stored_spp:  # it holds no reference to refine: only the record moves to the new settings
                record.update(ref_spp=settings["ref_spp"], settings_hash=digest)
                _write_json(rec_path, record)
            records.append({**record, "resumed": True})
            continue
        if loaded is None:
            loaded = render.load_scene(scene_dict, variant)
        seeds = {res: {kind: derive_seed(spec["seed"], job["scene_seed"], job["view"], frame, res, code)
                       for kind, code in _BUFFER_CODES.items()} for res in ("lr", "hr")}
        if record is None:
            record = _new_record(job, frame, camera, seeds, settings, sizes, variant, features, digest)
        written = [res for res in ("lr", "hr") if any(b.startswith(res) for b in todo.missing)]
        attributes = {"srd_sequence": job["sequence"], "srd_frame": frame}
        for res in written:
            _render_into(record, res, paths[res], sizes[res], loaded, camera, settings, seeds[res], todo,
                         gbuf_layers, attributes)
        record.update(ref_spp=settings["ref_spp"], settings_hash=digest)  # every reference is at it now
        record["buffers"] = sorted(set(record["buffers"]) | set(todo.wanted))
        record["files"] = {**(record.get("files") or {}), **{res: file_stamp(paths[res]) for res in written}}
        _write_json(rec_path, record)
        records.append({**record, "resumed": False})
    return records


@dataclasses.dataclass
class FrameTodo:
    """What a frame on disk needs (`_frame_todo`): its record (None: nothing usable), the reference spp
    it holds when its references are refined to more (else None), the layers each file holds, the
    buffers it should hold, those of them missing, and which files hold a reference to refine."""
    record: dict | None
    stored_spp: int | None
    present: dict
    wanted: list
    missing: list
    refinable: dict


def _frame_todo(rec_path, paths, sizes, settings, digest, passes, gbuf_layers) -> FrameTodo:
    record = _load_record(rec_path, digest)
    stored_spp = None
    if record is None:  # rendered with fewer reference samples on the same chain: refine, keep the rest
        record = _earlier_on_chain(rec_path, settings)
        stored_spp = record and int(record["ref_spp"])
    # a file changed since it was written (an edit, NaN written into it) or of the wrong size is
    # rendered again whole: every buffer its record holds at that resolution, not only this job's passes
    changed = {res for res, path in paths.items() if record and os.path.exists(path) and not (
        as_written(record, res, path) and _exr_size(path) in (None, tuple(sizes[res])))}
    present = {res: _present_layers(path) if record and res not in changed else set()
               for res, path in paths.items()}
    wanted = list(passes) + [b for b in (record or {}).get("buffers", []) if b[:2] in changed and b not in passes]
    # a stored reference is refined only where its file is stamped as written with this record: a
    # refinement cut off between the LR and HR files leaves one refined file beside the old record
    refinable = {res: "ref" in layers and bool(((record or {}).get("files") or {}).get(res))
                 for res, layers in present.items()}
    if stored_spp:
        wanted += [b for b in record["buffers"] if b.endswith("_ref") and b not in wanted]
        present = {res: layers - {"ref"} for res, layers in present.items()}
    missing = [b for b in wanted if not set(buffer_layers(b, gbuf_layers)) <= present[b[:2]]]
    return FrameTodo(record, stored_spp, present, wanted, missing, refinable)


def _new_record(job, frame, camera, seeds, settings, sizes, variant, features, digest) -> dict:
    """The record of a frame about to be rendered for the first time (its buffers, times and files
    are filled in as they are written)."""
    return {"split": job["split"], "family": job["family"], "scene": f"{job['family']}-{job['scene_seed']}",
            "scene_seed": job["scene_seed"], "sequence": job["sequence"], "view": job["view"],
            "frame": frame, "camera": camera, "seeds": seeds, "spp": settings["spp"],
            "ref_spp": settings["ref_spp"], "lr_size": list(sizes["lr"]), "hr_size": list(sizes["hr"]),
            "max_depth": settings["max_depth"], "variant": variant, "device": _device(variant),
            "host": socket.gethostname(),
            "features": {k: features[k] for k in ("bsdf_types", "object_kinds", "glossy",
                                                  "transmissive", "specular_chain")},
            "left_out": features["left_out"], "settings_hash": digest, "buffers": [], "time_s": {},
            "nonfinite_repaired": 0, "channels": {}}


def _render_into(record, res, path, size, loaded, camera, settings, seeds, todo, gbuf_layers, attributes):
    """Render the frame's missing buffers at resolution `res` and merge them into its EXR (the layers
    it keeps are read back and written with them, with the EXR `attributes`); `record` gets the times,
    repairs, reference error and channels."""
    missing = [b for b in todo.missing if b.startswith(res)]
    stored = (exrio.read_exr(path, ["ref"])["ref"], todo.stored_spp) \
        if todo.stored_spp and todo.refinable[res] and f"{res}_ref" in missing else None
    layers, times, repaired, ref_error = render_resolution(
        loaded, camera, *size, settings["spp"], ReferencePlan.of(settings, stored), seeds, missing, res,
        gbuf_layers, settings["max_depth"])
    if stored is not None:  # the reference's time and repairs include the samples it had
        times[f"{res}_ref_s"] += record["time_s"].get(f"{res}_ref_s", 0.0)
        repaired[f"{res}_ref"] += (record.get("nonfinite_repaired_by_buffer") or {}).get(f"{res}_ref", 0)
    if ref_error is not None:
        record.setdefault("ref_error", {})[res] = ref_error
    present = todo.present[res]
    kept = exrio.read_exr(path, sorted(present - set(layers))) if present else {}
    merged = {**kept, **layers}
    half = [g for g in gbuf_layers if settings["half_gbuffer"]]
    exrio.write_exr(path, merged, suffixes=SUFFIXES, half=half, attributes=attributes)
    record["time_s"].update(times)
    _count_repaired(record, repaired)
    record["channels"][res] = [f"{n}.{s}" for n in merged for s in SUFFIXES[n]]


def _device(variant):
    """'cuda' for GPU variants, else 'cpu' (llvm and scalar variants run on the CPU)."""
    return "cuda" if variant.startswith("cuda") else "cpu"


def _write_json(path, obj):
    """Atomic JSON write (temp file + rename)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    write_atomic(path, lambda tmp: tmp.write_text(json.dumps(obj, indent=1, default=float)))


def _leave_interrupts_to_the_parent():
    """Render workers ignore Ctrl-C (the terminal sends it to the whole process group): the parent
    stops them, instead of each printing a traceback and taking the next job."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _worker(args):
    root, job, spec, passes, variant, threads = args
    if threads:
        # Several worker processes share the cores: cap each one's Dr.Jit thread pool.
        import drjit
        drjit.set_thread_count(threads)
    return render_sequence(root, job, spec, passes, variant)


def build_dataset(root, spec, passes=BUFFERS, workers=1, progress=True, variant=None, splits=None):
    """Render the dataset described by ``spec`` (a conf/data/<scale>.yaml dict) into ``root``.

    passes: buffers to produce (subset of BUFFERS); buffers rendered by earlier builds are kept.
    splits: the splits to render (None: all); the manifest also lists the other splits whose every
    frame is already there (`complete_splits`), so it only ever holds whole splits.
    workers: at most this many processes render sequences in parallel, no more than there are sequences
    (one: this process renders it); each sets its own Mitsuba variant and a share of the cores; 'spawn'
    start, so no JIT state is forked. variant: Mitsuba variant (None: pick_variant).
    Returns the manifest as a DataFrame with one row per frame (column 'resumed': it was already complete).
    """
    passes = [p for p in passes if p]
    unknown = set(passes) - set(BUFFERS)
    if unknown:
        raise ValueError(f"unknown buffers {sorted(unknown)}; known: {BUFFERS}")
    os.makedirs(root, exist_ok=True)
    if workers > 1 and multiprocessing.get_start_method(allow_none=True) not in (None, *multiprocessing.get_all_start_methods()):
        # inside a joblib (loky) sweep job: spawned children would ask for the 'loky' start method, which a
        # fresh interpreter does not know, and die; one process rendering with all cores instead
        log.info("render: one process (this process's start method %r cannot spawn render workers)",
                 multiprocessing.get_start_method())
        workers = 1
    plan = [job for job in plan_sequences(spec) if splits is None or job["split"] in splits]
    # no more processes than sequences, and none for one: a spawned worker starts Python, Mitsuba and its
    # JIT again (about 2 s), ten times the render of a small sequence (tests/test_faults.py's)
    workers = min(workers, len(plan))
    start = time.perf_counter()
    threads = max(1, (os.cpu_count() or 1) // workers) if workers > 1 else 0
    jobs = [(os.fspath(root), job, spec, passes, variant, threads) for job in plan]
    records = []
    bar = tqdm(total=len(plan) * int(spec["seq_len"]), desc=f"render {spec.get('name', root)}", unit="frame",
               disable=None if progress else True)
    logged = [start]
    samples = {job["sequence"]: sequence_samples(spec, job) for job in plan}
    left, rendered = [sum(samples.values())], [0.0]  # samples not yet done; samples rendered by this call

    def advance(done):
        records.extend(done)
        bar.update(len(done))
        work = samples[done[0]["sequence"]] if done else 0
        left[0] -= work
        rendered[0] += work * sum(not r.get("resumed") for r in done) / max(1, len(done))  # resumed frames: free
        now = time.perf_counter()
        if progress and bar.disable and now - logged[0] >= PROGRESS_LOG_S:  # no terminal: a line now and then
            logged[0] = now
            rate = rendered[0] / (now - start)  # samples/s
            log.info("render: %d/%d frames, %.2f frames/s, about %.0f min left (counted in samples: the "
                     "sequences' references differ)", len(records), bar.total, len(records) / (now - start),
                     left[0] / max(rate, 1e-9) / 60)

    if workers <= 1:
        for job in jobs:
            advance(_worker(job))
    else:
        # ProcessPoolExecutor (not Pool): a worker that dies raises BrokenProcessPool instead of hanging.
        # 'spawn' needs the calling script to guard its entry point with `if __name__ == "__main__":`.
        context = multiprocessing.get_context("spawn")
        pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_leave_interrupts_to_the_parent)
        try:
            for future in as_completed([pool.submit(_worker, job) for job in jobs]):
                advance(future.result())
        except BaseException:  # Ctrl-C, or a worker failed: stop now, not after the queue (frames are
            # written atomically: none is left half-written). Every child multiprocessing started, not
            # pool._processes: a Ctrl-C while the pool spawns a worker leaves it out of that, and exit joins it.
            for process in multiprocessing.active_children():
                process.terminate()
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()
    bar.close()
    if splits is not None:
        records += complete_splits(root, spec, [s for s in spec["splits"] if s not in splits])
    records.sort(key=lambda r: (r["split"], r["sequence"], r["frame"]))
    present = sorted(set().union(*(r.get("buffers", []) for r in records)))
    manifest = {"spec": spec, "passes": present, "variant": records[0]["variant"] if records else variant,
                "build_wall_time_s": time.perf_counter() - start, "frames": records}
    _write_json(os.path.join(root, "manifest.json"), manifest)
    return manifest_frame(records)


def complete_splits(root, spec, splits):
    """The frame records beside `root` of those of `splits` whose every planned frame has a record
    rendered with the spec's settings (each written when its frame was complete); reads no image."""
    records = []
    for split in splits:
        part = {**spec, "splits": {split: spec["splits"][split]}}
        found = [_load_record(frame_paths(root, split, job["sequence"], frame)[2], digest)
                 for job, digest in planned_settings(part) for frame in range(int(spec["seq_len"]))]
        if all(found):
            records += found
    return records


def rebuild_manifest(root, spec):
    """Write `root`'s manifest again from the frame records beside it, rendering nothing: for a manifest
    that was damaged. It lists the splits whose every frame has its record (`complete_splits`). Returns
    the manifest, or None when no split is complete (building the dataset renders what is missing)."""
    records = complete_splits(root, spec, list(spec["splits"]))
    if not records:
        return None
    manifest = {"spec": spec, "passes": sorted(set().union(*(r.get("buffers", []) for r in records))),
                "variant": records[0]["variant"] if records else None, "frames": records}
    _write_json(os.path.join(root, "manifest.json"), manifest)
    return manifest


def manifest_frame(records):
    """Flatten frame records into a DataFrame (nested timing and seed dicts become columns)."""
    import pandas as pd  # here, not at the top: render workers never need it
    return pd.json_normalize(records, sep=".")


def load_manifest(root):
    """The manifest dict of a dataset directory."""
    with open(os.path.join(root, "manifest.json")) as f:
        return json.load(f)


def frame_view(record):
    """(scene, camera, gBuffer layers, max_depth) of a manifest frame record, so that the same view can be
    re-rendered with other settings (spp, resolution, seed), as the timing experiment does.

    A procedural frame's scene is rebuilt from its family and seed (make_scene is deterministic); a user
    scene (record with 'source') is its XML path, rendered from its own first sensor (camera None).
    Layers left out of the dataset (roughness of an all-diffuse scene) are left out here too.
    """
    left_out = record.get("left_out") or {}
    layers = [g for g in GBUF_LAYERS if g not in left_out]
    if record.get("source"):
        return record["source"], None, layers, int(record["max_depth"])
    return scenes.make_scene(record["family"], record["scene_seed"]), record["camera"], layers, \
        int(record["max_depth"])


def render_user_scene(xml_path, root, lr_width, lr_height, spp=8, ref_spp=256, seed=0, passes=BUFFERS,
                      max_depth=8, split="user", scale=2):
    """Render a user's Mitsuba XML scene (from its own first sensor) as a one-frame dataset in ``root``.

    The result loads with ``SequenceDataset(root, split, ..., seq_len=1)``, so any trained model can be run
    on it. Returns the manifest DataFrame.
    """
    variant = render.use_variant()
    scene = render.load_scene(os.fspath(xml_path), variant)
    name = os.path.splitext(os.path.basename(os.fspath(xml_path)))[0]
    lr_path, hr_path, rec_path = frame_paths(root, split, name, 0)
    seeds = {res: {kind: derive_seed(seed, name, res, code) for kind, code in _BUFFER_CODES.items()}
             for res in ("lr", "hr")}
    record = {"split": split, "family": "user", "scene": name, "scene_seed": int(seed), "sequence": name,
              "view": 0, "frame": 0, "seeds": seeds, "spp": spp, "ref_spp": ref_spp, "source": os.fspath(xml_path),
              "lr_size": [lr_width, lr_height], "hr_size": [lr_width * scale, lr_height * scale],
              "max_depth": max_depth, "variant": variant, "device": _device(variant), "host": socket.gethostname(),
              "left_out": {}, "buffers": sorted(passes), "time_s": {},
              "nonfinite_repaired": 0, "channels": {}}
    for res, (w, h), path in (("lr", (lr_width, lr_height), lr_path),
                              ("hr", (lr_width * scale, lr_height * scale), hr_path)):
        if not [b for b in passes if b.startswith(res)]:
            continue
        layers, times, repaired, _ = render_resolution(scene, None, w, h, spp, ReferencePlan(ref_spp), seeds[res],
                                                       passes, res, GBUF_LAYERS, max_depth)
        exrio.write_exr(path, layers, suffixes=SUFFIXES)
        record["time_s"].update(times)
        _count_repaired(record, repaired)
        record["channels"][res] = [f"{n}.{s}" for n in layers for s in SUFFIXES[n]]
    _write_json(rec_path, record)
    spec = {"name": name, "lr_width": lr_width, "lr_height": lr_height, "scale": scale, "spp": spp,
            "ref_spp": ref_spp, "seq_len": 1, "seed": seed,
            "splits": {split: {"families": ["user"], "sequences": 1}}}
    _write_json(os.path.join(root, "manifest.json"),
                {"spec": spec, "passes": list(passes), "variant": variant, "frames": [record]})
    return manifest_frame([record])


def tonemap_png(image):
    """Linear HDR -> 8-bit display (Reinhard x/(1+x), then gamma 2.2); for previews only."""
    image = np.clip(np.asarray(image, np.float32), 0, None)
    return (np.clip(image / (1 + image), 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


def export_examples(root, out_dir, split="train", count=4, frame=0):
    """Save preview PNGs (LR input, LR albedo, LR normal, HR reference) of ``count`` sequences.

    Normals are shown as 0.5 + 0.5 n (camera space), albedo clipped to [0, 1] with gamma 2.2.
    Returns the paths written.
    """
    from PIL import Image

    os.makedirs(out_dir, exist_ok=True)
    records = [r for r in load_manifest(root)["frames"] if r["split"] == split and r["frame"] == frame]
    paths = []
    for rec in records[:count]:
        lr_path, hr_path, _ = frame_paths(root, split, rec["sequence"], frame)
        lr, hr = exrio.read_exr(lr_path), exrio.read_exr(hr_path)
        panels = {"input": tonemap_png(lr["noisy"]),
                  "albedo": (np.clip(lr["albedo"], 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8),
                  "normal": (np.clip(lr["normal"] * 0.5 + 0.5, 0, 1) * 255 + 0.5).astype(np.uint8),
                  "reference": tonemap_png(hr["ref"])}
        for name, pixels in panels.items():
            path = os.path.join(out_dir, f"{rec['sequence']}_{frame:04d}_{name}.png")
            Image.fromarray(pixels).save(path)
            paths.append(path)
    return paths

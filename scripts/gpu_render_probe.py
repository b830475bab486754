"""How fast, and how repeatably, a Mitsuba variant renders a data preset's frames (issue #62, item 3):
the first `--per-family` sequences of each of the first `--families` families of a split, rendered twice
into two empty folders in one process with every buffer, then compared; with `--workers N`, a third time
by N processes at once.

- frames/s, and each frame's render seconds from its record (`time_s`, per buffer); the first frame of a
  sequence against the median of its later ones gives the scene's set-up and kernel compile (the first
  pass) or what a warm kernel cache leaves of it (the second);
- bit-identity: every decoded layer of every frame of the two renders, compared (np.array_equal), and
  the largest difference where they are not;
- the frames' digests (sha256 of the decoded layers) in `<out>.digests.json`; where that file already
  exists (committed by an earlier machine), the new digests are compared with it: the same frames on
  another machine;
- `--compare VARIANT` (e.g. llvm_ad_rgb): the first sequence's first `--compare-frames` frames rendered with
  it too, timed, and the relative difference of each layer from the main variant's (they draw their
  samples through other code, so the noisy layers differ by noise, the references by their error);
- a projection of the whole preset's render time from the buffers' measured seconds (the references
  scaled by each split's spp, each sequence's first-frame set-up added): a lead, not a measurement.

Writes a Markdown record (`--out`, default results/<preset>/data/<device>-render-probe.md). On a CPU dry
run: `python scripts/gpu_render_probe.py --data smoke --variant scalar_rgb --families 1 --out /tmp/p.md`.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import site
import statistics
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import datagen, exrio, render  # noqa: E402
from bench.atomic import write_atomic  # noqa: E402
from bench.datagen import BUFFERS, plan_sequences  # noqa: E402
from bench.measure import error_summary  # noqa: E402
from bench.table_writer import write_record  # noqa: E402


def probe_spec(spec: dict, split: str, families: int, per_family: int) -> dict:
    """`spec` with `split` cut to its first `families` families and `per_family` sequences of each: the
    same scenes and camera paths as the preset's first sequences of those families (a sequence's scene
    seed depends on its family and rank, not on how many the split has); every pass renders it, so its
    sequences get the split's own reference spp (`sequence_ref_spp`, naming sequences it may not keep, is dropped)."""
    part = spec["splits"][split]
    kept = list(part["families"])[:families]
    return {**spec, "splits": {split: {**{k: v for k, v in part.items() if k != "sequence_ref_spp"},
                                       "families": kept, "sequences": len(kept) * per_family}}}


def render_pass(root: Path, jobs: list[dict], spec: dict, variant: str, deadline: float) -> list[dict]:
    """Render each job's sequence into `root` (every buffer); per sequence: wall seconds and its frame
    records. Stops before a sequence once `deadline` (time.monotonic) has passed."""
    done = []
    for job in jobs:
        if time.monotonic() > deadline:
            print(f"render_probe: deadline reached before {job['sequence']}", flush=True)
            break
        start = time.perf_counter()
        records = datagen.render_sequence(root, job, spec, BUFFERS, variant=variant)
        wall = time.perf_counter() - start
        done.append({"job": job, "wall_s": wall, "records": records})
        print(f"render_probe: {variant} {job['sequence']}: {len(records)} frames in {wall:.2f} s", flush=True)
    return done


def frame_layers(root: Path, split: str, sequence: str, frame: int) -> dict[str, np.ndarray]:
    """Every layer of a frame's LR and HR files, decoded, keyed `lr.noisy`, `hr.ref`, ..."""
    lr, hr, _ = datagen.frame_paths(root, split, sequence, frame)
    return {f"{res}.{name}": value for res, path in (("lr", lr), ("hr", hr))
            for name, value in exrio.read_exr(path).items()}


def digest(layers: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(layers):
        h.update(name.encode())
        h.update(np.ascontiguousarray(layers[name]).tobytes())
    return h.hexdigest()[:16]


def relative_l2(a: np.ndarray, b: np.ndarray) -> float:
    """||a - b|| / ||b|| over the whole layer, in float64."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30))


def frame_seconds(record: dict) -> float:
    return float(sum(record["time_s"].values()))


def sequence_row(first: dict, second: dict | None) -> dict:
    """A table row: a sequence's first-frame and later-frame render seconds in both passes."""
    def split(records):
        times = [frame_seconds(r) for r in records]
        return times[0], statistics.median(times[1:]) if len(times) > 1 else float("nan")
    row = {"sequence": first["job"]["sequence"], "frames": len(first["records"]), "wall 1 s": first["wall_s"]}
    row["first frame 1 s"], row["later frame 1 s"] = split(first["records"])
    if second is not None:
        row["wall 2 s"] = second["wall_s"]
        row["first frame 2 s"], row["later frame 2 s"] = split(second["records"])
    return row


def buffer_seconds(passes: list[dict]) -> dict[str, float]:
    """Median seconds of each buffer (lr_noisy_s, lr_ref_s, hr_noisy_s, hr_ref_s: the records' `time_s`)
    over the later frames of the sequences, and `first_frame_s`: the median over sequences of the first
    frame's seconds beyond its sequence's later-frame median (the scene's set-up and kernel compile)."""
    times: dict[str, list[float]] = {}
    extra = []
    for seq in passes:
        later = seq["records"][1:]
        for record in later:
            for name, value in record["time_s"].items():
                times.setdefault(name, []).append(float(value))
        if later:
            extra.append(frame_seconds(seq["records"][0]) - statistics.median(frame_seconds(r) for r in later))
    medians = {name: statistics.median(values) for name, values in times.items()}
    if extra:
        medians["first_frame_s"] = statistics.median(extra)
    return medians


def split_seconds(data: dict, split: str, rates: dict) -> float:
    """A split's render seconds in one process, projected from measured `rates` (`lr`: their LR width and
    height, `spp`, `ref_spp`, `buffers`: seconds of each buffer of a later frame, `setup_s`: a sequence's
    first frame's extra seconds): per frame the noisy passes scaled by spp and the references by the
    split's reference spp (a sequence's own, `sequence_ref_spp`), both by the frames' pixels, plus each
    sequence's set-up."""
    part = data["splits"][split]
    frames = int(part["sequences"]) * int(data["seq_len"])
    pixels = data["lr_width"] * data["lr_height"] / (rates["lr"][0] * rates["lr"][1])
    buffers = rates["buffers"]
    noisy = (buffers.get("lr_noisy_s", 0) + buffers.get("hr_noisy_s", 0)) * data["spp"] / rates["spp"]
    ref_spp = int(part.get("ref_spp") or data["ref_spp"])
    # sequences given more reference samples (sequence_ref_spp) render theirs at that count
    ref_frames_spp = frames * ref_spp + sum(int(data["seq_len"]) * (int(spp) - ref_spp)
                                            for spp in (part.get("sequence_ref_spp") or {}).values())
    ref = (buffers.get("lr_ref_s", 0) + buffers.get("hr_ref_s", 0)) / rates["ref_spp"]
    return pixels * (frames * noisy + ref_frames_spp * ref) + int(part["sequences"]) * rates["setup_s"]


def projection(spec: dict, split: str, warm: dict[str, float], cold: dict[str, float]) -> list[str]:
    """Lines: each split's render time projected from the measured buffers of `split` (`split_seconds`):
    the later frames of the second pass, and the first frame's extra seconds of the first pass (a scene
    not rendered before)."""
    rates = {"lr": (spec["lr_width"], spec["lr_height"]), "spp": spec["spp"],
             "ref_spp": int(spec["splits"][split].get("ref_spp") or spec["ref_spp"]),
             "buffers": warm, "setup_s": cold.get("first_frame_s", 0.0)}
    lines = ["- per frame (median of the later frames, second pass): "
             + ", ".join(f"{k} {v:.3f}" for k, v in sorted(warm.items()) if k != "first_frame_s")
             + f"; per sequence, the first frame's extra seconds in the first pass: {rates['setup_s']:.2f}"]
    total = 0.0
    for name, part in spec["splits"].items():
        seconds = split_seconds(spec, name, rates)
        total += seconds
        lines.append(f"- {name}: {part['sequences']} sequences, {int(part['sequences']) * int(spec['seq_len'])} frames "
                     f"at ref {int(part.get('ref_spp') or spec['ref_spp'])} spp: about {seconds / 60:.1f} min")
    lines.append(f"- all splits: about {total / 60:.1f} min on one such device, one sequence at a time, in one process")
    return lines


def differing_layers(a: dict, b: dict) -> dict[str, float]:
    """The layers of two decodings of a frame that are not bit-identical, with their relative difference."""
    return {name: relative_l2(a[name], b[name]) for name in a
            if not np.array_equal(a[name], b[name], equal_nan=True)}


def passes_section(first: list[dict], second: list[dict], layers_total: int, differing: dict, cold: bool) -> list[str]:
    """The table of sequences and the lines on passes 1 and 2."""
    lines = []
    rows = [sequence_row(f, s) for f, s in zip(first, second + [None] * (len(first) - len(second)))]
    if rows:
        columns = list(rows[0])
        lines += ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        lines += ["| " + " | ".join(f"{r[c]:.2f}" if isinstance(r.get(c), float) else str(r.get(c, "-"))
                                    for c in columns) + " |" for r in rows]
    frames_one = sum(len(s["records"]) for s in first)
    frames_two = sum(len(s["records"]) for s in second)
    rendered_s = sum(frame_seconds(r) for s in second for r in s["records"])
    same = layers_total - sum(map(len, differing.values()))
    return lines + [
        "",
        f"- pass 1: {frames_one} frames in {sum(s['wall_s'] for s in first):.1f} s wall "
        f"from {'an empty kernel cache' if cold else 'the kernel cache the host had'}; pass 2: {frames_two} "
        f"frames in {sum(s['wall_s'] for s in second):.1f} s wall, "
        f"{frames_two / rendered_s if rendered_s else float('nan'):.2f} frames/s of render time",
        f"- pass 1 against pass 2: {same} of {layers_total} decoded layers bit-identical"
        + ("; the others, per layer (frames, largest relative difference): " + ", ".join(
            f"{name} ({len(d)}, {max(d):.3g})" for name, d in sorted(differing.items())) if differing else "")]


def digests_line(digest_file: Path, earlier: dict, digests: dict, variant: str) -> str:
    if not earlier:
        return f"- digests: {len(digests)} frames written to `{digest_file.name}` (no earlier record to compare)"
    if earlier.get("variant") != variant:
        return f"- `{digest_file.name}` holds {earlier.get('variant')}'s digests, not {variant}'s: not compared"
    shared = sorted(set(earlier["frames"]) & set(digests))
    matching = sum(earlier["frames"][k] == digests[k] for k in shared)
    return (f"- against `{digest_file.name}` as committed (written on {earlier.get('device')}): {matching} of "
            f"{len(shared)} frames' digests equal")


def kernel_cache_empty() -> bool:
    """Whether Dr.Jit's kernel cache (HOME/.drjit, OptiX's as well) holds nothing yet."""
    cache = Path(os.environ.get("HOME", "~")).expanduser() / ".drjit"
    return not cache.is_dir() or not any(cache.iterdir())


def concurrent_pass(root: Path, probed: dict, split: str, workers: int, variant: str, first: list[dict]) -> str:
    """Pass 3: the same sequences by `workers` processes at once (build_dataset), each starting with an
    empty kernel cache as a fresh machine's first render does (HOME, where Dr.Jit and OptiX keep theirs,
    is an empty folder for the spawned workers), against pass 1, one process's render (cold where the
    record's pass 1 line says so, as on a fresh machine)."""
    home = root / "home"
    home.mkdir(parents=True)
    # the user's site-packages stay where they are (a `pip install --user` mitsuba too); the whole
    # environment is restored on leaving
    with mock.patch.dict(os.environ, HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"),
                         PYTHONUSERBASE=site.getuserbase()):
        for key in ("OPTIX_CACHE_PATH", "CUDA_CACHE_PATH"):   # set, they would point past the empty HOME
            os.environ.pop(key, None)
        t0 = time.perf_counter()
        frames = len(datagen.build_dataset(root / "frames", probed, BUFFERS, workers=workers, progress=False,
                                           variant=variant, splits=[split]))
        wall = time.perf_counter() - t0
    one_process = sum(len(q["records"]) for q in first) / sum(q["wall_s"] for q in first)
    setup = buffer_seconds(first).get("first_frame_s", 0.0)
    spawned = min(workers, int(probed["splits"][split]["sequences"])) > 1   # build_dataset's rule
    cache = "an empty kernel cache" if spawned else "the host's kernel cache (one sequence, rendered in this process)"
    return (f"- pass 3: the same {frames} frames by {workers} processes at once (bench.datagen.build_dataset, "
            f"workers={workers}) from {cache}: {wall:.1f} s wall, {frames / wall:.2f} frames/s against "
            f"pass 1's {one_process:.2f} in one process, whose first frames took {setup:.2f} s more a sequence "
            "than its later ones (each process loads Mitsuba and compiles its scenes' kernels)")


def compare_variant(root: Path, tmp: Path, spec: dict, split: str, other: str, frames: int, first: dict) -> list[str]:
    """The first sequence's first `frames` frames rendered with variant `other`, against pass 1's."""
    job = first["job"]
    try:
        render.use_variant(other)
        t0 = time.perf_counter()
        records = datagen.render_sequence(tmp, job, {**spec, "seq_len": frames}, BUFFERS, variant=other)
        wall = time.perf_counter() - t0
    except Exception as err:  # noqa: BLE001 - a variant this machine cannot run is a line saying so
        return [f"{other}: failed: {error_summary(err, 200)}"]
    lines = [f"{other}: {len(records)} frames of {job['sequence']} in {wall:.1f} s (scene load and kernel "
             "compile included)"]
    for frame, record in enumerate(records):
        a = frame_layers(root, split, job["sequence"], frame)
        b = frame_layers(tmp, split, job["sequence"], frame)
        diffs = ", ".join(f"{name} {relative_l2(b[name], a[name]):.3g}" for name in sorted(a))
        lines.append(f"- frame {frame}: {frame_seconds(record):.2f} s render (against "
                     f"{frame_seconds(first['records'][frame]):.2f} s); relative L2 difference per layer: {diffs}")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="gpu", help="conf/data/<name>.yaml (default gpu)")
    parser.add_argument("--split", default="train")
    parser.add_argument("--families", type=int, default=4, help="the split's first N families")
    parser.add_argument("--per-family", type=int, default=1,
                        help="sequences of each (2: whether a family's second scene pays the first frame's set-up again)")
    parser.add_argument("--workers", type=int, default=0,
                        help="a third pass: the same sequences rendered by bench.datagen.build_dataset with N "
                             "processes at once (throughput of several renders sharing the device)")
    parser.add_argument("--variant", default="cuda_ad_rgb")
    parser.add_argument("--compare", default=None, help="another variant to render the first frames with (llvm_ad_rgb)")
    parser.add_argument("--compare-frames", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=120.0,
                        help="no sequence of pass 1 starts after this many seconds, nor of pass 2 after twice "
                             "that; pass 3 and the comparison run only if they start within three times that")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    spec = yaml.safe_load((ROOT / "conf" / "data" / f"{args.data}.yaml").read_text())
    if args.split not in spec["splits"]:
        parser.error(f"--split {args.split}: conf/data/{args.data}.yaml has {sorted(spec['splits'])}")
    for name, value, least in (("--families", args.families, 1), ("--per-family", args.per_family, 1),
                               ("--workers", args.workers, 0), ("--compare-frames", args.compare_frames, 1)):
        if value < least:
            parser.error(f"{name} {value}: expected at least {least}")
    if args.compare_frames > int(spec["seq_len"]):
        parser.error(f"--compare-frames {args.compare_frames}: a sequence of {args.data} has {spec['seq_len']} frames")
    import mitsuba as mi
    import drjit as dr
    tag = "cpu"
    if args.variant.startswith("cuda"):
        import torch
        from bench.machine import device_tag
        tag = device_tag("cuda") if torch.cuda.is_available() else "cuda-unknown"
    out = args.out or ROOT / "results" / spec["name"] / "data" / f"{tag}-render-probe.md"
    digest_file = out.with_suffix(".digests.json")
    earlier = json.loads(digest_file.read_text()) if digest_file.exists() else {}
    header = [f"# Rendering `{args.data}` with {args.variant}", ""]
    try:
        variant = render.use_variant(args.variant)
    except Exception as err:  # noqa: BLE001 - a variant this machine cannot run (no OptiX, no LLVM) is the record
        write_record(out, header + [f"mitsuba {mi.__version__}, drjit {dr.__version__}, {tag}: the variant did "
                                    f"not start: {error_summary(err, 400)}"], "the variant did not start")
        print(out.read_text())
        return 1
    header += [f"`python scripts/gpu_render_probe.py {' '.join(argv if argv is not None else sys.argv[1:])}`: "
               f"mitsuba {mi.__version__}, drjit {dr.__version__}, {tag}; split {args.split}, "
               f"{spec['lr_width']}x{spec['lr_height']} LR x{spec.get('scale', 2)}, {spec['spp']} spp, reference "
               f"{spec['splits'][args.split].get('ref_spp') or spec['ref_spp']} spp, {spec['seq_len']} frames a "
               "sequence, every buffer. Seconds: the frame records' render times (every buffer); wall: the "
               "sequence's, scene load and EXR writes included. Pass 2 renders the same frames again in the same "
               "process.", ""]
    probed = probe_spec(spec, args.split, args.families, args.per_family)
    jobs = plan_sequences(probed)
    deadline = time.monotonic() + args.seconds
    with tempfile.TemporaryDirectory() as tmp:
        one, two = Path(tmp) / "one", Path(tmp) / "two"
        cold = kernel_cache_empty()   # a fresh machine's; pass 3's gain over pass 1 compares two cold starts
        first = render_pass(one, jobs, probed, variant, deadline)
        second = render_pass(two, [s["job"] for s in first], probed, variant, deadline + args.seconds)
        digests, layers_total, differing = {}, 0, {}
        for seq in second:
            sequence = seq["job"]["sequence"]
            for frame in range(len(seq["records"])):
                a = frame_layers(one, args.split, sequence, frame)
                b = frame_layers(two, args.split, sequence, frame)
                layers_total += len(a)
                for name, diff in differing_layers(a, b).items():
                    differing.setdefault(name, []).append(diff)
                digests[f"{sequence}/{frame}"] = digest(a)
        if not earlier and digests:
            write_atomic(digest_file, lambda tmp_file: tmp_file.write_text(
                json.dumps({"variant": variant, "device": tag, "frames": digests}, indent=1) + "\n"))
        parts = {"passes": passes_section(first, second, layers_total, differing, cold), "pass 3": [],
                 "digests": [digests_line(digest_file, earlier, digests, variant)],
                 "projection": ["", "Projected render time of the whole preset (a lead, from the buffers' measured "
                                "seconds):", *projection(spec, args.split, buffer_seconds(second or first),
                                                        buffer_seconds(first))],
                 "the comparison": []}
        todo = [name for name, wanted in (("pass 3", args.workers), ("the comparison", args.compare)) if wanted]

        def save():
            write_record(out, header + [line for part in parts.values() for line in part],
                         f"{' and '.join(todo)} not in yet" if todo else None)
        save()
        late = len(first) < len(jobs) or time.monotonic() > deadline + 2 * args.seconds
        if args.workers:
            parts["pass 3"] = ["- pass 3 not run: passes 1 and 2 took their time" if late else
                               concurrent_pass(Path(tmp) / "workers", probed, args.split, args.workers, variant, first)]
            todo.remove("pass 3")
            save()
        if args.compare:
            parts["the comparison"] = [""] + (["The comparison not run: passes 1 and 2 took their time"] if late else
                                              compare_variant(one, Path(tmp) / "other", probed, args.split, args.compare,
                                                              args.compare_frames, first[0]))
            todo.remove("the comparison")
            save()
    print(out.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

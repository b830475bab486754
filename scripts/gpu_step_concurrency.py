"""Several trainings on one device at once (issue #62, item 2): N processes each take the same number of
training steps of a model at the same time, and their aggregate steps/s is set against one process
alone. A table's trainings (rows x seeds) are independent runs, so this is what `jobs=N` can gain on a GPU
whose single training leaves it idle between launches (eager: busy 18% for Ours on an H200,
results/gpu/profile/) or on a CPU whose one training does not use its cores.

Each process builds the model at the preset's widths and times `bench.experiments.speed.training_step`:
the trainer's step (bench.train: HDR encode, the loss without its perceptual term, gradient clip, Adam,
EMA) at the preset's recipe, in fp32 and the standard memory layout as the speed table's fp32 rows, on
a random batch of the preset's training crop; training data are not read (at the gpu preset they are
held on the device, docs/gpu.md). The processes take warm-up steps (and compile, with --compile), wait
for each other at a barrier, then time --steps steps each; the aggregate is their steps over the wall
time from the first start to the last end. On a CPU each process gets its share of the cores as threads
(bench.scheduler.threads_per_job).

    python scripts/gpu_step_concurrency.py --device cuda --models srd edsr --processes 1 2 4 \
        --compile none reduce-overhead --out results/gpu/profile/cuda-nvidia-h200-concurrency.md
    python scripts/gpu_step_concurrency.py --device cpu --preset smoke --models edsr --processes 1 2 \
        --steps 3 --out /tmp/c.md
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import queue
import statistics
import threading
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.table_writer import PARTIAL, write_record  # noqa: E402   PARTIAL: the first line until every configuration is in



def composed(preset: str, overrides: list[str]) -> dict:
    """The suite's config at `preset` with Hydra `overrides`, its eval split resolved as the entry point
    resolves it (bench.cli.apply_split), as plain values (the GPU scripts' one way to read the config)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf
    from bench.cli import CONF_DIR, apply_split
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=[f"preset={preset}", *overrides])
    apply_split(cfg)
    return OmegaConf.to_container(cfg, resolve=True)


TEST_EXIT = "SRD_BENCH_TEST_WORKER_EXIT"   # "<processes>:<rank>": that worker exits after warming up (tests)


def worker(rank: int, model_cfg: dict, recipe, device: str, threads: int, warmup: int, steps: int,
           compile: str | None, barrier, results) -> None:
    """One process: build, warm up (compile), wait for the others, time `steps` steps; puts (start, end)
    wall-clock seconds, or the error's first line (then the others are released from the barrier)."""
    os.environ["TORCHINDUCTOR_COMPILE_THREADS"] = str(threads)   # N processes compiling share the cores
    from bench.measure import error_summary   # a failure to import this far is a death, said by the parent
    try:
        import torch
        torch.set_num_threads(threads)
        from bench.experiments.speed import build, training_step
        recipe = replace(recipe, precision="fp32", channels_last=False, compile=compile)   # the speed table's fp32
        step = training_step(build(model_cfg, device, perturb=0.02), recipe, device)
        sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
        for _ in range(warmup):
            step()
        sync()
    except Exception as err:  # noqa: BLE001 - a configuration that fails here is that row, said
        barrier.abort()
        results.put(error_summary(err, 160))
        return
    if os.environ.get(TEST_EXIT) == f"{barrier.parties}:{rank}":
        os._exit(3)   # a worker that dies without a word (tests/test_gpu_job.py)
    try:
        barrier.wait()
    except threading.BrokenBarrierError:
        results.put("released: another process of this configuration failed, died or timed out first")
        return
    try:
        start = time.time()   # wall clock: comparable between the processes
        for _ in range(steps):
            step()
        sync()
        results.put((start, time.time()))
    except Exception as err:  # noqa: BLE001 - out of memory, a graph replay: the row, not a hang
        results.put(error_summary(err, 160))


def measure(model_cfg: dict, recipe, device: str, processes: int, warmup: int, steps: int, compile: str | None,
            timeout: float) -> dict:
    """Run `processes` workers at once; per-process ms/step and aggregate steps/s, or why it failed.
    Never waits past `timeout` in all: a worker that dies without a word releases the others."""
    from bench.scheduler import threads_per_job
    spawn = multiprocessing.get_context("spawn")
    barrier, results = spawn.Barrier(processes, timeout=timeout), spawn.Queue()
    threads = threads_per_job(processes)
    workers = [spawn.Process(target=worker, args=(rank, model_cfg, recipe, device, threads, warmup, steps, compile,
                                                 barrier, results)) for rank in range(processes)]
    for w in workers:
        w.start()
    got, deadline = [], time.monotonic() + timeout
    while len(got) < processes:
        if time.monotonic() > deadline:
            barrier.abort()
            got.append(f"no answer from every process within --timeout {timeout:g} s")
            break
        try:
            got.append(results.get(timeout=2))
            continue
        except queue.Empty:
            pass
        dead = [w.exitcode for w in workers if w.exitcode not in (None, 0)]
        if dead:
            barrier.abort()   # the others stop waiting for it, and say so
            if len(got) + len(dead) >= processes:   # every process has answered or died
                got.append(f"a process exited with code {dead[0]} without a word")
                break
    for w in workers:
        w.join(timeout=5)
        if w.is_alive():
            w.kill()
            w.join()
    said = [g for g in got if isinstance(g, str)]
    if said:   # the cause before the processes it released
        return {"failed": ([g for g in said if not g.startswith("released:")] or said)[0]}
    wall = max(end for _, end in got) - min(start for start, _ in got)
    return {"ms": statistics.mean((end - start) / steps * 1000 for start, end in got),
            "steps/s": processes * steps / wall, "threads": threads}


def done_rows(out: Path, title: str, settings: str) -> dict[tuple[str, str, str], str]:
    """The rows of a PARTIAL record at `out` of the same machine (`title`) and `settings`, by (model label,
    path, processes): a job step stopped at its limit goes on from them instead of timing them again. A
    record of other settings is timed again, whole."""
    text = out.read_text() if out.exists() else ""
    if not text.startswith(PARTIAL):
        return {}
    if f"\n{title}\n" not in text or f"`: {settings} ms/step" not in text:
        print(f"{out}: a PARTIAL record of another machine or other settings: every configuration is timed again")
        return {}
    rows = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| model")]
    return {tuple(cell.strip() for cell in line.split("|")[1:4]): line for line in rows}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--preset", default="gpu", help="the widths, batch, frames, crop and lr (conf/preset)")
    parser.add_argument("--models", nargs="+", default=["srd", "edsr", "rae", "kpcn", "cfm"])
    parser.add_argument("--processes", nargs="+", type=int, default=[1, 2, 4])
    parser.add_argument("--compile", nargs="+", default=["none"],
                        help="paths: none (eager) and/or a torch.compile mode, as the trainer's train.compile")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds a configuration may take in all")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="Hydra overrides (models.edsr.channels=8)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    compiled = any(path != "none" for path in args.compile)
    # reduce-overhead's first two calls warm up and record the graphs: they must not be timed
    for name, values, least in (("--processes", args.processes, 1), ("--steps", [args.steps], 1),
                                ("--warmup", [args.warmup], 3 if compiled else 1)):
        if min(values) < least:
            parser.error(f"{name}: expected at least {least}" + (" with --compile" if name == "--warmup" else ""))
    cfg = composed(args.preset, args.set)
    unknown = [m for m in args.models if m not in cfg["models"]]
    if unknown:
        parser.error(f"--models: no model {unknown[0]!r}; models: {', '.join(cfg['models'])}")
    from bench.experiments.speed import LABELS, step_note
    from bench.machine import device_tag
    from bench.train import Recipe
    import torch
    recipe = Recipe.from_config(cfg["train"])
    where = device_tag(args.device)
    # what a row depends on (the command line may differ: more processes, another --out)
    settings = (f"preset {args.preset} widths and recipe" + (f" with {' '.join(args.set)}" if args.set else "")
                + f", {recipe.batch_size} x {recipe.seq_len} frames of {recipe.crop}x{recipe.crop} LR a step, "
                f"{step_note(recipe)}, in fp32; torch {torch.__version__}. Each process: {args.warmup} warm-up "
                f"steps, then {args.steps} timed once all are warm.")
    title = f"# Training steps of several processes at once on {where}"
    header = [title, "",
              f"`python scripts/gpu_step_concurrency.py {' '.join(argv if argv is not None else sys.argv[1:])}`: "
              f"{settings} ms/step: the processes' mean; steps/s: all processes' steps over the wall time from the "
              "first start to the last end; x one: steps/s against one process on the same path.", "",
              "| model | path | processes | threads each | ms/step | steps/s | x one |", "|---|---|---|---|---|---|---|"]
    # every model eager first: a compiled path's configurations each compile again (from the Inductor cache)
    todo = [(m, c, n) for c in args.compile for m in args.models for n in sorted(set(args.processes))]
    kept = done_rows(args.out, title, settings)
    rows, alone = [], {}
    for done, (name, path, processes) in enumerate(todo, 1):
        label = LABELS.get(name, name)
        if (label, path, str(processes)) in kept:
            rows.append(kept[(label, path, str(processes))])
            cells = [c.strip() for c in rows[-1].split("|")]
            if processes == 1 and cells[6] != "-":
                alone[(name, path)] = float(cells[6])
            continue
        got = measure(cfg["models"][name], recipe, args.device, processes, args.warmup, args.steps,
                      None if path == "none" else path, args.timeout)
        if "failed" in got:
            rows.append(f"| {label} | {path} | {processes} | - | - | - | failed: {got['failed']} |")
        else:
            if processes == 1:
                alone[(name, path)] = got["steps/s"]
            one = alone.get((name, path))
            rows.append(f"| {label} | {path} | {processes} | {got['threads']} | {got['ms']:.1f} | {got['steps/s']:.2f} | "
                        + (f"{got['steps/s'] / one:.2f}" if one else "-") + " |")
        print(rows[-1], flush=True)
        write_record(args.out, header + rows, f"{done} of {len(todo)} configurations timed" if done < len(todo) else None)
    return 0


if __name__ == "__main__":
    sys.exit(main())

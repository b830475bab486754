"""Helpers shared by the tests: smoke-preset experiments, small models and their inputs."""
import atexit
import dataclasses
import fcntl
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import pytest

# One OpenMP thread per core among pytest-xdist's workers, set before torch loads its OpenMP runtime and
# inherited by every `python -m bench` a test starts: two workers of two threads each on 2 cores made
# every torch process spin-wait for a core, most of make test's time (figures: git log of this line).
# Tests that time or count threads set their own.
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1)
                                                      // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))))
# Inductor compiles its C++ kernels in a pool of one process per core; on 2 cores the pool's start-up costs
# more than it saves: test_train's compiled-step test took 64 s with it and 37 s in one thread (plain
# pytest, a render running beside both). Measured on 2 cores only, so set there only.
if (os.cpu_count() or 1) <= 2:
    os.environ.setdefault("TORCHINDUCTOR_COMPILE_THREADS", "1")
import torch  # noqa: E402

# Without a GPU the fused Triton kernels run in Triton's interpreter (read when bench.nn.triton_kernels
# is imported, so set before anything imports bench: with SRD_BENCH_FUSED_GPU=1 bench.nn imports them);
# with one, tests/test_cuda.py compiles them.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

from baselines.cfm import CFMNet  # noqa: E402
from baselines.edsr import EDSR  # noqa: E402
from baselines.kpcn import KPCN  # noqa: E402
from baselines.rae import RAE  # noqa: E402
# Mirroring to MLflow costs seconds per command; the tests that check it turn it on (tracking=mlflow).
os.environ.setdefault("SRD_TRACKING", "none")
# What the suite caches per machine (predict's measured fast path) stays out of the user's home, and goes
# with the process (each pytest process, xdist's workers included, left one behind in /tmp before).
os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp(prefix="srd-bench-test-cache-")
atexit.register(shutil.rmtree, os.environ["XDG_CACHE_HOME"], ignore_errors=True)


def _parse_each_config_file_once():
    """Hydra has OmegaConf parse every YAML file of a config afresh at each compose, and the suite composes
    some 600 times (every experiment and study at every preset, each in-process command). Here a file's
    parse is kept by its path and text (an edited file is parsed again) and each compose gets a copy, from
    which OmegaConf builds its config as before: a compose of conf's sota at the cpu preset took 0.091 s
    against 0.105 s (AVX512 EPYC). OmegaConf's other uses of yaml (dump, a YAML string) are untouched."""
    import copy
    import io
    import types
    import yaml
    from omegaconf import omegaconf as omegaconf_module
    parses = {}

    def load(stream, Loader):
        name = getattr(stream, "name", None)
        if not isinstance(name, str):
            return yaml.load(stream, Loader=Loader)
        text = stream.read()
        key = (name, text, Loader.__qualname__)    # OmegaConf makes its Loader class anew at each load
        if key not in parses:
            named = io.StringIO(text)
            named.name = name                      # a YAML error names the file, as it would unpatched
            parses[key] = yaml.load(named, Loader=Loader)
        return copy.deepcopy(parses[key])
    omegaconf_module.yaml = types.SimpleNamespace(**{**vars(yaml), "load": load})


_parse_each_config_file_once()


# The files that take longest, first (`make test --durations`, summed per file, in this order): pytest-xdist
# hands whole files to its workers in the order collected (make test passes --no-loadscope-reorder; its
# default orders files by their number of tests, which left files of two to six tests and half a minute
# each to the end, one worker idle). An order only: a stale list costs balance, never a test. Measured
# after the GPU job's steps left make test (make test-gpu-job: tests/test_gpu_job.py, the note at its top).
LONGEST_FIRST = ["test_experiments.py", "test_cli.py", "test_faults.py", "test_adopt.py", "test_stability.py",
                 "test_scheduler.py", "test_tracking.py", "test_train.py", "test_fused_gpu.py", "test_speed.py",
                 "test_gpu_speedrun_plan.py", "test_eval_data.py", "test_measure.py", "test_gpu_job.py",
                 "test_render_repro.py", "test_layers.py", "test_distributed.py"]


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order


# the dataset the smoke tests share (`smoke_data`): references at 64 spp, not 256, render in half the time
SMOKE_DATA = ["preset=smoke", "data.splits.train.sequences=4", "data.ref_spp=64"]


def smoke_overrides(root, steps=2):
    """Hydra overrides for a fast smoke-preset run whose runs, results and data stay under `root`: plumbing,
    so 2 training steps (the tables fixture of tests/test_experiments.py trains 40 runs with it)."""
    return [*SMOKE_DATA, f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}",
            f"data_dir={root / 'data'}", "progress=false", f"train.steps={steps}",
            f"train.checkpoint_every={steps}", "train.val_sequences=1"]  # a curve of 1 sequence: half the scoring


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory):
    """A function copying the smoke dataset `smoke_overrides` asks for (SMOKE_DATA: every split and buffer,
    4 training sequences) into a data_dir: rendered once per test run and shared by the pytest-xdist workers
    (a render is deterministic; the modules that render it would each take 20-35 s). A run with another
    data spec renders its copy again, as it would any dataset of another spec."""
    base = tmp_path_factory.getbasetemp()
    shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "smoke-data"
    with open(f"{shared}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one worker renders, the other waits for it
        if not (shared / "manifest.json").exists():
            done = bench_here("+experiment=data", "progress=false", *SMOKE_DATA, f"data_dir={shared}",
                              f"runs_dir={shared}-runs", f"results_dir={shared}-results")
            assert done.returncode == 0, done.stderr[-3000:]

    def copy(data_dir: Path, runs_dir: Path | None = None) -> Path:
        """`runs_dir`: the render's data run record goes there too (as if this store had rendered it)."""
        shutil.copytree(shared, data_dir, ignore=shutil.ignore_patterns(".render.lock"))
        if runs_dir is not None:
            shutil.copytree(Path(f"{shared}-runs") / "data", runs_dir / "data")
        return data_dir
    return copy


def smoke_context(**fields):
    """The experiments' Context as the CLI builds it from the real config at the smoke preset (`make_context`),
    with `fields` replaced: tests never restate the config's defaults."""
    from hydra import compose, initialize_config_dir
    from bench.cli import CONF_DIR, make_context
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        ctx = make_context(compose("config", overrides=["preset=smoke"]))
    return dataclasses.replace(ctx, **fields)


def config_recipe(**fields):
    """A training Recipe from conf/config.yaml's `train:` (which sets every field) with `fields` replaced:
    tests never restate the config's values."""
    from omegaconf import OmegaConf
    from bench.train import Recipe
    config = OmegaConf.to_container(OmegaConf.load(Path(__file__).parents[1] / "conf/config.yaml").train)
    return dataclasses.replace(Recipe.from_config(config), **fields)


# Small instances of every learned baseline, (constructor, arguments), and their inputs: shared by the
# files that check models on every device.
SMALL = {
    "edsr": (EDSR, dict(channels=8, blocks=2)),
    "edsr_dilated_deform": (EDSR, dict(channels=8, blocks=2, dilation=2, deformable=True)),
    "rae": (RAE, dict(width=8)),
    "kpcn": (KPCN, dict(channels=8, layers=3, filter_size=5)),
    "cfm": (CFMNet, dict(channels=8, blocks=2)),
    "cfm_deform": (CFMNet, dict(channels=8, blocks=2, deformable_blocks=2)),
}


def perturbed(model, std=0.02, seed=0):
    """`model` with N(0, std) added to every parameter, in place. At initialisation the learned models'
    zero convs (the input_residual output conv, CFM gamma/beta, deform offsets) make the output the
    bilinear upsample exactly, whatever the gBuffer or the other frames: a test of what the network does
    with its inputs needs these perturbed."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(std * torch.randn(p.shape, generator=gen, dtype=p.dtype).to(p.device))
    return model


def inputs(b=2, t=3, h=13, w=17, g=7, seed=0):
    """Noisy LR frames (b, t, 3, h, w) and a gBuffer (b, t, g, h, w), uniform in [0, 1)."""
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(b, t, 3, h, w, generator=gen), torch.rand(b, t, g, h, w, generator=gen)


# ---------------------------------------------------------------- the command line, and a smoke run store

REPO = Path(__file__).resolve().parents[1]
# What the project's shared folder beside a checkout holds (not shipped: the product never reads it; the
# tests of these files skip where it is absent, as in a CI clone elsewhere): the paper's full text (its
# LaTeX tables and the loss ratios) and two partial torchvision VGG16 files.
PAPER_TEXT = Path(os.environ.get("SRD_PAPER_TEXT") or REPO.parent / "shared" / "seed" / "000_0570fe89fc995d8b.txt")
VGG16_WEIGHTS_DIR = Path(os.environ.get("SRD_VGG16_WEIGHTS_DIR") or REPO.parent / "shared" / "weights")


def bench(*args, cwd=REPO, timeout=600):
    """`python -m bench ARGS` in a process of its own (`python_process`): for what only a process shows (an
    edited copy of the code, another folder, a launcher's processes). Elsewhere `bench_here`; a process to
    signal or to run beside others: subprocess.Popen."""
    return python_process("-m", "bench", *args, cwd=cwd, timeout=timeout,
                          env=dict(os.environ, HYDRA_FULL_ERROR="0", PYTHONUNBUFFERED="1"))


_preloaded = {"env": dict(os.environ), "lock": threading.Lock()}   # its environment: as this file set it up


def _forks(env: dict) -> bool:
    """Whether the preloaded interpreter can run a command in `env`: it differs from the interpreter's own
    only in what is read after the imports there (preloaded.READ_LATE, but for READ_AT_IMPORT)."""
    from preloaded import READ_AT_IMPORT, READ_LATE
    start = _preloaded["env"]
    return all(k.startswith(READ_LATE) and not k.startswith(READ_AT_IMPORT)
               for k in {*start, *env} if env.get(k) != start.get(k))


def python_process(*argv, cwd=REPO, env=None, timeout=600) -> subprocess.CompletedProcess:
    """`python ARGV` as `subprocess.run(..., capture_output=True, text=True, stdin=DEVNULL)` runs it, in a
    process forked from one that imported torch, numpy, pandas, Hydra and Dynamo (tests/preloaded.py, started at
    the first call; what differs from a fresh interpreter is said there): the same process but for the
    1-3 s of those imports. The command imports the project afresh from its folder and PYTHONPATH. One
    command at a time; an environment that differs from this process's start in what torch & co. read at
    import gets a fresh interpreter. Raises subprocess.TimeoutExpired after `timeout` seconds, the process
    killed."""
    argv, env = [str(a) for a in argv], dict(os.environ if env is None else env)
    if not Path(cwd).is_dir():
        raise FileNotFoundError(f"no folder {cwd}")          # as subprocess.run raises
    if not _forks(env):
        return subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=timeout, stdin=subprocess.DEVNULL)
    with _preloaded["lock"], tempfile.TemporaryDirectory() as tmp:
        server = _preloaded.get("server")
        if server is None or server.poll() is not None:
            log = tempfile.NamedTemporaryFile("w", prefix="srd-bench-preloaded-", suffix=".log", delete=False)
            server = _preloaded["server"] = subprocess.Popen(
                [sys.executable, str(REPO / "tests" / "preloaded.py")], cwd=REPO, env=_preloaded["env"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True)
            _preloaded["log"] = Path(log.name)
            # its loop ends at the end of its input; waited for, so its children's CPU time counts to this process
            atexit.register(lambda: (server.stdin.close(), server.wait(), log.close(), os.unlink(log.name)))
        out, err, ident = Path(tmp) / "out", Path(tmp) / "err", os.urandom(8).hex()
        try:
            server.stdin.write(json.dumps({"id": ident, "argv": argv, "cwd": str(cwd), "env": env, "out": str(out),
                                           "err": str(err), "timeout": timeout}) + "\n")
            server.stdin.flush()
            answer = json.loads(server.stdout.readline() or "{}")
            assert answer.get("id") == ident, \
                f"tests/preloaded.py answered {answer} running {argv}: {_preloaded['log'].read_text()[-2000:]}"
        except BaseException:       # an answer left unread would be the next command's: start again
            server.kill()
            server.wait()
            raise
        said = [out.read_text(errors="backslashreplace"), err.read_text(errors="backslashreplace")]
    if answer["code"] is None:
        raise subprocess.TimeoutExpired([sys.executable, *argv], timeout, *said)
    return subprocess.CompletedProcess([sys.executable, *argv], answer["code"], *said)


def bench_here(*args, timeout=600) -> subprocess.CompletedProcess:
    """`python -m bench ARGS` run in this process (bench.cli.entry, Hydra included), as `command_here` runs
    a command, without the process's seconds of imports (torch, Hydra, the project: about 2.5 s of every
    `bench` call). keep_freed_memory=false unless given: its mallopt would stay for the rest of this
    process."""
    from bench.cli import entry
    argv = ["bench", *map(str, args)]
    if not any(a.startswith("keep_freed_memory=") for a in argv):
        argv.append("keep_freed_memory=false")
    return command_here(entry, argv, timeout)


def srd_bench_here(*args, timeout=600) -> subprocess.CompletedProcess:
    """`srd-bench ARGS` (its console script's function, bench.predict.main) run in this process, as
    `command_here` runs a command."""
    from bench.predict import main
    return command_here(lambda: sys.exit(main()), ["srd-bench", *map(str, args)], timeout)


def command_here(entry, argv, timeout) -> subprocess.CompletedProcess:
    """`entry()` run with `argv` as sys.argv, from the repository: the exit code and what it printed, as the
    command's process would return them. As a process would show it: file descriptors 1 and 2 are captured
    (C++ libraries' lines and child processes' too, in the order written), and warnings print as in a fresh
    process (pytest would record them instead). Afterwards the logging, the folder, argv and the environment
    are as before. A command still running after `timeout` seconds ends this process (pytest-xdist reports
    the worker gone), with every thread's traceback."""
    import faulthandler
    import logging
    import tempfile
    import warnings
    root, saved = logging.getLogger(), (sys.argv, os.getcwd(), dict(os.environ), sys.stdout, sys.stderr)
    saved_handlers, saved_level = root.handlers[:], root.level
    sys.stdout.flush()
    sys.stderr.flush()
    saved_fds = os.dup(1), os.dup(2)
    with tempfile.TemporaryFile() as out_file, tempfile.TemporaryFile() as err_file, \
            open(saved_fds[1], "w", closefd=False) as real_stderr:
        os.dup2(out_file.fileno(), 1)
        os.dup2(err_file.fileno(), 2)
        sys.stdout = open(1, "w", buffering=1, closefd=False, errors="backslashreplace")  # line-buffered, as
        sys.stderr = open(2, "w", buffering=1, closefd=False, errors="backslashreplace")  # PYTHONUNBUFFERED
        sys.argv, code = argv, 0
        os.environ["HYDRA_FULL_ERROR"] = "0"
        os.chdir(REPO)
        faulthandler.dump_traceback_later(timeout, exit=True, file=real_stderr)
        try:
            with warnings.catch_warnings():
                warnings.resetwarnings()  # a fresh process's filters (python -W none), printed to stderr
                for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
                    warnings.filterwarnings("ignore", category=category)
                warnings.filterwarnings("default", category=DeprecationWarning, module="__main__")
                warnings.showwarning = lambda message, category, filename, lineno, file=None, line=None: \
                    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))
                entry()
        except SystemExit as stop:
            from preloaded import exit_status     # the interpreter's, as a forked command's (a message printed)
            code = exit_status(stop)
        finally:
            faulthandler.cancel_dump_traceback_later()
            sys.stdout.close()
            sys.stderr.close()
            sys.argv, cwd, environ, sys.stdout, sys.stderr = saved
            os.dup2(saved_fds[0], 1)
            os.dup2(saved_fds[1], 2)
            os.chdir(cwd)
            os.environ.clear()
            os.environ.update(environ)
            for handler in root.handlers:  # Hydra's console and log-file handlers
                if handler not in saved_handlers:
                    handler.close()
            root.handlers[:] = saved_handlers
            root.setLevel(saved_level)
        out_file.seek(0)
        err_file.seek(0)
        said = [f.read().decode(errors="backslashreplace") for f in (out_file, err_file)]
    for fd in saved_fds:
        os.close(fd)
    return subprocess.CompletedProcess(argv, code, *said)


@pytest.fixture(scope="module")
def smoke_dirs(tmp_path_factory, smoke_data):
    """`make run`, shorter, run once for the module; the tests below read its store in any order."""
    root = tmp_path_factory.mktemp("smoke")
    smoke_data(root / "data")
    args = [f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}", f"data_dir={root / 'data'}",
            "progress=false", "train.steps=12", *SMOKE_DATA]  # adopt replays 10 steps
    first = bench_here("+experiment=smoke", *args)
    assert first.returncode == 0, first.stderr[-3000:]
    return args, root


def copy_of_project_and_store(smoke_dirs, tmp_path):
    """A copy of the project's code (to edit) and of the smoke run store, and the overrides that run the
    copy against the copied store and the smoke data."""
    args, root = smoke_dirs
    project = tmp_path / "project"
    for part in ("bench", "baselines", "conf"):
        shutil.copytree(REPO / part, project / part, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    shutil.copytree(root / "runs", tmp_path / "runs", ignore=shutil.ignore_patterns("mlflow*", "hydra"))
    return project, [a for a in args if not a.startswith(("runs_dir=", "results_dir="))] + [
        f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}"]

"""A Python that imported torch, numpy, pandas, Hydra and Dynamo once, and forks a process for each command it is
sent (tests/conftest.py's `python_process`): `python ARGV` without the 1-3 s every such process spent
importing them again. The child runs the command as that interpreter would: `-m MODULE` (through runpy, as
the interpreter does), `-c CODE` or a script as __main__, sys.path as it would have it (the command's
folder, its PYTHONPATH, the site's folders), the project's modules imported afresh from there (this
process imports none of them), in the command's folder and environment, stdin empty, file descriptors 1
and 2 in files, numpy's random numbers seeded anew, non-daemon threads joined and atexit run at the end,
and its exit status the interpreter's (a SystemExit message printed, an uncaught exception's traceback
without this file's frames and 1, Ctrl-C's SIGINT).
What it does not: the environment the libraries imported here read at import (OMP_NUM_THREADS, locale,
...) is this process's, so the caller forks only for commands whose environment differs from it in
READ_LATE alone; the hash seed is this process's; the interpreter's final teardown (modules cleared, their
objects finalised) does not run, so a file the command never closed is not flushed.
Reads one JSON request a line on stdin: {id, argv, cwd, env, out, err, timeout}; answers {id, code} a line,
code null where the command ran past its timeout (then killed). One command at a time.
    python tests/preloaded.py
"""
import atexit, json, os, runpy, signal, sys, threading, time, traceback, types, warnings
import hydra, numpy, omegaconf, pandas, torch, yaml  # noqa: F401,E401   imported once, before the forks
# Dynamo too: a training's first optimizer imports it (and with it Triton and Inductor's config), 1-2 s of
# every training command otherwise. Inductor's config reads TORCHINDUCTOR_* at that import, so a command
# whose environment differs there gets an interpreter of its own (READ_LATE leaves them out); one that sets
# them in its own code before its first compile would find them read already (the project's one such
# place, the worker of scripts/gpu_step_concurrency.py, runs in a process it spawns). The cache folder is
# read again at each compile's use of it; Dynamo's precompile cache took it at import, but that cache is
# on only with TORCH_CACHING_PRECOMPILE=1, which READ_LATE leaves out too.
import torch._dynamo  # noqa: F401,E402

# What a command's environment may change: read by the project's modules (which the child imports), by
# Triton (its knobs read the environment when asked) and Dr.Jit (imported when first used, not here; the
# project sets DRJIT_LIBLLVM_PATH), or after start-up
READ_LATE = ("PYTHONPATH", "PYTHONUNBUFFERED", "HYDRA_FULL_ERROR", "SRD_", "PYTEST_", "TRITON_", "DRJIT_",
             "TORCHINDUCTOR_CACHE_DIR")
READ_AT_IMPORT = ("TRITON_BACKENDS_IN_TREE",)   # of READ_LATE's, read when Dynamo imported Triton here
IMPORTED_FILTERS = warnings.filters[:]   # a fresh interpreter's, and what importing torch & co. adds


def pythonpath_entries() -> list[str]:
    """PYTHONPATH's folders as the interpreter adds them: each made absolute, an empty one the folder."""
    pythonpath = os.environ.get("PYTHONPATH")
    return [os.path.abspath(p) for p in pythonpath.split(os.pathsep)] if pythonpath else []


SITE_PATH = [p for p in sys.path[1:] if p not in pythonpath_entries()]   # without this file's folder


def python_path(first: str) -> list[str]:
    """sys.path as a fresh interpreter builds it for a command: `first` (its folder, or '' for -c), the
    command's PYTHONPATH, then the site's."""
    return [first, *pythonpath_entries(), *SITE_PATH]


def exit_status(stop: SystemExit) -> int:
    """What CPython exits with for an uncaught SystemExit (printing a code that is not an int)."""
    if stop.code is None or isinstance(stop.code, int):
        code = stop.code or 0
        return code & 0xFF if -2**63 <= code < 2**63 else 255   # beyond a C long: -1, as CPython exits
    print(stop.code, file=sys.stderr)
    return 1


def run(argv: list[str]) -> int:
    """`python ARGV` in this process, already in the command's folder and environment."""
    main = sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        if argv[0] == "-m":
            sys.argv, sys.path[:] = ["-m", *argv[2:]], python_path(os.getcwd())
            runpy._run_module_as_main(argv[1])             # what the interpreter's -m calls
        elif argv[0] == "-c":
            sys.argv, sys.path[:] = ["-c", *argv[2:]], python_path("")
            exec(compile(argv[1], "<string>", "exec", dont_inherit=True), main.__dict__)
        else:
            sys.argv, sys.path[:] = list(argv), python_path(os.path.dirname(os.path.realpath(argv[0])))
            path = os.path.abspath(argv[0])                # as the interpreter names a script since 3.9
            with open(path, "rb") as source:
                code = compile(source.read(), path, "exec", dont_inherit=True)
            main.__file__, main.__cached__ = path, None
            exec(code, main.__dict__)
        return 0
    except SystemExit as stop:
        return exit_status(stop)
    except KeyboardInterrupt as err:
        print_uncaught(err)
        return -signal.SIGINT
    except BaseException as err:
        print_uncaught(err)
        return 1


def print_uncaught(err: BaseException) -> None:
    """The traceback the interpreter prints, without this file's frames (a SyntaxError in -c's code: no
    traceback, the error alone, as there)."""
    tb = err.__traceback__
    while tb is not None and tb.tb_frame.f_code.co_filename == __file__:
        tb = tb.tb_next
    traceback.print_exception(type(err), err, tb)


def child(request: dict) -> None:
    """The forked process: never returns into the server's loop."""
    code = 1
    try:
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        with open(os.devnull) as empty, open(request["out"], "w") as out, open(request["err"], "w") as err:
            for fd, f in ((0, empty), (1, out), (2, err)):
                os.dup2(f.fileno(), fd)
        unbuffered = bool(os.environ.get("PYTHONUNBUFFERED"))   # else stdout block-buffered, stderr by line
        sys.stdin = sys.__stdin__ = open(0, closefd=False)
        sys.stdout = sys.__stdout__ = open(1, "w", buffering=1 if unbuffered else -1, closefd=False)
        sys.stderr = sys.__stderr__ = open(2, "w", buffering=1, closefd=False, errors="backslashreplace")
        warnings.filters[:] = IMPORTED_FILTERS
        warnings._filters_mutated()
        numpy.random.seed()          # from the OS, as a new process seeds it (Python's random reseeds at fork
                                     # itself; torch's default seed is the same in every process anyway)
        code = run(request["argv"])
        threading._shutdown()        # as the interpreter's exit: non-daemon threads joined, then atexit
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
        if code < 0:                 # Ctrl-C: ended by SIGINT, as CPython ends then
            signal.signal(-code, signal.SIG_DFL)
            os.kill(os.getpid(), -code)
    finally:
        os._exit(code & 0xFF if code >= 0 else 1)


def serve() -> None:
    assert not [m for m in sys.modules if m.split(".")[0] in ("bench", "baselines", "drjit", "mitsuba")], \
        "imported here: READ_LATE would not hold"
    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            child(request)
        deadline = time.monotonic() + (request["timeout"] if request["timeout"] is not None else float("inf"))
        while not (ended := os.waitpid(pid, os.WNOHANG))[0] and time.monotonic() < deadline:
            time.sleep(0.01)
        if not ended[0]:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        code = os.waitstatus_to_exitcode(ended[1]) if ended[0] else None
        print(json.dumps({"id": request["id"], "code": code}), flush=True)


if __name__ == "__main__":
    serve()

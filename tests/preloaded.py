"""A Python that imported torch, numpy, pandas and Hydra once, and forks a process for each command it is
sent (tests/conftest.py's `python_process`): `python ARGV` without the seconds every test's own process
spent importing them again. The child runs the command as that interpreter would: `-m MODULE`, `-c CODE`
or a script as __main__, sys.path as it would have it (the command's folder, its PYTHONPATH, the site's
folders), the project's modules imported afresh from there (this process imports none of them), in the
command's folder and environment, stdin empty, file descriptors 1 and 2 in files, the warnings filters a
fresh interpreter has, non-daemon threads joined and atexit run at the end, and its exit status the
interpreter's (a SystemExit message printed, an uncaught exception's traceback, less this file's and
runpy's frames, and 1; Ctrl-C's SIGINT).
What the libraries imported here read from the environment at import (OMP_NUM_THREADS, ...) is this
process's: the caller starts a real interpreter for a command whose environment differs there.
Reads one JSON request a line on stdin: {argv, cwd, env, out, err, timeout}; answers {code} a line, code
null where the command ran past its timeout (then killed).
    python tests/preloaded.py
"""
import atexit, json, os, runpy, signal, sys, threading, time, traceback, types, warnings
FRESH_FILTERS = warnings.filters[:]   # as a fresh interpreter has them, before any import changes them
import hydra, numpy, omegaconf, pandas, torch, yaml  # noqa: F401,E401   imported once, before the forks

OWN_PYTHONPATH = [os.path.abspath(p) for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
SITE_PATH = [p for p in sys.path[1:] if p not in OWN_PYTHONPATH]   # without this file's folder


def exit_status(stop: SystemExit) -> int:
    """What CPython exits with for an uncaught SystemExit (printing a code that is not an int)."""
    if stop.code is None or isinstance(stop.code, int):
        code = stop.code or 0
        return code & 0xFF if -2**63 <= code < 2**63 else 255   # beyond a C long: -1, as CPython exits
    print(stop.code, file=sys.stderr)
    return 1


def run(argv: list[str]) -> int:
    """`python ARGV` in this process, already in the command's folder and environment."""
    extra = [os.path.abspath(p) for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    try:
        if argv[0] == "-m":
            sys.argv, sys.path[:] = [argv[1], *argv[2:]], [os.getcwd(), *extra, *SITE_PATH]
            runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
        elif argv[0] == "-c":
            sys.argv, sys.path[:] = ["-c", *argv[2:]], ["", *extra, *SITE_PATH]
            main = types.ModuleType("__main__")
            sys.modules["__main__"] = main
            exec(compile(argv[1], "<string>", "exec"), main.__dict__)
        else:
            script = os.path.abspath(argv[0])
            sys.argv, sys.path[:] = list(argv), [os.path.dirname(script), *extra, *SITE_PATH]
            runpy.run_path(script, run_name="__main__")
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
    """The traceback the interpreter prints, without this file's frames and runpy's (a SyntaxError in -c's
    code: no traceback, the error alone, as there)."""
    tb = err.__traceback__
    while tb is not None and tb.tb_frame.f_code.co_filename in (__file__, "<frozen runpy>"):
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
        sys.stdin = open(0, closefd=False)
        sys.stdout = open(1, "w", buffering=1 if unbuffered else -1, closefd=False)
        sys.stderr = open(2, "w", buffering=1, closefd=False, errors="backslashreplace")
        warnings.filters[:] = FRESH_FILTERS
        code = run(request["argv"])
        threading._shutdown()      # as the interpreter's exit: non-daemon threads joined, then atexit
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
        if code < 0:               # Ctrl-C: ended by SIGINT, as CPython ends then
            signal.signal(-code, signal.SIG_DFL)
            os.kill(os.getpid(), -code)
    finally:
        os._exit(code & 0xFF if code >= 0 else 1)


def serve() -> None:
    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            child(request)
        deadline = time.monotonic() + request["timeout"]
        while not (ended := os.waitpid(pid, os.WNOHANG))[0] and time.monotonic() < deadline:
            time.sleep(0.01)
        if not ended[0]:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        print(json.dumps({"code": os.waitstatus_to_exitcode(ended[1]) if ended[0] else None}), flush=True)


if __name__ == "__main__":
    serve()

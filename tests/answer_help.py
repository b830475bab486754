"""`python scripts/X.py --help` for each script named, each in a process forked from this one, which
imported the libraries they share once (tests/test_cli.py's test_every_script_answers_help): the child runs
the script as that command does (as __main__, its folder first on sys.path, the project's modules and its
sibling scripts imported afresh), its file descriptors 1 and 2 in files, its exit status the interpreter's
(a SystemExit message printed, atexit run, 120 s each). Writes {script: {code, stdout, stderr}} as JSON.
    python tests/answer_help.py SCRIPTS_FOLDER REPORT.json SCRIPT...
"""
import atexit, json, os, runpy, sys, time, traceback
import hydra, numpy, omegaconf, pandas, torch, yaml  # noqa: F401   imported once, before the forks
folder, report, names = sys.argv[1], sys.argv[2], sys.argv[3:]
here = os.path.dirname(os.path.abspath(__file__))
path = [p for p in sys.path if p not in ("", here)]   # this file's folder is not the script's


def status_of(script):
    sys.argv, sys.path[:] = [script, "--help"], [folder, *path]
    try:
        runpy.run_path(script, run_name="__main__")
        return 0
    except SystemExit as stop:
        if stop.code is None or isinstance(stop.code, int):   # beyond a C long: -1, as CPython exits
            return (stop.code or 0) & 0xFF if -2**63 <= (stop.code or 0) < 2**63 else 255
        print(stop.code, file=sys.stderr)
        return 1
    except BaseException:
        traceback.print_exc()
        return 1


said = {}
for name in names:
    out, err = report + "." + name + ".out", report + "." + name + ".err"
    pid = os.fork()
    if pid == 0:
        code = 1
        try:                                  # the child never returns into this loop
            with open(out, "w") as o, open(err, "w") as e:
                os.dup2(o.fileno(), 1)
                os.dup2(e.fileno(), 2)
            code = status_of(os.path.join(folder, name))
            atexit._run_exitfuncs()
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)
    deadline = time.monotonic() + 120
    while not (ended := os.waitpid(pid, os.WNOHANG))[0] and time.monotonic() < deadline:
        time.sleep(0.02)
    if not ended[0]:
        os.kill(pid, 9)
        os.waitpid(pid, 0)
    said[name] = {"code": os.waitstatus_to_exitcode(ended[1]) if ended[0] else "timed out after 120 s",
                  "stdout": open(out).read(), "stderr": open(err).read()}
with open(report, "w") as f:
    json.dump(said, f)

"""conftest.python_process (tests/preloaded.py): a command in a process forked from an interpreter that
imported torch once says and exits what the same command in a fresh interpreter does."""
import os
import subprocess
import sys

import pytest

from conftest import REPO, python_process

THREAD_THEN_ATEXIT = ("import atexit, threading, time\n"
                      "def late():\n    time.sleep(0.2); print('thread done', flush=True)\n"
                      "threading.Thread(target=late).start()\natexit.register(lambda: print('atexit'))\n")
COMMANDS = {
    "exit 3": ["-c", "import sys; print('out'); sys.exit(3)"],
    "exit with a message": ["-c", "import sys; sys.exit('bye')"],
    "exit beyond a C long": ["-c", "import sys; sys.exit(2**70)"],
    "uncaught exception": ["-c", "def f():\n    raise ValueError('x')\nf()"],
    "syntax error": ["-c", "print(1 +)"],
    "KeyboardInterrupt": ["-c", "raise KeyboardInterrupt"],
    "killed by SIGTERM": ["-c", "import os, signal; print('before', flush=True); os.kill(os.getpid(), signal.SIGTERM)"],
    "a thread joined, then atexit": ["-c", THREAD_THEN_ATEXIT],
    "warnings as a fresh interpreter shows them": ["-c", "import warnings; warnings.warn('shown'); "
                                                   "warnings.warn('hidden', DeprecationWarning)"],
    "argv, sys.path[0], stdin": ["-c", "import sys; print(sys.argv, repr(sys.path[0]), repr(sys.stdin.read()))", "a"],
    "a module as __main__": ["-m", "tool", "--size", "3"],
    "a module's usage error": ["-m", "tool", "--size", "x"],
    "a module's traceback": ["-m", "tool", "--size", "0"],
    "a module that is not there": ["-m", "no_such_tool"],
    "a script": ["tool.py", "--help"],
    "a script's traceback": ["tool.py", "--size", "0"],
}
TOOL = ("import argparse, sys\n"
        "parser = argparse.ArgumentParser(description='a tool')\nparser.add_argument('--size', type=int)\n"
        "size = parser.parse_args().size\n"
        "print(__name__, __spec__ and __spec__.name, sys.argv[0], sys.path[0], size)\n"
        "if size == 0:\n    raise RuntimeError('zero')\n")


@pytest.mark.parametrize("name", COMMANDS)
def test_a_command_says_and_exits_what_a_fresh_interpreter_does(name, tmp_path):
    argv = COMMANDS[name]
    (tmp_path / "tool.py").write_text(TOOL)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    real = subprocess.run([sys.executable, *argv], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120, stdin=subprocess.DEVNULL)
    forked = python_process(*argv, cwd=tmp_path, env=env, timeout=120)
    assert (forked.returncode, forked.stdout, forked.stderr) == (real.returncode, real.stdout, real.stderr)


def test_the_command_imports_the_project_from_its_folder_in_its_environment(tmp_path):
    """The server imported no module of the project: an edited copy is what the command runs."""
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "__init__.py").write_text("EDITED = True\n")
    code = ("import os, sys, bench; print(bench.EDITED, os.getcwd(), os.environ['SRD_TEST_ONLY_HERE'], "
            "'torch' in sys.modules, sys.path[1])")
    env = dict(os.environ, SRD_TEST_ONLY_HERE="1", PYTHONPATH="/nowhere", DRJIT_LIBLLVM_PATH="/x.so",  # what the
               TORCHINDUCTOR_CACHE_DIR=str(tmp_path))    # project and torch set in a test's process: read late
    done = python_process("-c", code, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", str(tmp_path), "1", "True", "/nowhere"]   # torch: preloaded


def test_a_command_past_its_timeout_is_killed_and_raises_as_subprocess_run_does():
    with pytest.raises(subprocess.TimeoutExpired):
        python_process("-c", "import time; time.sleep(30)", timeout=1)
    assert python_process("-c", "print('next')").stdout == "next\n"     # the server goes on


@pytest.mark.parametrize("variable", ["OMP_NUM_THREADS", "TORCHINDUCTOR_COMPILE_THREADS"])  # torch's, Inductor's
def test_an_environment_torch_reads_at_import_gets_an_interpreter_of_its_own(variable):
    done = python_process("-c", "import sys; print('torch' in sys.modules)", env=dict(os.environ, **{variable: "7"}))
    assert done.stdout == "False\n"


@pytest.mark.parametrize("draw", ["import random; print(random.random())",
                                  "import numpy; print(numpy.random.rand())"])
def test_each_command_draws_other_random_numbers_as_each_new_process_does(draw):
    assert python_process("-c", draw).stdout != python_process("-c", draw).stdout


def test_sys_path_takes_pythonpath_as_the_interpreter_does(tmp_path):
    """An empty entry is the folder and a relative one is made absolute; the site's folders follow."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(["", "rel", str(REPO)]))
    code = "import sys; print(sys.path)"
    real = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=60, stdin=subprocess.DEVNULL)
    assert python_process("-c", code, cwd=tmp_path, env=env).stdout == real.stdout

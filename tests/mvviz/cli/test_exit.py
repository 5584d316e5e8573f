"""``mvviz.cli.exit_now``, how the ``mvviz`` script ends: the exit code, the exit
functions run, buffered output flushed into a pipe, and a running non-daemon thread
waited for; and ``python -m mvviz.cli`` ends through it with the command's code."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO

PROBE = """
import atexit, sys, threading, time
from mvviz.cli import exit_now
atexit.register(lambda: print("exit function ran"))
sys.stdout.write("buffered " * 2000 + "\\n")  # not flushed: stdout is a pipe
if sys.argv[1] == "thread":
    threading.Thread(target=lambda: (time.sleep(0.5), print("thread finished"))).start()
exit_now(3)
"""


def _probe(mode: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", PROBE, mode], cwd=REPO, capture_output=True, text=True, timeout=60
    )


def test_exit_now_keeps_the_code_the_exit_functions_and_the_output():
    done = _probe("plain")
    assert done.returncode == 3, done.stderr
    assert done.stdout.count("buffered ") == 2000
    assert done.stdout.endswith("exit function ran\n")


@pytest.mark.slow
def test_exit_now_waits_for_a_running_thread():
    done = _probe("thread")
    assert done.returncode == 3, done.stderr
    lines = done.stdout.split("\n")
    assert "thread finished" in lines and lines.index("thread finished") < lines.index(
        "exit function ran"
    )


def test_the_module_entry_returns_the_commands_code(tmp_path):
    """An input error (no such scene) is exit code 2 and its one line, through entry()."""
    done = subprocess.run(
        [sys.executable, "-m", "mvviz.cli", "eval", str(tmp_path / "missing")],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 2, (done.stdout, done.stderr)
    assert "mvviz eval: error:" in done.stderr and "missing" in done.stderr

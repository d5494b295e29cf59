"""Ctrl-C while ``hybrid-pk`` is still starting (importing torch and every command takes
seconds on a loaded machine) is one line and exit 130, as an interrupt later in a
command is; before, a Python traceback of the import machinery.

Each child starts with SIGINT at its default, as a terminal's foreground command does:
a shell starts background jobs with SIGINT ignored (``pytest ... &``), the children
inherit that, and an ignored interrupt stays ignored (the last test)."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time

import pytest

from tests.helpers import default_sigint


@pytest.mark.skipif(shutil.which("hybrid-pk") is None, reason="hybrid-pk not installed")
@pytest.mark.parametrize("after_s", [0.3, 0.8])
def test_ctrl_c_while_starting_is_one_line(tmp_path, after_s):
    proc = subprocess.Popen(
        ["hybrid-pk", "demo", "--out", str(tmp_path / "demo"), "--n", "400", "--epochs", "1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
    )
    time.sleep(after_s)  # past the interpreter's own start, inside the imports
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("demo [")]
    assert len(lines) == 1, err
    assert "interrupted" in lines[0], err


def _python(code: str, argv0: str, start=default_sigint) -> subprocess.CompletedProcess:
    script = f"import sys\nsys.argv[0] = {argv0!r}\n{code}"
    return subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
        preexec_fn=start,
    )  # fmt: skip


def test_an_interrupt_an_importing_library_swallows_still_leaves_with_one_line():
    # before: the interrupt became a KeyboardInterrupt inside numpy's import, which a
    # library caught; numpy's lazy __getattr__ then recursed to a RecursionError (CI,
    # 1 run in 60 on loaded cores). Here the swallowing library is written out.
    code = (
        "import os, signal, time\n"
        "import hybrid_pk\n"
        "try:  # a library that catches everything while it imports\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    time.sleep(30)\n"
        "except BaseException:\n"
        "    pass\n"
        "print('went on')\n"
    )
    proc = _python(code, "/usr/bin/hybrid-pk")
    assert proc.returncode == 130, (proc.stdout, proc.stderr)
    assert proc.stdout == ""
    assert proc.stderr == "hybrid-pk: interrupted while starting\n"


def test_a_script_importing_the_library_keeps_its_own_interrupt():
    code = (
        "import signal\n"
        "import hybrid_pk\n"
        "print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)\n"
    )
    proc = _python(code, "my_script.py")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "True"


@pytest.mark.skipif(shutil.which("hybrid-pk") is None, reason="hybrid-pk not installed")
def test_ctrl_c_once_the_command_runs_is_the_commands_own_line(tmp_path):
    proc = subprocess.Popen(
        ["hybrid-pk", "demo", "--out", str(tmp_path / "demo"), "--n", "400", "--epochs", "1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
    )
    first = proc.stderr.readline()  # the first progress line: the command is running
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert first.startswith("demo ["), (first, err)
    assert proc.returncode == 130, (out, err)
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("demo [")]
    assert lines == ["hybrid-pk demo: interrupted"], err


def test_an_inherited_ignored_interrupt_stays_ignored():
    # a background job of a shell script (``hybrid-pk train ... &``): a Ctrl-C meant for
    # the script in the foreground must not stop it
    def ignored() -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    code = (
        "import signal\n"
        "import hybrid_pk\n"
        "from hybrid_pk.startup import release\n"
        "release()  # what the command line does once its commands are imported\n"
        "print(signal.getsignal(signal.SIGINT) == signal.SIG_IGN)\n"
    )
    proc = _python(code, "/usr/bin/hybrid-pk", start=ignored)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "True"

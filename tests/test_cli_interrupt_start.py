"""Ctrl-C while ``hybrid-pk`` is still starting (importing torch and every command takes
seconds on a loaded machine) is one line and exit 130, as an interrupt later in a
command is; before, a Python traceback of the import machinery."""

from __future__ import annotations

import shutil
import signal
import subprocess
import time

import pytest


@pytest.mark.skipif(shutil.which("hybrid-pk") is None, reason="hybrid-pk not installed")
@pytest.mark.parametrize("after_s", [0.3, 0.8])
def test_ctrl_c_while_starting_is_one_line(tmp_path, after_s):
    proc = subprocess.Popen(
        ["hybrid-pk", "demo", "--out", str(tmp_path / "demo"), "--n", "400", "--epochs", "1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(after_s)  # past the interpreter's own start, inside the imports
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("demo [")]
    assert len(lines) == 1, err
    assert "interrupted" in lines[0], err

"""The CLI's error policy: one line on stderr, never a traceback unless --debug."""

from __future__ import annotations

import pytest

import hybrid_pk.cli.evaluate_cmd as evaluate_cmd
from hybrid_pk.cli.main import main
from hybrid_pk.errors import HybridPKError


def _fail_with(exc: Exception):
    def run(args):
        raise exc

    return run


@pytest.mark.parametrize(
    ("exc", "code", "text"),
    [
        (HybridPKError("give --fit-frames"), 2, "hybrid-pk evaluate: error: give --fit-frames"),
        (RuntimeError("boom\nsecond line"), 1, "internal error: RuntimeError: boom second line"),
    ],
)
def test_an_error_is_one_line(monkeypatch, capsys, tmp_path, exc, code, text):
    monkeypatch.setattr(evaluate_cmd, "run", _fail_with(exc))
    assert main(["evaluate", "nominal:rx160", str(tmp_path / "d.csv")]) == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert text in err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("argv", "text"),
    [
        (["diagnose", "d.csv", "--robot", "rx160"], "hybrid-pk diagnose: error: the following"),
        (["simulate", "rx160", "--out", "x.csv", "--trajectory", "spiral"], "invalid choice"),
        (["import", "ipa"], "hybrid-pk import ipa: error:"),
        (["evaluate", "nominal:rx160", "d.csv", "--no-such-flag"], "unrecognized arguments"),
    ],
)
def test_a_flag_error_is_one_line_too(capsys, argv, text):
    # contract section 10: an error is one line on stderr and exit code 2; argparse's own
    # errors (a missing or bad flag) printed the whole usage block before that line
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert text in err
    assert "--help lists the options" in err


def test_debug_shows_the_traceback(monkeypatch, tmp_path):
    monkeypatch.setattr(evaluate_cmd, "run", _fail_with(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        main(["--debug", "evaluate", "nominal:rx160", str(tmp_path / "d.csv")])


@pytest.mark.parametrize("command", ["simulate", "plan"])
def test_the_robot_as_a_flag_too(tmp_path, capsys, command):
    """``simulate`` and ``plan`` name the robot first (the contract's ``ROBOT``); every
    other command takes ``--robot ROBOT``, and a user who types that here is understood;
    neither, or two different robots, is one line naming the fix."""
    out = str(tmp_path / "t.csv")
    assert main([command, "--robot", "rx160", "--n", "12", "--out", out, "--no-progress"]) == 0
    assert (tmp_path / "t.csv").exists()
    capsys.readouterr()
    assert main([command, "--n", "12", "--out", out]) == 2
    assert "the robot is missing: give ROBOT (or --robot ROBOT)" in capsys.readouterr().err
    assert main([command, "ur10", "--robot", "rx160", "--n", "12", "--out", out]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "two robots given" in err

"""The CLI's error policy: one line on stderr, never a traceback unless --debug; a
command loads only its own module, ``--help`` none (and no torch)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import hybrid_pk.cli
import hybrid_pk.cli.evaluate_cmd as evaluate_cmd
from hybrid_pk.cli.main import COMMANDS, main
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


def test_import_errors_name_the_format(tmp_path, capsys):
    """A runtime error of ``import ipa`` is prefixed as argparse prefixes its usage
    errors, ``hybrid-pk import ipa:`` (was ``hybrid-pk import:``)."""
    assert main(["import", "ipa", str(tmp_path / "none.csv"), "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.startswith("hybrid-pk import ipa: error: ")


def _modules_after(argv: list[str]) -> tuple[str, set[str]]:
    """``hybrid-pk ARGV`` in a fresh interpreter: its output and the modules it loaded."""
    code = (
        "import sys\nfrom hybrid_pk.cli.main import main\n"
        f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
        "print('MODULES', *sorted(sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    text, _, modules = out.stdout.rpartition("MODULES ")
    return text, set(modules.split())


def test_help_lists_every_command_and_loads_none():
    text, loaded = _modules_after(["--help"])
    for name, (_, line) in COMMANDS.items():
        assert name in text
        assert line.split()[0] in text
    assert "torch" not in loaded
    assert not {m for m in loaded if m.endswith("_cmd")}


def test_a_command_loads_only_its_own_module():
    _, loaded = _modules_after(["simulate", "--help"])
    assert {m for m in loaded if m.endswith("_cmd")} == {"hybrid_pk.cli.simulate_cmd"}


def test_every_command_module_is_listed():
    folder = Path(hybrid_pk.cli.__file__).parent
    modules = {f"hybrid_pk.cli.{f.stem}" for f in folder.glob("*_cmd.py")}
    assert modules == {path for path, _ in COMMANDS.values()}


def test_diagnose_and_calibrate_do_not_load_scipy_stats(tmp_path):
    """Their tests and thresholds use hybrid_pk.distributions (scipy.special): importing
    scipy.stats cost every such command ~0.3-0.7 s (tests/test_distributions.py checks
    the numbers against scipy.stats)."""
    data = tmp_path / "d.csv"
    argv = ["simulate", "rx160", "--n", "300", "--effects", "joint_offset:joint_2=0.001"]
    assert main([*argv, "--seed", "3", "--out", str(data), "--no-progress"]) == 0
    out, robot = tmp_path / "diag.json", ["--robot", "rx160"]
    _, loaded = _modules_after(["diagnose", str(data), *robot, "--json", str(out), "--no-progress"])
    assert out.exists()
    assert "hybrid_pk.calibration.diagnosis.power" in loaded
    assert "scipy.stats" not in loaded
    model = tmp_path / "m.pt"
    argv = ["calibrate", str(data), *robot, "--robust", "huber", "--out", str(model)]
    _, loaded = _modules_after([*argv, "--no-urdf", "--no-progress"])
    assert model.exists()
    assert "hybrid_pk.calibration.robust" in loaded
    assert "scipy.stats" not in loaded

"""Flags that contradict each other, or a value no run can use, are refused before any
work (one line, exit code 2, nothing written) instead of being silently ignored or
failing after minutes; a plan too small for calibrate says so."""

from __future__ import annotations

import pytest

from hybrid_pk.cli.main import main


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    folder = tmp_path_factory.mktemp("flags")
    table = folder / "a.csv"
    assert main(["simulate", "rx160", "--n", "30", "--out", str(table), "--no-progress"]) == 0
    model = folder / "m.pt"
    calibrate = ["calibrate", str(table), "--robot", "rx160", "--effects", "none"]
    assert main([*calibrate, "--out", str(model), "--no-urdf", "--no-progress"]) == 0
    return table, model


def _refused(args: list[str], capsys) -> str:
    capsys.readouterr()
    code = None
    try:
        code = main(args)
    except SystemExit as exc:  # argparse's own refusal
        code = exc.code
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def test_contradicting_flags_are_refused_before_any_work(campaign, tmp_path, capsys):
    table, model = campaign
    out = tmp_path / "z.csv"
    err = _refused(
        ["simulate", "rx160", "--poses", str(table), "--trajectory", "zigzag", "--out", str(out)],
        capsys,
    )
    assert "--trajectory zigzag: give one of them" in err
    err = _refused(
        ["export", str(model), "--format", "dh", "--ur-root", "base_link", "--out",
         str(tmp_path / "e.yaml")],
        capsys,
    )  # fmt: skip
    assert "--ur-root is for --format ur-calibration, not dh" in err
    err = _refused(
        ["diagnose", str(table), "--robot", "rx160", "--candidates", "", "--json",
         str(tmp_path / "d.json")],
        capsys,
    )  # fmt: skip
    assert "--candidates: no effect given" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_refused_demo_leaves_no_folder(tmp_path, capsys):
    out = tmp_path / "demo"
    err = _refused(["demo", "--epochs", "0", "--out", str(out)], capsys)
    assert "--epochs: expected a whole number >= 1, got '0'" in err
    assert not out.exists()
    err = _refused(["demo", "--n", "-1", "--noise-mm", "-0.1", "--out", str(out)], capsys)
    assert "argument --n: expected a whole number >= 1, got '-1'" in err
    err = _refused(["demo", "--noise-mm", "nan", "--out", str(out)], capsys)
    assert "argument --noise-mm: expected a finite number >= 0, got 'nan'" in err
    err = _refused(["demo", "--robot", "no_such_robot", "--out", str(out), "--no-progress"], capsys)
    assert "unknown robot 'no_such_robot'" in err
    assert not out.exists()  # the folder is made once the campaign is drawn


def test_a_plan_with_fewer_poses_than_parameters_says_calibrate_needs_more(tmp_path, capsys):
    out = tmp_path / "p.csv"
    args = ["plan", "rx160", "--n", "3", "--candidates", "40", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "warning: 3 poses for 12 parameters: calibrate needs at least one row per" in printed
    assert main([*args[:3], "12", *args[4:]]) == 0
    assert "warning: 12 poses" not in capsys.readouterr().out


def test_a_folder_given_as_a_file_is_named_as_one(tmp_path, capsys):
    err = _refused(["evaluate", "nominal:rx160", str(tmp_path)], capsys)
    assert err.endswith(f"{tmp_path}: is a folder, not a file")
    err = _refused(["import", "dh", str(tmp_path), "--out", str(tmp_path / "r.urdf")], capsys)
    assert err.endswith(f"{tmp_path}: is a folder, not a DH table file")


def test_a_temperature_below_absolute_zero_is_not_simulated(tmp_path, capsys):
    out = tmp_path / "cold.csv"
    args = ["simulate", "rx160", "--n", "5", "--temperature-range", "-400", "-300"]
    err = _refused([*args, "--out", str(out)], capsys)
    assert "temperature range must be -273.15 <= LO <= HI" in err
    assert not out.exists()

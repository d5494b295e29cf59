"""A model that misses the rows by more than small corrections make (rows of another
robot with the same joint names, as a UR5 table and a UR10 model) is named by train
and evaluate, which no column check can do (a robotics user's tour, 2026-12-05)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.io.model_file import save_model
from hybrid_pk.simulate import simulate_campaign

REPO = Path(__file__).resolve().parents[1]


def _scaled(match: re.Match) -> str:
    return match.group(1) + " ".join(f"{0.6 * float(v):.6g}" for v in match.group(2).split())


@pytest.fixture(scope="module")
def tables(ur10, tmp_path_factory):
    """A UR10 model file, a table of a 60 % UR10 (the UR10's joint names) and one of
    the UR10 itself, both measured at the flange in the base frame."""
    folder = tmp_path_factory.mktemp("gross")
    text = (REPO / "urdf" / "ur10.urdf").read_text(encoding="utf-8")
    small = folder / "small.urdf"
    small.write_text(re.sub(r'(<origin[^>]*?xyz=")([^"]*)', _scaled, text), encoding="utf-8")
    out = {}
    for name, robot in (("small", Robot.from_urdf(str(small))), ("ur10", ur10)):
        data, _ = simulate_campaign(robot, 60, "none", noise_mm=0.0, known_frames=True, seed=5)
        out[name] = write_table(folder / f"{name}.csv", data)
    return save_model(folder / "ur10.pt", ExtendedModel(ur10)), out


def test_evaluate_names_rows_of_another_robot(tables, capsys):
    model, table = tables
    assert main(["evaluate", str(model), str(table["small"]), "--fit-frames"]) == 0
    out = capsys.readouterr().out
    assert "more than small corrections make (20 mm): the rows are not this robot's" in out
    assert main(["evaluate", str(model), str(table["ur10"])]) == 0
    assert "misses these rows" not in capsys.readouterr().out


def test_train_names_a_base_model_far_off_the_rows(tables, tmp_path, capsys):
    # before: 'trained ...' with a base model 300 mm off, no word of the mismatch
    model, table = tables
    args = ["train", str(table["small"]), "--model", str(model), "--out", str(tmp_path / "h")]
    nets = ["--preset", "joints", "--position-net", "mlp:8x1", "--orientation-net", "none"]
    assert main([*args, *nets, "--epochs", "1", "--no-blocked"]) == 0
    out = capsys.readouterr().out
    assert "warning: the base model misses these rows by " in out
    assert "the networks would learn that mismatch" in out


def test_evaluate_says_when_data_is_the_file_the_model_was_fitted_on(tables, tmp_path, capsys):
    # before: the errors on the calibration file itself were printed as any others
    _, table = tables
    model = tmp_path / "fitted.pt"
    assert main(["calibrate", str(table["ur10"]), "--robot", "ur10", "--effects", "none",
                 "--no-urdf", "--out", str(model)]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["evaluate", str(model), str(table["ur10"])]) == 0
    out = capsys.readouterr().out
    assert f"note: {model} was calibrated on {table['ur10']}: these errors are on its " in out
    assert main(["evaluate", str(model), str(table["small"]), "--fit-frames"]) == 0
    assert "fitting rows" not in capsys.readouterr().out

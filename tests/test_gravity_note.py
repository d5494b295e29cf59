"""The mounting a calibration states against the one its fitted base shows: a robot on a
tilted base measured by a levelled total station but diagnosed with the default upright
gravity (or a gravity of the wrong sign) gets a note naming the angle and
``--gravity level-tracker``; a re-stationing with ``level-tracker`` prints the tilt it
found (tour 5: a construction robot re-stationed on a tilted set-up)."""

from __future__ import annotations

import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.cli.common import TILT_NOTE_DEG, gravity_note, mounting_lines
from hybrid_pk.effects import ExtendedModel, Gravity

pytestmark = pytest.mark.usefixtures("one_thread")


def _robot():
    robot = hpk.Robot.from_urdf("column_arm", end_link="tool0")
    robot.requires_grad_(False)
    return robot


def _base(tilt_deg: float) -> torch.Tensor:
    """The robot's root in the measurement frame, turned ``tilt_deg`` about x."""
    a = math.radians(tilt_deg)
    T = torch.eye(4, dtype=torch.float64)
    T[1:3, 1:3] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    T[:3, 3] = torch.tensor([3.0, 2.0, 0.5], dtype=torch.float64)
    return T


def _stated(tilt_deg: float) -> Gravity:
    """Gravity in the root frame of a robot whose base is ``_base(tilt_deg)``, the
    instrument levelled."""
    down = _base(tilt_deg)[:3, :3].T @ torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64)
    return Gravity(tuple(down.tolist()))


def _model(tilt_deg: float, gravity: Gravity | None = None, loaded: bool = True):
    robot = _robot()
    label = "joint_compliance:dsr_joint2" if loaded else "joint_offset:dsr_joint3"
    effects = [hpk.make_effect(robot, label, 1e-4 if loaded else 1e-3)]
    kw = {} if gravity is None else {"gravity": gravity}
    return ExtendedModel(robot, effects, base=_base(tilt_deg), **kw)


def test_default_gravity_on_a_tilted_base_is_noted():
    note = gravity_note(_model(8.0))
    assert note is not None
    assert "8.0 deg from the measurement frame's vertical" in note, note
    assert "upright, the default" in note, note
    assert "--gravity level-tracker" in note, note
    assert "joint_compliance:dsr_joint2" in note, note
    assert note in mounting_lines(_model(8.0))


def test_a_gravity_of_the_wrong_sign_is_noted():
    note = gravity_note(_model(0.0, Gravity((0.0, 0.0, 9.81))))
    assert note is not None
    assert "180.0 deg" in note, note
    assert "(--gravity)" in note, note


@pytest.mark.parametrize(
    "model",
    [
        pytest.param(lambda: _model(0.5 * TILT_NOTE_DEG), id="within the tilt a fit resolves"),
        pytest.param(lambda: _model(8.0, Gravity.level_tracker()), id="levelled"),
        pytest.param(lambda: _model(8.0, loaded=False), id="no gravity effect"),
        pytest.param(lambda: _model(8.0, _stated(8.0)), id="stated as the base shows"),
    ],
)
def test_no_note_where_the_mounting_agrees_or_does_not_matter(model):
    m = model()
    assert gravity_note(m) is None
    assert not any(line.startswith("note:") for line in mounting_lines(m))


def _campaigns(tmp_path):
    """An upright calibration campaign and 40 rows of the robot on an 8° tilted base."""
    from hybrid_pk.data import write_table
    from hybrid_pk.simulate import simulate_campaign
    from hybrid_pk.simulate.mounting import parse_mount

    robot = _robot()
    soft = [hpk.make_effect(robot, "joint_compliance:dsr_joint2", 5e-5)]
    kw = {"noise_mm": 0.1, "position_only": True, "temperature_range": None}
    upright, truth = simulate_campaign(robot, 120, soft, mount=parse_mount("floor"), seed=1, **kw)
    tool = torch.tensor(truth["tool_frame"], dtype=torch.float64)
    tilted, _ = simulate_campaign(
        robot, 40, soft, mount=parse_mount("tilt:8"), seed=2, tool=tool, **kw
    )
    return write_table(tmp_path / "cal.csv", upright), write_table(tmp_path / "st.csv", tilted)


def _calibrated(tmp_path, cal, gravity: list[str]):
    from hybrid_pk.cli.main import main

    model = tmp_path / f"m{len(gravity)}.pt"
    argv = ["calibrate", str(cal), "--robot", "column_arm", "--end-link", "tool0",
            "--effects", "joint_compliance:dsr_joint2", "--out", str(model), "--no-urdf",
            *gravity]  # fmt: skip
    assert main(argv) == 0
    return model


def test_the_re_stationing_prints_the_tilt_it_found(tmp_path, capsys):
    from hybrid_pk.cli.main import main

    cal, moved = _campaigns(tmp_path)
    model = _calibrated(tmp_path, cal, ["--gravity", "level-tracker"])
    capsys.readouterr()
    argv = ["calibrate", str(moved), "--model", str(model), "--refit", "base",
            "--out", str(tmp_path / "r.pt"), "--no-urdf"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "root z axis 8.0 deg from upright (level-tracker)" in out, out
    assert "note:" not in out, out


def test_evaluate_fit_frames_says_what_the_re_fit_says(tmp_path, capsys):
    """``evaluate --fit-frames`` on the moved set-up, the re-stationing judged in one
    step: the tilt found with ``level-tracker``, the note with a fixed mounting."""
    from hybrid_pk.cli.main import main

    cal, moved = _campaigns(tmp_path)
    out = {}
    for gravity in ([], ["--gravity", "level-tracker"]):
        model = _calibrated(tmp_path, cal, gravity)
        capsys.readouterr()
        argv = ["evaluate", str(model), str(moved), "--fit-frames", "--json",
                str(tmp_path / "e.json")]  # fmt: skip
        assert main(argv) == 0
        out[bool(gravity)] = capsys.readouterr().out
    assert "note: the frames fitted to DATA tilt the robot by 8.0 deg" in out[False], out
    assert "--gravity level-tracker" in out[False], out
    assert "root z axis 8.0 deg from upright (level-tracker)" in out[True], out
    assert "note:" not in out[True], out

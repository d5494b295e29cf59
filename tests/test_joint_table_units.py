"""A joint table (a robot program for `compensate`, poses for `simulate --poses`) in
degrees, or a prismatic column in mm, is named as such, as in a pose table (contract
section 1); before, the first row was only 'outside the joint limits'."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.data.joint_table import read_joint_table
from hybrid_pk.errors import DataError

pytestmark = pytest.mark.usefixtures("one_thread")


def _program(tmp_path, robot: Robot, scale: float):
    q = robot.sample_q(20).numpy() * scale
    frame = pd.DataFrame(q, columns=robot.joint_names)
    frame.insert(0, "line", np.arange(10, 30))
    path = tmp_path / "program.csv"
    frame.to_csv(path, index=False)
    return path


def test_program_in_degrees(tmp_path, capsys):
    robot = Robot.from_urdf("rx160")
    path = _program(tmp_path, robot, 180 / math.pi)
    with pytest.raises(
        DataError, match=r"program\.csv, row \d+, column 'joint_1': looks like degrees"
    ):
        read_joint_table(path, robot)
    argv = ["compensate", "nominal:rx160", str(path), "--out", str(tmp_path / "c.csv")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "looks like degrees" in err
    assert "outside the joint limits" not in err
    assert read_joint_table(_program(tmp_path, robot, 1.0), robot)[0].shape == (20, 6)


def test_prismatic_program_in_mm(tmp_path):
    robot = Robot.from_urdf("column_arm", end_link="tool0")
    q = robot.sample_q(20).numpy()
    j = robot.joint_types.index("prismatic")
    q[:, j] *= 1000
    path = tmp_path / "poses.csv"
    pd.DataFrame(q, columns=robot.joint_names).to_csv(path, index=False)
    with pytest.raises(DataError, match=rf"column '{robot.joint_names[j]}': looks like mm"):
        read_joint_table(path, robot)


def test_compensate_reads_and_writes_a_program_in_degrees(tmp_path, capsys):
    """`compensate --angle-unit deg`: a controller's program in degrees is corrected as
    the same program in radians is, and written back in degrees, its other columns kept
    (before: no such flag; the program had to be converted both ways by hand)."""
    robot = Robot.from_urdf("rx160")
    model = tmp_path / "m.pt"
    effects = "joint_offset:joint_2=8e-4; joint_offset:joint_3=-5e-4"
    argv = ["simulate", "rx160", "--n", "30", "--noise-mm", "0.01", "--seed", "3"]
    assert main([*argv, "--effects", effects, "--out", str(tmp_path / "c.csv")]) == 0
    argv = ["calibrate", str(tmp_path / "c.csv"), "--robot", "rx160", "--no-urdf"]
    assert (
        main([*argv, "--effects", "joint_offset:joint_2,joint_offset:joint_3", "--out", str(model)])
        == 0
    )
    rad = _program(tmp_path, robot, 1.0)
    deg = tmp_path / "program_deg.csv"
    frame = pd.read_csv(rad)
    frame[robot.joint_names] = np.degrees(frame[robot.joint_names])
    frame.to_csv(deg, index=False)
    outs = {}
    for unit, path in (("rad", rad), ("deg", deg)):
        outs[unit] = tmp_path / f"out_{unit}.csv"
        argv = ["compensate", str(model), str(path), "--out", str(outs[unit]), "--no-progress"]
        assert main([*argv, "--angle-unit", unit]) == 0
    capsys.readouterr()
    a, b = pd.read_csv(outs["deg"]), pd.read_csv(outs["rad"])
    assert (
        np.abs(np.radians(a[robot.joint_names].values) - b[robot.joint_names].values).max() < 1e-12
    )
    assert np.abs(a[robot.joint_names].values - frame[robot.joint_names].values).max() > 1e-3
    assert list(a["line"]) == list(range(10, 30))
    assert (a["status"] == "ok").all()


def test_a_radian_program_read_as_degrees_is_a_warning(tmp_path, capsys):
    """`compensate --angle-unit deg` on a program in radians: every value lies within 2 pi,
    a program moving each joint by less than 6.3 deg; a warning line names the largest
    value and its column (before: read silently as a tiny program). A program in degrees
    gets no such line."""
    from hybrid_pk.pipelines.compensation import read_program

    robot = Robot.from_urdf("rx160")
    rad = _program(tmp_path, robot, 1.0)
    notes = read_program(str(rad), robot, "deg").notes
    warned = [n for n in notes if "look like radians" in n]
    assert len(warned) == 1
    assert warned[0].startswith(f"warning: {rad}: ")
    q = pd.read_csv(rad)[robot.joint_names].abs()
    top = q.max().max()
    assert f"largest {top:.4g}, column {q.max().idxmax()}" in warned[0]
    assert not [n for n in read_program(str(rad), robot, "rad").notes if "radians" in n]
    deg = tmp_path / "deg.csv"
    pd.DataFrame(np.degrees(q.values), columns=robot.joint_names).to_csv(deg, index=False)
    assert not [n for n in read_program(str(deg), robot, "deg").notes if "radians" in n]
    argv = ["compensate", "nominal:rx160", str(rad), "--out", str(tmp_path / "c.csv")]
    assert main([*argv, "--angle-unit", "deg", "--no-progress"]) == 0
    assert "these look like radians" in capsys.readouterr().out

"""A datasheet's DH table in millimetres and degrees reads as it is printed
(``--length-unit mm --angle-unit deg``, ``units=``, a YAML file's ``units``): the same
robot as the table converted exactly to m and rad. Before, every cell had to be
converted by hand, and pi/2 written as 1.5708 moved a KR6's flange by up to 6 um."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.errors import DataError

pytestmark = pytest.mark.usefixtures("one_thread")

# KUKA KR 6 R900 as its datasheet prints it: a, alpha, d, theta [mm, deg], the axis
# ranges [deg] and link masses [kg] with centres of mass [mm].
SHEET = [
    (25, -90, 400, 0, (-170, 170), 12.0, (0, 0, 100)),
    (455, 0, 0, -90, (-190, 45), 9.0, (-230, 0, 50)),
    (35, -90, 0, 0, (-120, 156), 6.0, (0, -20, 0)),
    (0, 90, 420, 0, (-185, 185), 3.0, (0, 80, 0)),
    (0, -90, 0, 0, (-120, 120), 1.5, (0, 0, 0)),
    (0, 0, 80, 0, (-350, 350), 0.3, (0, 0, -10)),
]


def _rows(mm: float, deg: float) -> list[dict]:
    """The table with lengths times ``mm`` and angles times ``deg``."""
    rows = []
    for i, (a, alpha, d, theta, (lo, hi), m, c) in enumerate(SHEET, start=1):
        rows.append(
            {"name": f"a{i}", "a": a * mm, "alpha": alpha * deg, "d": d * mm}
            | {"theta": theta * deg, "type": "revolute", "lower": lo * deg, "upper": hi * deg}
            | {"mass": m, "com_x": c[0] * mm, "com_y": c[1] * mm, "com_z": c[2] * mm}
        )
    return rows


SI = _rows(1e-3, math.pi / 180)  # the exact conversion


def _same_robot(a: Robot, b: Robot) -> None:
    q = b.sample_q(200, torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert float((a.fk(q) - b.fk(q)).abs().max()) < 1e-12
        assert float((a.gravity_torques(q) - b.gravity_torques(q)).abs().max()) < 1e-9
    assert torch.allclose(a.lower, b.lower, atol=1e-12)
    assert torch.allclose(a.upper, b.upper, atol=1e-12)


def test_datasheet_in_mm_and_degrees_on_the_command_line(tmp_path, capsys):
    path = tmp_path / "kr6.csv"
    rows = _rows(1, 1)
    path.write_text(
        ",".join(rows[0]) + "\n" + "".join(",".join(map(str, r.values())) + "\n" for r in rows)
    )
    out = tmp_path / "kr6.urdf"
    argv = ["import", "dh", str(path), "--convention", "dh", "--out", str(out)]
    assert main(argv) == 2  # read as m and rad, it says which flag reads it as printed
    err = capsys.readouterr().err
    assert "row 1, column 'a': 25 m" in err
    assert "--length-unit mm" in err
    assert main([*argv, "--length-unit", "mm"]) == 2
    err = capsys.readouterr().err
    assert "row 1, column 'alpha': -90 is not an angle in radians" in err
    assert "--angle-unit deg" in err
    assert main([*argv, "--length-unit", "mm", "--angle-unit", "deg"]) == 0
    _same_robot(Robot.from_urdf(out), Robot.from_dh(SI, "dh"))
    # the table rounded by hand (pi/2 as 1.5708) is what this replaces: 6.4 um off
    rounded = [r | {k: round(r[k], 4) for k in ("alpha", "theta")} for r in SI]
    q = Robot.from_urdf(out).sample_q(200, torch.Generator().manual_seed(0))
    with torch.no_grad():
        gap = Robot.from_dh(rounded, "dh").fk(q) - Robot.from_urdf(out).fk(q)
    assert float(gap[:, :3, 3].norm(dim=-1).max()) > 5e-6  # beyond a tracker's noise


def test_yaml_states_its_units_with_frames_and_inertia(tmp_path):
    """A YAML table's ``units``: base / flange xyz in mm, rpy in degrees, inertias in
    kg mm^2 (times 1e-6 into kg m^2)."""
    rows = _rows(1, 1)
    rows[1] |= {"ixx": 2.0e4, "iyy": 3.0e4, "izz": 4.0e4}
    doc = {"convention": "dh", "units": {"length": "mm", "angle": "deg"}, "joints": rows}
    doc["base"] = {"xyz": [100, 0, 250], "rpy": [0, 0, 90]}
    doc["flange"] = {"xyz": [0, 0, 15], "rpy": [180, 0, 0]}
    path = tmp_path / "kr6.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    si = [dict(r) for r in SI]
    si[1] |= {"ixx": 0.02, "iyy": 0.03, "izz": 0.04}
    want = Robot.from_dh(
        si,
        "dh",
        base={"xyz": [0.1, 0, 0.25], "rpy": [0, 0, math.pi / 2]},
        flange={"xyz": [0, 0, 0.015], "rpy": [math.pi, 0, 0]},
    )
    _same_robot(Robot.from_dh(path), want)
    inertia = Robot.from_dh(path).spec.segment_inertia[2]
    assert np.abs(inertia - want.spec.segment_inertia[2]).max() < 1e-15
    assert np.allclose(np.linalg.eigvalsh(inertia), [0.02, 0.03, 0.04], atol=1e-15)


def test_python_units_and_bad_units():
    _same_robot(
        Robot.from_dh(_rows(1, math.pi / 180), "dh", units={"length": "mm"}),
        Robot.from_dh(SI, "dh"),
    )
    with pytest.raises(DataError, match=r"column 'units': length unit 'mmm': one of m, mm"):
        Robot.from_dh(SI, "dh", units={"length": "mm" + "m"})
    with pytest.raises(DataError, match=r"units .* write"):
        Robot.from_dh(SI, "dh", units={"lenght": "mm"})
    rows = _rows(1, math.pi / 180)
    rows[0]["d"] = 400e3  # micrometres in a mm table
    with pytest.raises(DataError, match=r"row 1, column 'd': 400000 mm is 400 m: longer"):
        Robot.from_dh(rows, "dh", units={"length": "mm"})


def test_file_and_given_units_must_agree(tmp_path):
    path = tmp_path / "t.yaml"
    doc = {"convention": "dh", "units": {"length": "mm"}, "joints": _rows(1, math.pi / 180)}
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    with pytest.raises(DataError, match="states length unit 'mm', but 'cm' was given"):
        Robot.from_dh(path, units={"length": "cm"})
    _same_robot(Robot.from_dh(path, units={"length": "mm"}), Robot.from_dh(SI, "dh"))


def test_limits_in_the_wrong_order_are_named_as_written():
    """Before: 'lower limit 0.785398 is not below upper limit -3.31613' for a table read
    in degrees (45, -190): the converted figures, not the cells."""
    rows = _rows(1, 1)
    rows[1]["lower"], rows[1]["upper"] = 45, -190
    with pytest.raises(DataError, match="row 2, column 'upper': lower limit 45 deg is not below"):
        Robot.from_dh(rows, "dh", units={"length": "mm", "angle": "deg"})

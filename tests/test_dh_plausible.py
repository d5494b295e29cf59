"""A DH table's lengths in millimetres (or cm, inches) are refused with file, row and
column and the figure in metres; real robots' tables, and the tables exported from the
shipped robots, pass.

The real tables are the makers' published figures (lengths [m], angles [rad]), as
``(a, alpha, d, theta)`` per row, standard DH unless marked ``mdh`` (Craig's
``alpha_{i-1}, a_{i-1}, d_i, theta_i``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import DataError
from hybrid_pk.io.dh_export import model_dh_table, write_dh_yaml
from hybrid_pk.robot.dh_table import read_dh_table

pytestmark = pytest.mark.usefixtures("one_thread")

H = math.pi / 2
UR_ALPHA = (H, 0, 0, H, -H, 0)


def _ur(d1, a2, a3, d4, d5, d6):
    """Universal Robots' table: the same structure for every size."""
    a = (0, a2, a3, 0, 0, 0)
    d = (d1, 0, 0, d4, d5, d6)
    return [(a[i], UR_ALPHA[i], d[i], 0) for i in range(6)]


def _six_axis(d1, a1, a2, a3, d4, d6, alpha=(-H, 0, -H, H, -H, 0)):
    """An industrial 6-axis arm with a spherical wrist (KUKA, ABB, Fanuc, Staubli)."""
    return [
        (a1, alpha[0], d1, 0),
        (a2, alpha[1], 0, -H),
        (a3, alpha[2], 0, 0),
        (0, alpha[3], d4, 0),
        (0, alpha[4], 0, 0),
        (0, alpha[5], d6, 0),
    ]


REAL = {
    "ur3": ("dh", _ur(0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819)),
    "ur5": ("dh", _ur(0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823)),
    "ur10": ("dh", _ur(0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922)),
    "ur3e": ("dh", _ur(0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921)),
    "ur5e": ("dh", _ur(0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996)),
    "ur10e": ("dh", _ur(0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655)),
    "ur16e": ("dh", _ur(0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655)),
    "panda": (
        "mdh",
        [
            (0, 0, 0.333, 0),
            (0, -H, 0, 0),
            (0, H, 0.316, 0),
            (0.0825, H, 0, 0),
            (-0.0825, -H, 0.384, 0),
            (0, H, 0, 0),
            (0.088, H, 0.107, 0),  # the flange distance folded into the last row
        ],
    ),
    "kuka_kr6_r900": ("dh", _six_axis(0.4, 0.025, 0.455, 0.035, 0.42, 0.08)),
    "abb_irb120": ("dh", _six_axis(0.29, 0.0, 0.27, 0.07, 0.302, 0.072)),
    "fanuc_lr_mate_200id": ("dh", _six_axis(0.33, 0.05, 0.33, 0.035, 0.335, 0.08)),
    "staubli_tx2_60": ("dh", _six_axis(0.375, 0.0, 0.29, 0.0, 0.31, 0.07)),
    "staubli_rx160": ("dh", _six_axis(0.55, 0.15, 0.825, 0.0, 0.625, 0.11)),
    "kuka_iiwa14": (
        "dh",
        [
            *((0, -H, 0.36, 0), (0, H, 0, 0), (0, H, 0.42, 0), (0, -H, 0, 0)),
            *((0, -H, 0.4, 0), (0, H, 0, 0), (0, 0, 0.126, 0)),
        ],
    ),
    "kinova_gen3": (
        "dh",
        [
            *((0, H, -0.2848, 0), (0, H, -0.0118, math.pi), (0, H, -0.4208, math.pi)),
            *((0, H, -0.0128, math.pi), (0, H, -0.3143, math.pi), (0, H, 0, math.pi)),
            (0, math.pi, -0.1674, math.pi),
        ],
    ),
    # At the reach of the longest industrial arms (4.7 m): two 2 m links.
    "long_reach": ("dh", _six_axis(1.05, 0.5, 2.0, 0.25, 2.0, 0.3)),
}


def _rows(name: str, scale: float = 1.0) -> list[dict]:
    values = REAL[name][1]
    rows = []
    for i, (a, alpha, d, theta) in enumerate(values, start=1):
        rows.append(
            {"name": f"joint_{i}", "a": a * scale, "alpha": alpha, "d": d * scale}
            | {"theta": theta, "type": "revolute", "lower": -6.28, "upper": 6.28}
        )
    return rows


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_tables_pass(name):
    """Every real robot's published table reads as it is."""
    convention = REAL[name][0]
    robot = Robot.from_dh(_rows(name), convention)
    assert robot.dof == len(REAL[name][1])


@pytest.mark.parametrize("robot", ["rx160", "ur10"])  # column_arm's mimic joints fit no table
@pytest.mark.parametrize("convention", ["dh", "mdh"])
def test_shipped_robots_exported_tables_read_back(tmp_path, robot, convention):
    """The DH / MDH tables exported from the shipped robots (masses included) read back."""
    model = ExtendedModel(Robot.from_urdf(robot))
    path = write_dh_yaml(model_dh_table(model, convention), tmp_path / "t.yaml")
    assert read_dh_table(path).n == model.robot.dof


@pytest.mark.parametrize("name", sorted(REAL))
@pytest.mark.parametrize(("unit", "scale"), [("mm", 1000.0), ("cm", 100.0)])
def test_real_tables_in_mm_or_cm_are_refused(name, unit, scale):
    """The same tables in millimetres or centimetres: refused at their first length
    beyond 5 m, with its row and column and the figure in metres."""
    rows = _rows(name, scale)
    first = next((i, k) for i, r in enumerate(rows, start=1) for k in ("a", "d") if abs(r[k]) > 5.0)
    with pytest.raises(DataError, match=r"write .* for .* mm") as caught:
        Robot.from_dh(rows, REAL[name][0])
    assert (caught.value.row, caught.value.column) == first, unit


def test_one_length_in_mm_names_its_cell(tmp_path, capsys):
    """UR5's table in metres with d1 left in mm (89.159): before, an 89 m link was read
    without a word; now exit 2, one line naming file, row 1, column 'd' and 0.089159."""
    rows = _rows("ur5")
    rows[0]["d"] = 89.159
    path = tmp_path / "ur5.csv"
    path.write_text(
        "name,a,alpha,d,theta,type,lower,upper\n"
        + "".join(",".join(str(r[k]) for k in r) + "\n" for r in rows),
        encoding="utf-8",
    )
    out = tmp_path / "ur5.urdf"
    assert main(["import", "dh", str(path), "--convention", "dh", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"{path}, row 1, column 'd': 89.159 m" in err
    assert "write 0.089159 for 89.159 mm" in err
    assert not out.exists()


def test_centre_of_mass_and_flange_in_mm(tmp_path):
    """A centre of mass or a YAML flange offset in mm is refused the same way."""
    rows = _rows("kuka_kr6_r900")
    rows[1] |= {"mass": 12.0, "com_x": 227.5, "com_y": 0.0, "com_z": 0.0}
    with pytest.raises(DataError, match=r"row 2, column 'com_x': 227\.5 m"):
        Robot.from_dh(rows, "dh")
    doc = {"convention": "dh", "flange": {"xyz": [0, 0, 80], "rpy": [0, 0, 0]}}
    path = tmp_path / "kr6.yaml"
    path.write_text(yaml.safe_dump(doc | {"joints": _rows("kuka_kr6_r900")}), encoding="utf-8")
    with pytest.raises(DataError, match=r"column 'flange': z: 80 m .* write 0\.08 for 80 mm"):
        Robot.from_dh(path)
    base = np.eye(4)
    base[0, 3] = 1500.0  # a pedestal offset in mm
    with pytest.raises(DataError, match="column 'base': x: 1500 m"):
        Robot.from_dh(_rows("kuka_kr6_r900"), "dh", base=base)


def test_prismatic_limit_in_mm(tmp_path, capsys):
    """A 6 m track on a KR6 with its upper limit in mm (6000): before, a 6 km travel was
    read without a word; now one line naming row 1, column 'upper' and 6 m."""
    track = {"name": "track", "a": 0, "alpha": -H, "d": 0, "theta": 0, "type": "prismatic"}
    rows = [track | {"lower": 0.0, "upper": 6000.0}, *_rows("kuka_kr6_r900")]
    with pytest.raises(DataError, match=r"row 1, column 'upper': 6000 m .* write 6 for 6000 mm"):
        Robot.from_dh(rows, "dh")
    rows[0]["upper"] = 6.0
    assert Robot.from_dh(rows, "dh").dof == 7

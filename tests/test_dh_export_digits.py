"""An exported DH table holds the calibrated numbers without the round-off of turning
the chain's frames: 0.42, not 0.4199999999999998; 0, not 6.6e-20 (a zero inertia turned
came out as 2.3e-33 kg m^2), while it still carries the geometry to 1e-9 m."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yaml

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.effects import ExtendedModel, make_effect
from hybrid_pk.io.dh_export import geometric_model, model_dh_table, write_dh_yaml
from hybrid_pk.io.model_file import save_model
from hybrid_pk.robot.dh_table import INERTIA_COLUMNS

pytestmark = pytest.mark.usefixtures("one_thread")

H = math.pi / 2
# KUKA KR 6 R900's published DH table [m, rad] with link masses and centres of mass
# (no inertia columns): a, alpha, d, theta, mass, com.
KR6 = [
    (0.025, -H, 0.4, 0.0, 12.0, (0.0, 0.0, 0.1)),
    (0.455, 0.0, 0.0, -H, 9.0, (-0.23, 0.0, 0.05)),
    (0.035, -H, 0.0, 0.0, 6.0, (0.0, -0.02, 0.0)),
    (0.0, H, 0.42, 0.0, 3.0, (0.0, 0.08, 0.0)),
    (0.0, -H, 0.0, 0.0, 1.5, (0.0, 0.0, 0.0)),
    (0.0, 0.0, 0.08, 0.0, 0.3, (0.0, 0.0, -0.01)),
]


def _kr6(half_pi: float = H) -> Robot:
    """The table, pi/2 written as ``half_pi`` (1.5708 in hand-converted tables)."""
    rows = [
        {"name": f"a{i}", "a": a, "alpha": round(al / H) * half_pi, "d": d}
        | {"theta": round(th / H) * half_pi, "type": "revolute"}
        | {"lower": -2.9, "upper": 2.9, "mass": m, "com_x": c[0], "com_y": c[1], "com_z": c[2]}
        for i, (a, al, d, th, m, c) in enumerate(KR6, start=1)
    ]
    return Robot.from_dh(rows, "dh")


@pytest.mark.parametrize("convention", ["dh", "mdh"])
def test_exported_numbers_carry_no_roundoff(tmp_path, convention):
    robot = _kr6()
    effects = [
        make_effect(robot, "joint_offset:a2", 6e-4),
        make_effect(robot, "link_length:a3", [5e-4, 0.0, -3e-4]),
    ]
    model = ExtendedModel(robot, effects)
    path = write_dh_yaml(model_dh_table(model, convention), tmp_path / "t.yaml")
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    values = [v for f in ("base", "flange") for k in ("xyz", "rpy") for v in doc[f][k]]
    for row in doc["joints"]:
        values += [row[k] for k in ("a", "alpha", "d", "theta", "beta")]
        values += [row[k] for k in INERTIA_COLUMNS[1:4]]
        assert all(row[k] == round(row[k], 15) for k in INERTIA_COLUMNS[4:]), row
    assert all(v == round(v, 12) for v in values), values  # before: 6.6e-20, 0.4199999999999998
    assert doc["joints"][3]["d"] == 0.42  # before: 0.4199999999999998
    q = robot.sample_q(500, torch.Generator().manual_seed(0))
    with torch.no_grad():
        gap = (Robot.from_dh(path).fk(q) - geometric_model(model).end_pose(q))[:, :3, 3]
    assert float(gap.norm(dim=-1).max()) < 1e-9


@pytest.mark.parametrize("half_pi", [H, 1.5708])
def test_normals_keep_their_direction_through_a_calibration(half_pi):
    """A KR6 imported from its DH table (theta2 = -pi/2 puts link 2 upright, square to
    the reference axis) exported as MDH: the nominal table is the textbook one (a2 =
    +0.455, theta2 = -pi/2, theta3 = 0; before: a = -0.455, theta2 = +pi/2, theta3 = pi,
    round-off's choice), and the calibrated table keeps those directions (before: a
    jumped from -0.455 to +0.455 and theta3 from pi to -0.001, as if the calibration had
    turned the link over)."""
    robot = _kr6(half_pi)
    nominal = model_dh_table(ExtendedModel(robot), "mdh").rows
    assert nominal[2, 0] == pytest.approx(0.455, abs=1e-12)
    assert nominal[1, 3] == pytest.approx(-half_pi, abs=1e-12)
    assert nominal[2, 3] == pytest.approx(0.0, abs=1e-12)
    for offset in (6e-4, -6e-4):
        effects = [make_effect(robot, "joint_offset:a2", offset)]
        effects.append(make_effect(robot, "link_length:a3", [5e-4, 0.0, -3e-4]))
        calibrated = model_dh_table(ExtendedModel(robot, effects), "mdh").rows
        assert np.abs(calibrated - nominal).max() < 5e-3, calibrated - nominal


def test_export_names_the_cells_the_calibration_changed(tmp_path, capsys):
    """`export --format dh` lists each cell that differs from the nominal robot's table
    with its change (before: only what the file cannot carry; the numbers a controller
    has to take were left to a diff by hand); a model without geometric effects says
    its table is the nominal one."""
    robot = _kr6()
    effects = [make_effect(robot, "joint_offset:a2", 6e-4)]
    effects.append(make_effect(robot, "link_length:a3", [5e-4, 0.0, -3e-4]))
    for name, model in (("cal", ExtendedModel(robot, effects)), ("nom", ExtendedModel(robot))):
        save_model(tmp_path / f"{name}.pt", model)
        out = tmp_path / f"{name}.yaml"
        assert (
            main(["export", str(tmp_path / f"{name}.pt"), "--format", "dh", "--out", str(out)]) == 0
        )
    printed = capsys.readouterr().out
    assert "changed from the nominal dh's dh table [m, rad]:" in printed
    changed = [
        line.split(":")[0].strip() for line in printed.splitlines() if line.startswith("  a")
    ]
    assert changed == ["a2", "a3"], printed  # a1, a4-a6 as nominal
    assert "theta -1.57079633 -> -1.56909743 (+0.0017)" in printed  # offset + link_length
    assert "unchanged from the nominal dh's dh table" in printed
    assert "changed from the nominal" in (tmp_path / "cal.yaml").read_text(encoding="utf-8")

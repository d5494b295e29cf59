"""A robot whose links carry no mass (a datasheet's DH table without its mass columns)
and rows without payload: gravity loads no joint, so joint compliance and deflection
move nothing. `calibrate` refuses to size them, `diagnose` says it did not test them,
`simulate` says why an injected compliance is not in its rows (not 'absorbed by the
frames')."""

from __future__ import annotations

import math

import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.effects import unloaded_reason

pytestmark = pytest.mark.usefixtures("one_thread")

H = math.pi / 2
# KUKA KR 6 R900's published DH table [m, rad], no mass columns.
KR6 = """name,a,alpha,d,theta,type,lower,upper
a1,0.025,-{h},0.4,0,revolute,-2.9671,2.9671
a2,0.455,0,0,-{h},revolute,-3.3161,0.7854
a3,0.035,-{h},0,0,revolute,-2.0944,2.7227
a4,0,{h},0.42,0,revolute,-3.2289,3.2289
a5,0,-{h},0,0,revolute,-2.0944,2.0944
a6,0,0,0.08,0,revolute,-6.1087,6.1087
""".format(h=repr(H))


@pytest.fixture(scope="module")
def massless(tmp_path_factory):
    """``(urdf, campaign)``: the massless KR6 and 80 rows with a joint offset."""
    root = tmp_path_factory.mktemp("unloaded")
    (root / "kr6.csv").write_text(KR6, encoding="utf-8")
    urdf, data = root / "kr6.urdf", root / "c.csv"
    argv = ["import", "dh", str(root / "kr6.csv"), "--convention", "dh", "--out", str(urdf)]
    assert main(argv) == 0
    argv = ["simulate", str(urdf), "--n", "80", "--noise-mm", "0.02", "--seed", "1"]
    assert main([*argv, "--effects", "joint_offset:a2=6e-4", "--out", str(data)]) == 0
    return urdf, data


def test_reason_only_without_mass_and_payload(massless):
    robot = Robot.from_urdf(massless[0])
    assert "carry no mass" in unloaded_reason(robot, None)
    assert unloaded_reason(robot, torch.tensor([0.0, 0.0])) is not None
    assert unloaded_reason(robot, torch.tensor([0.0, 2.0])) is None  # a payload loads it
    assert unloaded_reason(Robot.from_urdf("rx160"), None) is None


def test_calibrate_refuses_a_compliance_nothing_loads(massless, tmp_path, capsys):
    """Before: exit 0 with 'joint_compliance:a2 0 +- nan' and a condition number of
    1e300 blamed on ISO cube poses; now exit 2, one line saying why and what to give."""
    urdf, data = massless
    out = tmp_path / "m.pt"
    argv = ["calibrate", str(data), "--robot", str(urdf), "--out", str(out), "--no-progress"]
    assert main([*argv, "--effects", "joint_offset:a2,joint_compliance:a2"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "joint_compliance:a2 cannot be sized: gravity loads no joint" in err
    assert "mass, com_x, com_y, com_z columns" in err
    assert not out.exists()
    assert main([*argv, "--effects", "joint_offset:a2", "--no-urdf"]) == 0


def test_diagnose_says_it_did_not_test_gravity_effects(massless, tmp_path, capsys):
    urdf, data = massless
    argv = ["diagnose", str(data), "--robot", str(urdf), "--no-progress"]
    assert main([*argv, "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    assert "note: gravity loads no joint: kr6's moving links carry no mass" in out
    assert "were not tested" in out


def test_simulate_names_why_a_compliance_is_not_there(massless, tmp_path, capsys):
    urdf = massless[0]
    argv = ["simulate", str(urdf), "--n", "40", "--noise-mm", "0.02", "--seed", "2"]
    argv += ["--effects", "joint_compliance:a2=5e-5", "--out", str(tmp_path / "s.csv")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "note: joint_compliance:a2: gravity loads no joint" in out
    assert "absorbed by" not in out

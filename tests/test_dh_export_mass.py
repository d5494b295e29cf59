"""``hybrid-pk export --format dh|mdh`` writes the links' inertials, and ``hybrid-pk
import dh`` reads them back: the statics survive the round trip.

Each row holds segment ``i``'s mass, centre of mass and inertia in table frame ``i``
(``dh``: the frame row ``i`` ends in; ``mdh``: the frame on joint ``i``'s axis), where
the importer attaches them. Read back, the robot must hold the same loads as the model:
gravity torques and full static wrenches at 50 random joint values, the moving mass,
its centre of mass and every segment's inertia tensor (in the root frame) at a few.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.effects import Conditions
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.io.dh_export import geometric_model
from hybrid_pk.io.model_file import save_model
from hybrid_pk.robot.dh_table import INERTIA_COLUMNS
from tests.helpers import run_rng
from tests.test_dh_export import _random_model

pytestmark = pytest.mark.usefixtures("one_thread")

# Relative to the largest torque: the URDF carries every float by its shortest exact
# text, the table rounds lengths and angles to 1e-12 and inertias to 1e-15 kg m^2, so
# the loads agree to that rounding; 1e-9 is the geometry's own acceptance.
REL = 1e-9


def _round_trip(source: str, convention: str, tmp_path: Path, capsys) -> tuple[Robot, str]:
    """export SOURCE --format CONVENTION, then import dh: the re-imported robot and what
    the export printed."""
    table, urdf = tmp_path / f"{convention}.yaml", tmp_path / f"{convention}.urdf"
    assert main(["export", source, "--format", convention, "--out", str(table)]) == 0
    printed = capsys.readouterr().out
    assert main(["import", "dh", str(table), "--out", str(urdf)]) == 0
    assert "statics from the table" in capsys.readouterr().out
    rows = yaml.safe_load(table.read_text(encoding="utf-8"))["joints"]
    assert all(set(INERTIA_COLUMNS) <= set(r) for r in rows)
    back = Robot.from_urdf(urdf)
    back.requires_grad_(False)
    return back, printed


def _loads(robot: Robot, q: torch.Tensor, params=None) -> dict[str, np.ndarray]:
    """Gravity torques, static wrenches (moment about the root origin: each robot's
    joint frames sit elsewhere on the same axes, and a moment is about a point), moving
    mass, its centre of mass and each segment's inertia in the root frame, at ``q``."""
    with torch.no_grad():
        tau = robot.gravity_torques(q, params=params)
        wrench = robot.static_wrenches(q, params=params)
        frames = robot.link_frames(q, params)[:, : robot.chain_dof]
        force, about_joint = wrench[..., :3], wrench[..., 3:]
        moment = about_joint + torch.linalg.cross(frames[..., :3, 3], force)
    m, c = robot.segment_mass[1:], robot.segment_com[1:]
    R, p = frames[..., :3, :3], frames[..., :3, 3]
    placed = (R @ c[..., None])[..., 0] + p
    com = (m[:, None] * placed).sum(-2) / m.sum()
    inertia = torch.as_tensor(robot.spec.segment_inertia[1:])
    turned = R @ inertia @ R.transpose(-1, -2)
    return {
        "tau": tau.numpy(),
        "force": force.numpy(),
        "moment": moment.numpy(),
        "mass": np.array(float(m.sum())),
        "com": com.numpy(),
        "inertia": turned.numpy(),
    }


def _compare(want: dict, got: dict) -> dict[str, float]:
    """Largest difference per quantity, relative to the quantity's largest value."""
    return {
        k: float(np.abs(got[k] - want[k]).max() / max(np.abs(want[k]).max(), 1e-300)) for k in want
    }


@pytest.mark.parametrize("convention", ["dh", "mdh"])
@pytest.mark.parametrize("name", ["ur10", "rx160"])
def test_nominal_statics_round_trip(name, convention, tmp_path, capsys):
    """export nominal:ROBOT -> import dh: the same gravity torques, static wrenches,
    moving mass, centre of mass and inertias (fails where the table holds no masses:
    the re-imported arm then has no load)."""
    robot = Robot.from_urdf(name)
    robot.requires_grad_(False)
    back, printed = _round_trip(f"nominal:{name}", convention, tmp_path, capsys)
    assert "link masses written" in printed
    assert "not the links' masses" not in printed
    root = float(robot.segment_mass[0])
    assert f"the root link's {root:.4g} kg" in printed  # fixed: no row, said
    q = robot.sample_q(50, torch.Generator().manual_seed(11))
    want, got = _loads(robot, q), _loads(back, q)
    assert np.abs(want["tau"]).max() > 10.0  # a loaded arm [Nm], not a vacuous compare
    errors = _compare(want, got)
    print(f"{name} {convention} relative errors: {errors}")
    assert max(errors.values()) < REL, errors


@pytest.mark.parametrize("convention", ["dh", "mdh"])
@pytest.mark.parametrize("name", ["ur10", "rx160"])
def test_calibrated_statics_round_trip(name, convention, tmp_path, capsys):
    """A model with random joint offsets, axis misalignments and link lengths: the
    re-imported robot at commanded q holds the loads of the model's geometry at q plus
    its offsets (the segments' masses ride on the calibrated joint frames)."""
    robot = Robot.from_urdf(name)
    robot.requires_grad_(False)
    model = _random_model(robot, run_rng(f"dh-mass-{name}-{convention}"))
    model.requires_grad_(False)
    save_model(tmp_path / "m.pt", model)
    back, _ = _round_trip(str(tmp_path / "m.pt"), convention, tmp_path, capsys)
    geometric = geometric_model(model)
    q = robot.sample_q(50, torch.Generator().manual_seed(12))
    with torch.no_grad():
        params = geometric.kinematic_params(
            Conditions(temperature=torch.tensor(REFERENCE_TEMPERATURE, dtype=torch.float64))
        )
        params = type(params)(*(t.detach() for t in params))
        moved = geometric.kinematic_joint_values(q)
    assert (moved - q).abs().max() > 1e-4  # the offsets are there to be carried
    want, got = _loads(robot, moved, params), _loads(back, q)
    errors = _compare(want, got)
    print(f"{name} {convention} calibrated relative errors: {errors}")
    assert max(errors.values()) < REL, errors


def test_massless_robot_gets_no_line_and_no_columns(tmp_path, capsys):
    """A table-built robot without masses exports no inertial columns and says nothing
    about masses."""
    rows = [
        {"name": f"j{i}", "a": 0.3, "alpha": 1.2, "d": 0.1, "theta": 0.0, "type": "revolute"}
        | {"lower": -2.0, "upper": 2.0}
        for i in range(1, 4)
    ]
    src = tmp_path / "arm.yaml"
    src.write_text(yaml.safe_dump({"convention": "dh", "joints": rows}), encoding="utf-8")
    urdf = tmp_path / "arm.urdf"
    assert main(["import", "dh", str(src), "--out", str(urdf)]) == 0
    capsys.readouterr()
    out = tmp_path / "out.yaml"
    assert main(["export", f"nominal:{urdf}", "--format", "mdh", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "masses" not in printed
    written = yaml.safe_load(out.read_text(encoding="utf-8"))["joints"]
    assert not any("mass" in r for r in written)


_BRANCHED = """<?xml version="1.0"?>
<robot name="branched">
  <link name="base_link"/>
  <link name="link_1">{inertial}</link>
  <link name="link_2">{inertial}</link>
  <link name="finger">{inertial}</link>
  <link name="tool0"/>
  <joint name="j1" type="revolute"><parent link="base_link"/><child link="link_1"/>
    <origin xyz="0 0 0.4"/><axis xyz="0 0 1"/>{limit}</joint>
  <joint name="j2" type="revolute"><parent link="link_1"/><child link="link_2"/>
    <origin xyz="0.3 0 0" rpy="1.5708 0 0"/><axis xyz="0 0 1"/>{limit}</joint>
  <joint name="finger_joint" type="revolute"><parent link="link_1"/><child link="finger"/>
    <origin xyz="0 0.1 0"/><axis xyz="1 0 0"/>{limit}
    <mimic joint="j2"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="link_2"/><child link="tool0"/>
    <origin xyz="0.5 0 0"/></joint>
</robot>
"""
_MASS = (
    '<inertial><origin xyz="0.1 0 0"/><mass value="2.0"/>'
    '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>'
)


def test_driven_off_chain_mass_is_not_written_and_said(tmp_path, capsys):
    """A mass on an off-chain joint that a chain joint drives (a finger following j2,
    on j1's link) moves about another axis than any row's: no inertial columns (a
    partial table would give wrong statics), and the line says why."""
    urdf = tmp_path / "branched.urdf"
    limit = '<limit lower="-2" upper="2" effort="0" velocity="0"/>'
    urdf.write_text(_BRANCHED.format(inertial=_MASS, limit=limit), encoding="utf-8")
    robot = Robot.from_urdf(urdf, end_link="tool0")
    assert robot.spec.branches  # what this test is about: a driven off-chain mass
    assert not robot.has_mimic
    out = tmp_path / "t.yaml"
    argv = ["export", f"nominal:{urdf}", "--end-link", "tool0", "--format", "dh"]
    assert main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "not the links' masses: a mass off the chain (on finger_joint," in printed
    written = yaml.safe_load(out.read_text(encoding="utf-8"))["joints"]
    assert not any("mass" in r for r in written)


def _pin_moving_inertia(pin, urdf: Path, q: np.ndarray) -> np.ndarray:
    """pinocchio's reading of ``urdf``: mass, first moment [kg m] and inertia about
    the root origin [kg m²] of every body a joint moves (its own fixed-link merging and
    parallel-axis sums, nothing from hybrid_pk), one ``(13,)`` row per configuration."""
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    out = []
    for qk in q:
        pin.forwardKinematics(model, data, qk)
        total = np.zeros(13)
        for j in range(1, model.njoints):
            body, pose = model.inertias[j], data.oMi[j]
            R, c = pose.rotation, pose.act(body.lever)
            at_origin = R @ body.inertia @ R.T + body.mass * ((c @ c) * np.eye(3) - np.outer(c, c))
            total += np.concatenate([[body.mass], body.mass * c, at_origin.ravel()])
        out.append(total)
    return np.array(out)


@pytest.mark.parametrize("convention", ["dh", "mdh"])
def test_inertias_in_pinocchio(convention, tmp_path, capsys, pin):
    """The RX160 (products of inertia, centres of mass off every axis) exported and
    imported: pinocchio reads the same moving mass, first moment and inertia about the
    root origin from the re-imported URDF as from the shipped one, at 10 random q."""
    from hybrid_pk.robot.chain_spec import resolve_urdf

    _round_trip("nominal:rx160", convention, tmp_path, capsys)
    robot = Robot.from_urdf("rx160")
    q = robot.sample_q(10, torch.Generator().manual_seed(13)).numpy()
    want = _pin_moving_inertia(pin, resolve_urdf("rx160"), q)
    got = _pin_moving_inertia(pin, tmp_path / f"{convention}.urdf", q)
    error = float(np.abs(got - want).max() / np.abs(want).max())
    print(f"rx160 {convention}: pinocchio inertia relative error {error:.2e}")
    assert error < REL

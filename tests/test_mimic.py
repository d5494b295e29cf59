"""Mimic joints: the robot's joints are the independent ones, the chain follows them.

Oracles: the same chain with the coupling expanded by hand (the URDF without its
``<mimic>`` tags, driven through a hand-written mapping), pinocchio on that full tree
(every joint independent, the side-branch cylinder included) and pinocchio's own mimic
joints where it can load them (a leader on the chain, declared before its mimic).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.func import functional_call

import hybrid_pk as hpk
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.robot import ChainKernel, KinematicParams
from tests.helpers import assert_transforms_close, check_gradients

F64 = torch.float64
G = 9.80665
ARM = [f"dsr_joint{i}" for i in range(1, 7)]
ROD_MASS = 6.5  # [kg] column_actuator_link, the cylinder rod on the side branch


def _column() -> hpk.Robot:
    return hpk.Robot.from_urdf("column_arm", end_link="tool0")


@pytest.fixture(scope="module")
def robot() -> hpk.Robot:
    return _column()


@pytest.fixture(scope="module")
def plain_urdf(robot, tmp_path_factory) -> Path:
    """The same URDF without its mimic tags: every joint independent."""
    text = Path(robot.spec.urdf_path).read_text(encoding="utf-8")
    plain, n = re.subn(r"\s*<mimic [^>]*/>", "", text)
    assert n == 2
    path = tmp_path_factory.mktemp("mimic") / "column_arm_plain.urdf"
    path.write_text(plain, encoding="utf-8")
    return path


def expand(q: torch.Tensor) -> torch.Tensor:
    """Hand-written coupling of column_arm.urdf: each telescopic segment extends by half
    the cylinder stroke, the top one from a 5 mm stop; the arm joints are themselves."""
    c = q[..., :1]
    return torch.cat([0.5 * c, 0.5 * c + 0.005, q[..., 1:]], -1)


def expand_matrix() -> torch.Tensor:
    """``d expand / dq``, written out: (8 chain joints, 7 robot joints)."""
    A = torch.zeros(8, 7, dtype=F64)
    A[0, 0] = A[1, 0] = 0.5
    A[2:, 1:] = torch.eye(6, dtype=F64)
    return A


def test_joints_are_the_independent_ones(robot):
    assert robot.joint_names == ["column_prismatic_joint", *ARM]
    assert robot.chain_joint_names == ["column_middle_joint", "column_top_joint", *ARM]
    assert (robot.dof, robot.chain_dof, robot.has_mimic) == (7, 8, True)
    assert robot.joint_types == ["prismatic"] + ["revolute"] * 6
    lower, upper = robot.joint_limits
    assert (float(lower[0]), float(upper[0])) == (0.0, 0.9)  # the leader's own limits
    A, b = robot.coupling()
    torch.testing.assert_close(A, expand_matrix(), rtol=0, atol=0)
    torch.testing.assert_close(b, expand(torch.zeros(7, dtype=F64)), rtol=0, atol=0)
    (rod,) = robot.spec.branches  # the leader's own link hangs beside the chain
    assert (rod.joint, rod.segment, rod.mass) == ("column_prismatic_joint", 0, ROD_MASS)
    assert robot.spec.ignored_mass == 0.0
    assert robot.origin_xyz.shape == (9, 3)
    assert robot.axis.shape == (8, 3)


def test_robot_without_mimic_has_identity_coupling():
    robot = hpk.Robot.from_urdf("rx160")
    assert not robot.has_mimic
    assert robot.chain_joint_names == robot.joint_names
    A, b = robot.coupling()
    torch.testing.assert_close(A, torch.eye(6, dtype=F64), rtol=0, atol=0)
    assert not bool(b.any())


def test_fk_jacobian_gravity_equal_the_hand_expanded_chain(robot, plain_urdf):
    """Acceptance: FK, Jacobian and gravity of the mimic robot = the hand-expanded chain
    to 1e-12 (the rod's weight is added by hand: the plain URDF has it off the chain)."""
    plain = hpk.Robot.from_urdf(plain_urdf, end_link="tool0")
    assert plain.joint_names == robot.chain_joint_names
    assert not plain.has_mimic
    assert plain.spec.ignored_mass == ROD_MASS
    A = expand_matrix()
    q = robot.sample_q(200, torch.Generator().manual_seed(0))
    with torch.no_grad():
        T, T_hand = robot.fk(q), plain.fk(expand(q))
        J, J_hand = robot.jacobian(q), plain.jacobian(expand(q)) @ A
        tau = robot.gravity_torques(q, payload=3.0)
        tau_hand = plain.gravity_torques(expand(q), payload=3.0) @ A  # A^T tau, per row
        tau_hand[:, 0] += ROD_MASS * G  # the rod rises straight up with the cylinder
    assert float((T - T_hand).abs().max()) <= 1e-12
    assert float((J - J_hand).abs().max()) <= 1e-12
    assert float((tau - tau_hand).abs().max()) <= 1e-12 * float(tau_hand.abs().max())
    # the leader holds half the load of each segment (virtual work) plus its rod
    above_middle = float(robot.spec.segment_mass[1:].sum()) + 3.0
    above_top = above_middle - float(robot.spec.segment_mass[1])
    expected = G * (0.5 * above_middle + 0.5 * above_top + ROD_MASS)
    torch.testing.assert_close(tau[:, 0], torch.full((200,), expected, dtype=F64))


def test_kernel_follows_the_coupling(robot):
    q = robot.sample_q(50, torch.Generator().manual_seed(1))
    base = transform(so3_exp(torch.tensor([0.1, -0.2, 0.3])), torch.ones(3))
    tool = transform(torch.eye(3, dtype=F64), torch.tensor([0.0, 0.0, 0.1], dtype=F64))
    T, J = ChainKernel(robot, base.to(F64), tool)(q)
    with torch.no_grad():
        assert float((T - base.to(F64) @ robot.fk(q) @ tool).abs().max()) <= 1e-12
        J0 = robot.jacobian(q)
    _, J_plain = ChainKernel(robot)(q)
    assert float((J_plain - J0).abs().max()) <= 1e-12
    assert J.shape == (50, 6, 7)


def test_matches_pinocchio_on_the_full_tree(pin, robot, plain_urdf):
    """pinocchio sees every joint (cylinder included) as independent; the coupling maps
    its joint space onto ours: q_full = f(q), J = J_full A_full, tau = A_full^T g_full."""
    model = pin.buildModelFromUrdf(str(plain_urdf))
    data = model.createData()
    fid = model.getFrameId("tool0")
    drive = {"column_prismatic_joint": (0, 1.0, 0.0), "column_middle_joint": (0, 0.5, 0.0)}
    drive["column_top_joint"] = (0, 0.5, 0.005)
    drive |= {name: (1 + i, 1.0, 0.0) for i, name in enumerate(ARM)}
    A_full = np.zeros((model.nv, 7))
    for name, (j, mul, _) in drive.items():
        A_full[model.idx_vs[model.getJointId(name)], j] = mul
    q = robot.sample_q(50, torch.Generator().manual_seed(2))
    gravity = tuple(float(v) for v in model.gravity.linear)
    with torch.no_grad():
        T, J = robot.fk(q).numpy(), robot.jacobian(q).numpy()
        tau = robot.gravity_torques(q, gravity=gravity).numpy()
    worst = np.zeros(3)
    for k, qk in enumerate(q.numpy()):
        q_full = np.zeros(model.nq)
        for name, (j, mul, off) in drive.items():
            q_full[model.idx_qs[model.getJointId(name)]] = mul * qk[j] + off
        pin.framesForwardKinematics(model, data, q_full)
        pin.computeJointJacobians(model, data, q_full)
        J_pin = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED) @ A_full
        g_pin = A_full.T @ pin.computeGeneralizedGravity(model, data, q_full)
        err = [
            np.abs(data.oMf[fid].homogeneous - T[k]).max(),
            np.abs(J_pin - J[k]).max(),
            np.abs(g_pin - tau[k]).max() / np.abs(g_pin).max(),
        ]
        worst = np.maximum(worst, err)
    assert bool((worst <= 1e-12).all()), f"FK, Jacobian, relative gravity: {worst}"


def _assert_matches_pinocchio_mimic(pin, robot: hpk.Robot, path: Path, seed: int) -> None:
    """FK, Jacobian and gravity of ``robot`` = pinocchio's model of ``path`` with its
    mimic joints (``mimic=True``: pinocchio's joint space is the independent joints)."""
    model = pin.buildModelFromUrdf(str(path), mimic=True)
    data = model.createData()
    fid = model.getFrameId(robot.end_link)
    ids = [model.getJointId(n) for n in robot.joint_names]
    cols = [model.idx_vs[jid] for jid in ids]
    q = robot.sample_q(30, torch.Generator().manual_seed(seed))
    gravity = tuple(float(v) for v in model.gravity.linear)
    with torch.no_grad():
        T, J = robot.fk(q).numpy(), robot.jacobian(q).numpy()
        tau = robot.gravity_torques(q, gravity=gravity).numpy()
        _, J_kernel = ChainKernel(robot)(q)
    np.testing.assert_allclose(J_kernel.numpy(), J, atol=1e-12)
    for k, qk in enumerate(q.numpy()):
        q_pin = np.zeros(model.nq)
        for i, jid in enumerate(ids):
            q_pin[model.idx_qs[jid]] = qk[i]
        pin.framesForwardKinematics(model, data, q_pin)
        pin.computeJointJacobians(model, data, q_pin)
        J_pin = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:, cols]
        g_pin = pin.computeGeneralizedGravity(model, data, q_pin)[cols]
        assert_transforms_close(T[k], data.oMf[fid].homogeneous, atol_pos=1e-12, atol_rot=1e-12)
        np.testing.assert_allclose(J[k], J_pin, atol=1e-12)
        np.testing.assert_allclose(tau[k], g_pin, rtol=1e-12, atol=1e-10)


def test_matches_pinocchio_mimic_joints(pin, tmp_path):
    """pinocchio's own mimic joints, on a variant it can load (its mimic support needs
    the leader on the chain): the top segment mimics the middle one, x1.0 + 5 mm."""
    text = (hpk.shipped_robots()["column_arm"]).read_text(encoding="utf-8")
    text = text.replace(
        '    <mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.0"/>\n', ""
    ).replace(
        '<mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.005"/>',
        '<mimic joint="column_middle_joint" multiplier="1.0" offset="0.005"/>',
    )
    path = tmp_path / "leader_on_chain.urdf"
    path.write_text(text, encoding="utf-8")
    robot = hpk.Robot.from_urdf(path, end_link="tool0")
    assert robot.joint_names == ["column_middle_joint", *ARM]
    assert robot.spec.ignored_mass == ROD_MASS  # the cylinder now drives nothing we model
    _assert_matches_pinocchio_mimic(pin, robot, path, seed=3)


def test_gradcheck_through_the_coupling(robot):
    """FK and gravity are differentiable w.r.t. the robot's joints and every chain
    parameter at once (float64)."""
    q = robot.sample_q(2, torch.Generator().manual_seed(4))
    rotvec = 1e-3 * torch.randn(9, 3, dtype=F64, generator=torch.Generator().manual_seed(5))

    def fk(q, xyz, rotvec, axis):
        params = {"origin_xyz": xyz, "origin_rotvec": rotvec, "axis": axis}
        return functional_call(robot, params, (q,))

    check_gradients(fk, q, robot.origin_xyz, rotvec, robot.axis)
    rot_urdf = robot.origin_rot_urdf

    def tau(q, xyz, rotvec, axis, payload):
        params = KinematicParams(xyz, rot_urdf @ so3_exp(rotvec), axis)
        return robot.gravity_torques(q, payload=payload, params=params)

    check_gradients(
        tau, q, robot.origin_xyz, rotvec, robot.axis, torch.tensor([2.0, 5.0]),
        require_all_used=False,
    )  # fmt: skip
    check_gradients(lambda q: robot.jacobian(q), q)


def test_effects_name_robot_joints_or_chain_origins(robot):
    """Joint-space effects name the robot's joints (the leader); geometric effects the
    origin in front of a chain joint, which may be a mimic joint."""
    offset = hpk.make_effect(robot, "joint_offset:column_prismatic_joint", 0.002)
    model = hpk.ExtendedModel(robot, [offset])
    q = robot.sample_q(5, torch.Generator().manual_seed(6))
    with torch.no_grad():
        shifted = robot.fk(q + torch.tensor([0.002, 0, 0, 0, 0, 0, 0], dtype=F64))
        torch.testing.assert_close(model.end_pose(q), shifted)
    with pytest.raises(hpk.HybridPKError, match=r"joint_offset needs a joint.*column_prismatic"):
        hpk.make_effect(robot, "joint_offset:column_top_joint")
    link = hpk.make_effect(robot, "link_length:column_top_joint", [0.0, 0.001, 0.0])
    assert link.joint_index == 1  # the origin between the two telescopic segments
    with pytest.raises(hpk.HybridPKError, match=r"link_length needs a joint.*column_middle_joint"):
        hpk.make_effect(robot, "link_length:column_prismatic_joint")  # off the chain
    with torch.no_grad():
        moved = hpk.ExtendedModel(robot, [link]).end_pose(q)[:, :3, 3] - robot.fk(q)[:, :3, 3]
    torch.testing.assert_close(moved, torch.tensor([0.0, 0.001, 0.0], dtype=F64).expand(5, 3))


def test_compliance_of_the_column_follows_its_load(robot):
    """A compliant column sags by c times the force its cylinder holds."""
    c = 2e-6  # [m/N]
    model = hpk.ExtendedModel(
        robot, [hpk.make_effect(robot, "joint_compliance:column_prismatic_joint", c)]
    )
    q = robot.sample_q(4, torch.Generator().manual_seed(7))
    with torch.no_grad():
        q_true = model.joint_values(q)
        force = robot.gravity_torques(q)[:, 0]
    torch.testing.assert_close(q_true[:, 0], q[:, 0] - c * force, rtol=0, atol=1e-12)
    torch.testing.assert_close(q_true[:, 1:], q[:, 1:])


def test_mimic_of_a_mimic_and_bad_tags(tmp_path):
    text = hpk.shipped_robots()["column_arm"].read_text(encoding="utf-8")
    chained = text.replace(
        '<mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.005"/>',
        '<mimic joint="column_middle_joint" multiplier="2.0" offset="0.001"/>',
    )
    (tmp_path / "chained.urdf").write_text(chained, encoding="utf-8")
    robot = hpk.Robot.from_urdf(tmp_path / "chained.urdf", end_link="tool0")
    A, b = robot.coupling()
    assert float(A[1, 0]) == 1.0
    assert float(b[1]) == 0.001

    missing = text.replace('<mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.0"/>',
                           '<mimic joint="no_such_joint"/>')  # fmt: skip
    (tmp_path / "missing.urdf").write_text(missing, encoding="utf-8")
    with pytest.raises(hpk.RobotModelError, match=r"column_middle_joint.*mimics 'no_such_joint'"):
        hpk.Robot.from_urdf(tmp_path / "missing.urdf", end_link="tool0")

    cycle = chained.replace(
        '<mimic joint="column_prismatic_joint" multiplier="0.5" offset="0.0"/>',
        '<mimic joint="column_top_joint"/>',
    )
    (tmp_path / "cycle.urdf").write_text(cycle, encoding="utf-8")
    with pytest.raises(hpk.RobotModelError, match="cycle"):
        hpk.Robot.from_urdf(tmp_path / "cycle.urdf", end_link="tool0")


def test_ik_solves_for_the_robot_joints(robot):
    q = robot.sample_q(4, torch.Generator().manual_seed(8))
    with torch.no_grad():
        targets = robot.fk(q)
    result = hpk.solve_ik(robot, targets, seeds=64, options=hpk.IKOptions(seed=0))
    assert result.joint_names == tuple(robot.joint_names)
    for i in range(4):
        sols = result.solutions(i)
        assert sols.shape[0] >= 1
        assert sols.shape[1] == 7
        with torch.no_grad():
            reached = robot.fk(sols)
        err = (reached[:, :3, 3] - targets[i, :3, 3]).norm(dim=-1)
        assert float(err.max()) < 1e-6
        lo, hi = robot.joint_limits
        assert bool(((sols >= lo) & (sols <= hi)).all())


def test_revolute_mimic_on_the_chain_matches_pinocchio(tmp_path, pin):
    """A leader on the chain with a revolute mimic further down (a parallelogram-like
    coupling, multiplier -1.5, offset 0.1 rad): the leader's Jacobian column sums both."""
    arm7 = Path(__file__).resolve().parent / "data" / "arm7_generic.urdf"
    text = arm7.read_text(encoding="utf-8").replace(
        '<limit lower="-2.0" upper="2.0" effort="30" velocity="3"/></joint>\n  <joint name="j7"',
        '<limit lower="-2.0" upper="2.0" effort="30" velocity="3"/>\n'
        '    <mimic joint="j2" multiplier="-1.5" offset="0.1"/></joint>\n  <joint name="j7"',
    )
    assert text.count("<mimic") == 1
    path = tmp_path / "arm7_mimic.urdf"
    path.write_text(text, encoding="utf-8")
    robot = hpk.Robot.from_urdf(path, end_link="tool0")
    assert robot.joint_names == ["j1", "j2", "j3", "j4", "j5", "j7"]
    assert robot.chain_dof == 7
    _assert_matches_pinocchio_mimic(pin, robot, path, seed=9)

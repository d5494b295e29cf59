"""Robot model: FK, Jacobian and gravity torques against pinocchio; gradients; errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch.func import functional_call

import hybrid_pk as hpk
from hybrid_pk.geometry import so3_exp
from hybrid_pk.robot import KinematicParams
from tests.helpers import BATCH_SHAPES, assert_transforms_close, check_gradients

HERE = Path(__file__).resolve().parent
ARM7 = HERE / "data" / "arm7_generic.urdf"
ROBOTS = ["rx160", "ur10", str(ARM7)]
N_RANDOM = 50


def _pin_model(pin, robot: hpk.Robot):
    model = pin.buildModelFromUrdf(robot.spec.urdf_path)
    return model, model.createData(), model.getFrameId(robot.end_link)


def _pin_q(model, robot: hpk.Robot, q: np.ndarray) -> np.ndarray:
    """Our joint vector in pinocchio's joint order (looked up by name)."""
    out = np.zeros(model.nq)
    for i, name in enumerate(robot.joint_names):
        out[model.idx_qs[model.getJointId(name)]] = q[i]
    return out


def _gravity_from_pin(model) -> tuple[float, float, float]:
    return tuple(float(v) for v in model.gravity.linear)


@pytest.fixture(scope="module", params=ROBOTS, ids=["rx160", "ur10", "arm7"])
def robot(request) -> hpk.Robot:
    # arm7 has a side-branch leaf (a sensor), so its end link must be named.
    return hpk.Robot.from_urdf(request.param, end_link="tool0")


def test_fk_matches_pinocchio_float64(pin, robot):
    model, data, fid = _pin_model(pin, robot)
    q = robot.sample_q(N_RANDOM, torch.Generator().manual_seed(1))
    with torch.no_grad():
        T = robot.fk(q)
    expected = []
    for qi in q.numpy():
        pin.framesForwardKinematics(model, data, _pin_q(model, robot, qi))
        expected.append(data.oMf[fid].homogeneous.copy())
    assert_transforms_close(T, np.stack(expected), atol_pos=1e-9, atol_rot=1e-9)


def test_jacobian_matches_pinocchio(pin, robot):
    model, data, fid = _pin_model(pin, robot)
    q = robot.sample_q(10, torch.Generator().manual_seed(2))
    with torch.no_grad():
        J = robot.jacobian(q).numpy()
    cols = [model.idx_vs[model.getJointId(n)] for n in robot.joint_names]
    for i, qi in enumerate(q.numpy()):
        qp = _pin_q(model, robot, qi)
        pin.computeJointJacobians(model, data, qp)
        pin.framesForwardKinematics(model, data, qp)
        Jp = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)[:, cols]
        np.testing.assert_allclose(J[i], Jp, atol=1e-12)


@pytest.mark.parametrize("payload", [0.0, 12.5])
def test_gravity_torques_match_pinocchio(pin, robot, payload):
    model, data, fid = _pin_model(pin, robot)
    if payload:
        # Independent payload model: a point mass added to the last joint's body at the
        # end-link frame, as pinocchio would represent a mounted tool.
        frame = model.frames[fid]
        jid = frame.parentJoint
        model.inertias[jid] = model.inertias[jid] + pin.Inertia(
            payload, frame.placement.translation, np.zeros((3, 3))
        )
        data = model.createData()
    q = robot.sample_q(N_RANDOM, torch.Generator().manual_seed(3))
    with torch.no_grad():
        tau = robot.gravity_torques(q, payload=payload, gravity=_gravity_from_pin(model)).numpy()
    cols = [model.idx_vs[model.getJointId(n)] for n in robot.joint_names]
    for i, qi in enumerate(q.numpy()):
        g = pin.computeGeneralizedGravity(model, data, _pin_q(model, robot, qi))[cols]
        scale = max(np.abs(g).max(), 1e-9)
        rel = np.abs(tau[i] - g).max() / scale
        assert rel <= 1e-6, f"config {i}: relative error {rel:.2e}, ours {tau[i]}, pin {g}"


def test_gravity_torque_payload_is_batched_per_sample(robot):
    q = robot.sample_q(4, torch.Generator().manual_seed(4))
    payload = torch.tensor([0.0, 1.0, 5.0, 20.0], dtype=torch.float64)
    with torch.no_grad():
        batched = robot.gravity_torques(q, payload=payload)
        single = torch.stack(
            [robot.gravity_torques(q[i], payload=float(payload[i])) for i in range(4)]
        )
    torch.testing.assert_close(batched, single, atol=1e-12, rtol=0)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_fk_any_batch_shape(robot, shape):
    q = robot.sample_q(int(np.prod(shape)) if shape else 1).reshape(*shape, robot.dof)
    T = robot.fk(q)
    assert T.shape == (*shape, 4, 4)
    assert robot.gravity_torques(q).shape == (*shape, robot.dof)
    assert robot.jacobian(q).shape == (*shape, 6, robot.dof)
    flat = robot.fk(q.reshape(-1, robot.dof)).reshape(*shape, 4, 4)
    torch.testing.assert_close(T, flat, atol=1e-14, rtol=0)


def test_float32_follows_q_dtype_and_agrees(robot):
    q = robot.sample_q(100, torch.Generator().manual_seed(5))
    with torch.no_grad():
        T64 = robot.fk(q)
        T32 = robot.fk(q.float())
    assert T32.dtype == torch.float32
    assert_transforms_close(T32, T64, atol_pos=2e-6, atol_rot=5e-6)


def test_link_frames_end_equals_fk(robot):
    q = robot.sample_q(7, torch.Generator().manual_seed(6))
    with torch.no_grad():
        torch.testing.assert_close(robot.link_frames(q)[..., -1, :, :], robot.fk(q))


def test_fk_gradcheck_joints_and_kinematic_params_together(robot):
    """FK is differentiable w.r.t. q and every kinematic parameter in one pass."""
    q = robot.sample_q(3, torch.Generator().manual_seed(7))
    rotvec = 1e-3 * torch.randn(robot.dof + 1, 3, dtype=torch.float64)

    def fk(q, xyz, rotvec, axis):
        params = {"origin_xyz": xyz, "origin_rotvec": rotvec, "axis": axis}
        return functional_call(robot, params, (q,))

    check_gradients(fk, q, robot.origin_xyz, rotvec, robot.axis)


def test_param_gradients_survive_q_requires_grad(robot):
    """Regression: pytorch-kinematics' analytic backward returns no gradient for chain
    offsets when q requires grad; ours must give both, and match finite differences."""
    q = robot.sample_q(5, torch.Generator().manual_seed(8)).requires_grad_(True)
    robot.zero_grad()
    robot.fk(q)[..., :3, 3].sum().backward()
    assert q.grad is not None
    assert bool(q.grad.abs().sum() > 0)
    g_xyz = robot.origin_xyz.grad.clone()
    # Moving the tip origin by d moves the end point by R_last·d, R_last the frame after
    # the last joint: d(sum of p)/dd = sum over the batch of 1^T R_last, exactly.
    with torch.no_grad():
        R_last = robot.link_frames(q)[:, robot.dof - 1, :3, :3]
        expected_tip = R_last.sum(dim=-2).sum(dim=0)
    torch.testing.assert_close(g_xyz[robot.dof], expected_tip, atol=1e-12, rtol=0)
    assert bool((g_xyz.abs().sum(-1) > 0).all()), "every origin translation must get a gradient"
    robot.zero_grad()


def test_gravity_gradcheck(robot):
    q = robot.sample_q(2, torch.Generator().manual_seed(9))
    rot_urdf = robot.origin_rot_urdf

    def tau(q, xyz, rotvec, axis, payload):
        params = KinematicParams(xyz, rot_urdf @ so3_exp(rotvec), axis)
        return robot.gravity_torques(q, payload=payload, params=params)

    # Translating the first origin moves the arm rigidly and changes no torque, so
    # zero gradients are legitimate for some parameters.
    rotvec = 1e-3 * torch.randn(robot.dof + 1, 3, dtype=torch.float64)
    check_gradients(
        tau,
        q,
        robot.origin_xyz,
        rotvec,
        robot.axis,
        torch.tensor([3.0, 7.0]),
        require_all_used=False,
    )
    # ... but q and the payload must reach the torques.
    check_gradients(lambda q, m: robot.gravity_torques(q, payload=m), q, torch.tensor([3.0, 7.0]))


def test_params_override_matches_modified_robot(robot):
    """fk(q, params=...) uses exactly the given parameters."""
    q = robot.sample_q(4, torch.Generator().manual_seed(10))
    base = robot.kinematic_params()
    shifted = KinematicParams(base.origin_xyz + 1e-3, base.origin_rot, base.axis)
    clone = hpk.Robot(robot.spec)
    with torch.no_grad():
        clone.origin_xyz += 1e-3
        torch.testing.assert_close(robot.fk(q, params=shifted), clone.fk(q))
        assert not torch.allclose(robot.fk(q), clone.fk(q))


def test_cache_sees_in_place_parameter_updates():
    robot = hpk.Robot.from_urdf("rx160")
    q = robot.sample_q(3, torch.Generator().manual_seed(11))
    with torch.no_grad():
        before = robot.fk(q).clone()
        robot.origin_xyz[2, 2] += 0.01  # link 2 longer by 10 mm
        after = robot.fk(q)
    assert float((after[..., :3, 3] - before[..., :3, 3]).norm(dim=-1).max()) > 1e-3


def test_contract_api_names():
    robot = hpk.Robot.from_urdf("ur10")
    assert robot.joint_names == [
        "shoulder_pan_joint",
        "shoulder_lift_joint",
        "elbow_joint",
        "wrist_1_joint",
        "wrist_2_joint",
        "wrist_3_joint",
    ]
    lower, upper = robot.joint_limits
    assert lower.shape == upper.shape == (6,)
    assert robot.end_link == "tool0"
    assert robot.to(torch.float32) is robot
    assert robot.dtype == torch.float32
    rx = hpk.Robot.from_urdf("rx160")
    assert rx.joint_names == [f"joint_{i}" for i in range(1, 7)]


def test_shipped_urdfs_have_tool0_as_only_leaf_and_masses():
    for name in ("rx160", "ur10"):
        spec = hpk.Robot.from_urdf(name).spec
        assert spec.end_link == "tool0"
        assert (spec.segment_mass[1:] > 0).all(), f"{name}: every moving segment has mass"


def test_end_link_option_shortens_chain():
    robot = hpk.Robot.from_urdf("rx160", end_link="link_4")
    assert robot.joint_names == ["joint_1", "joint_2", "joint_3", "joint_4"]
    assert robot.end_link == "link_4"


def test_unknown_end_link_lists_valid_links():
    with pytest.raises(hpk.InvalidFrame, match=r"unknown link 'nope'.*tool0"):
        hpk.Robot.from_urdf("rx160", end_link="nope")


def test_misspelled_end_link_names_the_urdf_and_the_close_link():
    with pytest.raises(hpk.InvalidFrame, match=r"rx160\.urdf: unknown link 'tool_0'") as info:
        hpk.Robot.from_urdf("rx160", end_link="tool_0")
    assert "(close match: 'tool0')" in str(info.value)


def test_unknown_robot_name_lists_shipped():
    with pytest.raises(hpk.RobotModelError, match=r"unknown robot 'kuka'.*rx160"):
        hpk.Robot.from_urdf("kuka")


def test_several_leaves_require_end_link(tmp_path):
    text = (
        ARM7.read_text()
        .replace('<link name="tool0"/>', '<link name="tool0"/>\n  <link name="camera"/>')
        .replace(
            "</robot>",
            '<joint name="cam" type="fixed"><parent link="l3"/><child link="camera"/></joint>\n'
            "</robot>",
        )
    )
    path = tmp_path / "two_leaves.urdf"
    path.write_text(text)
    with pytest.raises(hpk.RobotModelError, match=r"leaf links.*--end-link"):
        hpk.Robot.from_urdf(path)
    assert hpk.Robot.from_urdf(path, end_link="camera").dof == 3


def test_a_cut_off_urdf_is_one_line_naming_line_and_column(tmp_path, capsys):
    """A URDF cut off mid-joint: one line with the file, line and column of the XML
    error (before: yourdfpy's parser noise on two lines, then 'expected one root link')."""
    from hybrid_pk.cli.main import main

    lines = hpk.shipped_robots()["rx160"].read_text().splitlines()
    cut = next(i for i, line in enumerate(lines) if "<joint " in line) + 2
    path = tmp_path / "trunc.urdf"
    path.write_text("\n".join(lines[:cut]) + "\n")
    with pytest.raises(hpk.RobotModelError, match=r"trunc\.urdf, line \d+, column \d+: not well"):
        hpk.Robot.from_urdf(path)
    capsys.readouterr()
    assert main(["simulate", str(path), "--n", "5", "--out", str(tmp_path / "s.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"error: {path}, line {cut + 1}, column 1: not well-formed XML (premature end" in err
    assert not (tmp_path / "s.csv").exists()


def test_bad_q_shape_says_expected_and_found():
    robot = hpk.Robot.from_urdf("rx160")
    with pytest.raises(hpk.ShapeError, match=r"\(\*B, 6\).*found \(2, 5\)"):
        robot.fk(torch.zeros(2, 5))

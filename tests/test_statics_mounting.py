"""Statics for any mounting: the full static wrench per joint and gravity in any direction.

Oracle: pinocchio's recursive Newton-Euler at zero velocity and acceleration, whose
``data.f[i]`` is the spatial force the parent exerts on the subtree of joint ``i``
(local joint frame), in float64.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.robot import STANDARD_GRAVITY
from hybrid_pk.robot.statics import gravity_values

pin = pytest.importorskip("pinocchio")

HERE = Path(__file__).resolve().parent
ROBOTS = ["rx160", "ur10", str(HERE / "data" / "arm7_generic.urdf")]


@pytest.fixture(scope="module", params=ROBOTS, ids=["rx160", "ur10", "arm7"])
def robot(request) -> hpk.Robot:
    return hpk.Robot.from_urdf(request.param, end_link="tool0")


def _pin(robot: hpk.Robot, payload: float, gravity: np.ndarray):
    model = pin.buildModelFromUrdf(robot.spec.urdf_path)
    fid = model.getFrameId(robot.end_link)
    if payload:
        frame = model.frames[fid]
        jid = frame.parentJoint
        model.inertias[jid] = model.inertias[jid] + pin.Inertia(
            payload, frame.placement.translation, np.zeros((3, 3))
        )
    model.gravity.linear = gravity
    return model, model.createData()


def _pin_q(model, robot: hpk.Robot, q: np.ndarray) -> np.ndarray:
    out = np.zeros(model.nq)
    for i, name in enumerate(robot.joint_names):
        out[model.idx_qs[model.getJointId(name)]] = q[i]
    return out


@pytest.mark.parametrize("payload", [0.0, 8.0])
def test_static_wrenches_match_pinocchio_rnea_forces(robot, payload):
    gen = torch.Generator().manual_seed(11)
    gravity = torch.randn(3, generator=gen, dtype=torch.float64)
    gravity = gravity / gravity.norm() * STANDARD_GRAVITY  # any mounting
    model, data = _pin(robot, payload, gravity.numpy())
    q = robot.sample_q(20, gen)
    with torch.no_grad():
        W = robot.static_wrenches(q, payload=payload, gravity=gravity).numpy()
    ids = [model.getJointId(n) for n in robot.joint_names]
    nv = model.nv
    for i, qi in enumerate(q.numpy()):
        qp = _pin_q(model, robot, qi)
        pin.rnea(model, data, qp, np.zeros(nv), np.zeros(nv))
        pin.forwardKinematics(model, data, qp)  # rnea leaves oMi alone
        for j, jid in enumerate(ids):
            R = data.oMi[jid].rotation
            expected = np.concatenate([R @ data.f[jid].linear, R @ data.f[jid].angular])
            scale = max(np.abs(expected).max(), 1.0)
            err = np.abs(W[i, j] - expected).max() / scale
            assert err < 1e-10, f"config {i}, joint {robot.joint_names[j]}: {W[i, j]} vs {expected}"


def test_axial_component_of_the_wrench_is_the_gravity_torque(robot):
    gen = torch.Generator().manual_seed(12)
    q = robot.sample_q(16, gen)
    gravity = torch.randn(16, 3, generator=gen, dtype=torch.float64)  # one per sample
    with torch.no_grad():
        W = robot.static_wrenches(q, payload=3.0, gravity=gravity)
        tau = robot.gravity_torques(q, payload=3.0, gravity=gravity)
        frames = robot.link_frames(q)
    axis = robot.axis / robot.axis.norm(dim=-1, keepdim=True)
    z = (frames[:, : robot.dof, :3, :3] @ axis[:, :, None])[..., 0]
    axial = torch.where(robot.revolute, (z * W[..., 3:]).sum(-1), (z * W[..., :3]).sum(-1))
    torch.testing.assert_close(axial, tau, atol=1e-10, rtol=0)
    per_sample = torch.stack(
        [robot.gravity_torques(q[k], payload=3.0, gravity=gravity[k]) for k in range(16)]
    )
    torch.testing.assert_close(tau, per_sample, atol=1e-12, rtol=0)


def test_static_wrench_gradcheck():
    robot = hpk.Robot.from_urdf("ur10")
    q = robot.sample_q(3, torch.Generator().manual_seed(13)).requires_grad_(True)
    g = torch.tensor([0.3, -2.0, -9.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda q, g: robot.static_wrenches(q, payload=2.0, gravity=g), (q, g)
    )


def test_bad_gravity_shape_is_a_clear_error():
    robot = hpk.Robot.from_urdf("rx160")
    with pytest.raises(hpk.errors.ShapeError, match="gravity"):
        robot.gravity_torques(torch.zeros(6, dtype=torch.float64), gravity=(0.0, -9.8))


def test_wrench_in_joint_frames_is_the_rotated_root_wrench(robot):
    q = robot.sample_q(5, torch.Generator().manual_seed(14))
    with torch.no_grad():
        root = robot.static_wrenches(q, payload=1.0)
        local = robot.static_wrenches(q, payload=1.0, frame="joint")
        R = robot.link_frames(q)[:, : robot.dof, :3, :3]
    back = torch.cat([(R @ local[..., :3, None])[..., 0], (R @ local[..., 3:, None])[..., 0]], -1)
    torch.testing.assert_close(back, root, atol=1e-10, rtol=0)


@pytest.mark.parametrize("payload", [0.0, 8.0])
def test_values_path_and_its_derivative_match_pinocchio(robot, payload):
    """The path without autograd (batch last, closed-form dg/dq: the compliance fixed
    point and the identification Jacobian) against pinocchio's g(q) and dg/dq."""
    gen = torch.Generator().manual_seed(15)
    gravity = torch.randn(3, generator=gen, dtype=torch.float64)
    gravity = gravity / gravity.norm() * STANDARD_GRAVITY  # any mounting
    model, data = _pin(robot, payload, gravity.numpy())
    q = robot.sample_q(20, gen)
    with torch.no_grad():  # the robot's parameters carry gradients otherwise
        tau, G = gravity_values(robot, q, payload, gravity, derivative=True)
    cols = [model.idx_vs[model.getJointId(n)] for n in robot.joint_names]
    for i, qi in enumerate(q.numpy()):
        qp = _pin_q(model, robot, qi)
        g = pin.computeGeneralizedGravity(model, data, qp)[cols]
        dg = pin.computeGeneralizedGravityDerivatives(model, data, qp)[np.ix_(cols, cols)]
        assert np.abs(tau[i].numpy() - g).max() <= 1e-10 * max(np.abs(g).max(), 1.0)
        err = np.abs(G[i].numpy() - dg).max() / max(np.abs(dg).max(), 1.0)
        assert err <= 1e-10, f"config {i}: dg/dq off by {err:.2e} relative"


def test_values_path_follows_mimic_and_prismatic_joints():
    """column_arm without its off-chain body (which keeps the differentiable path):
    telescopic prismatic joints coupled by mimic tags, per-row gravity and payload;
    values equal the differentiable statics and dg/dq its forward-mode derivative."""
    robot = hpk.Robot.from_urdf("column_arm", end_link="tool0").requires_grad_(False)
    assert gravity_values(robot, robot.sample_q(2), 1.0, (0.0, 0.0, -9.8)) is None
    robot.spec = dataclasses.replace(robot.spec, branches=())
    assert robot.has_mimic
    assert not bool(robot.chain_revolute.all())
    gen = torch.Generator().manual_seed(16)
    q = robot.sample_q(30, gen)
    gravity = torch.randn(30, 3, generator=gen, dtype=torch.float64) * 5.0
    payload = torch.rand(30, generator=gen, dtype=torch.float64) * 10.0
    tau, G = gravity_values(robot, q, payload, gravity, derivative=True)
    with torch.enable_grad():  # inputs that carry gradients: the differentiable path
        tau_ref = robot.gravity_torques(q.requires_grad_(True), payload, gravity).detach()
    q = q.detach()
    torch.testing.assert_close(tau, tau_ref, atol=1e-10, rtol=0)

    def torques(d):
        return robot.gravity_torques(q + d, payload, gravity).reshape(-1)

    G_ref = jacobian(torques, torch.zeros(robot.dof, dtype=q.dtype))[1]
    torch.testing.assert_close(G, G_ref.reshape(30, robot.dof, robot.dof), atol=1e-9, rtol=0)

"""Statics for any mounting: the full static wrench per joint and gravity in any direction.

Oracle: pinocchio's recursive Newton-Euler at zero velocity and acceleration, whose
``data.f[i]`` is the spatial force the parent exerts on the subtree of joint ``i``
(local joint frame), in float64.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.robot import STANDARD_GRAVITY

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

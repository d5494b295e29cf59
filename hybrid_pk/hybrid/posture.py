"""Which joints move the flange point: the rule behind ``qarm`` and the blocked hold-out.

A joint's *lever* at ``q`` is how far the flange point moves per radian of it (the
norm of its column of the position Jacobian; 1 per metre for a prismatic joint). Its
mean over the training rows ranks the joints by how much of the measured point they
move, for any joint count:

- ``qarm`` (the posture stage's angle inputs, :func:`resolve_arm`): the joints after
  the stage's frame up to the last one with a lever. A joint whose axis passes through
  the flange point (the last joint of nearly every arm) turns only the tool: its angle
  changes neither where the point is nor the arm's load (the load inputs cover the
  tool's), so the posture does not read it. Replaces ``q2-4``, which presumed a 6-axis
  arm (chosen on the UR10's splits);
- :func:`moving_joints`: the joints whose contiguous regions the blocked hold-out of the
  networks' training rows leaves out (:mod:`~hybrid_pk.training.blocked`).
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from hybrid_pk.hybrid.features import FeatureSpec
from hybrid_pk.hybrid.tuning import hybrid_tuning
from hybrid_pk.robot import Robot

__all__ = ["joint_levers", "moving_joints", "resolve_arm"]


def joint_levers(robot: Robot, q: Tensor) -> Tensor:
    """``(dof,)`` mean flange-point displacement per unit of each joint over rows
    ``q (N, dof)`` [m/rad, or m/m for prismatic joints]."""
    q = q.detach().to(torch.float64)
    rows = hybrid_tuning().lever_rows
    if q.shape[0] > rows:
        q = q[torch.randperm(q.shape[0], generator=torch.Generator().manual_seed(0))[:rows]]
    with torch.no_grad():
        J = robot.jacobian(q)
    return J[..., :3, :].norm(dim=-2).mean(0)


def moving_joints(robot: Robot, q: Tensor, after: int = 1) -> list[int]:
    """0-based joints from ``after`` on (default: after joint 1), the one that moves the
    flange point most first; joints on the point's axis left out."""
    lever = joint_levers(robot, q)
    order = [int(j) for j in torch.argsort(lever, descending=True) if int(j) >= after]
    return [j for j in order if float(lever[j]) > hybrid_tuning().on_axis_m]


def resolve_arm(spec: FeatureSpec, robot: Robot, q: Tensor) -> FeatureSpec:
    """``spec`` with ``qarm`` replaced by the joints ``frame + 1 .. J`` (1-based), ``J``
    the last joint after the frame with a lever above the tuning's ``on_axis_m`` over the
    training rows ``q``; every joint after the frame when none has one. A spec without
    ``qarm`` is returned as it is."""
    if not spec.arm:
        return spec
    moving = moving_joints(robot, q, spec.frame)
    last = max(moving) + 1 if moving else robot.dof
    return dataclasses.replace(spec, angles=(spec.frame + 1, last), arm=False)

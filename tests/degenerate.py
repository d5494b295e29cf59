"""Campaigns whose frames the data cannot fully determine (issue 17).

``wrist_campaign`` draws the first joints in a box (the position spreads over the
workspace) and solves the remaining joints for a flange orientation that stays within
a small cone (the real re-stationing of issue 17: a few poses per column height, the
flange hardly turns). Measurements come from an :class:`ExtendedModel` directly, so the
generator does not share code with ``simulate``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, approach_direction
from hybrid_pk.geometry import so3_exp, so3_log
from hybrid_pk.robot import Robot

DOWN = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # flange z down


def wrist_configs(
    robot: Robot,
    n: int,
    lower: Tensor,
    upper: Tensor,
    span_deg: float,
    gen: torch.Generator,
    R_target: Tensor = DOWN,
) -> Tensor:
    """``(n, dof)`` joints: the first ``dof - 3`` uniform in ``[lower, upper]``, the
    wrist solved so that the flange orientation lies within ``span_deg / 2`` of
    ``R_target`` (so any two rows differ by at most ``span_deg``)."""
    dt = robot.dtype
    lo, hi = robot.joint_limits
    m = 4 * n
    q = lower + torch.rand(m, robot.dof, generator=gen, dtype=dt) * (upper - lower)
    w = torch.randn(m, 3, generator=gen, dtype=dt)
    radius = torch.rand(m, 1, generator=gen, dtype=dt) * math.radians(span_deg) / 2
    R_t = R_target @ so3_exp(w / w.norm(dim=1, keepdim=True) * radius)
    wrist = list(range(robot.dof - 3, robot.dof))
    for _ in range(40):  # Newton on the wrist joints for the orientation alone
        e = so3_log(R_t @ robot.fk(q)[:, :3, :3].transpose(-1, -2))
        J = robot.jacobian(q)[:, 3:, :][:, :, wrist]
        step = torch.linalg.lstsq(J, e[..., None]).solution[..., 0]
        q[:, wrist] = q[:, wrist] + step.clamp(-0.3, 0.3)
    err = so3_log(R_t @ robot.fk(q)[:, :3, :3].transpose(-1, -2)).norm(dim=-1)
    ok = (err < 1e-9) & (q >= lo).all(-1) & (q <= hi).all(-1)
    assert int(ok.sum()) >= n, f"only {int(ok.sum())} of {m} wrist solutions are valid"
    return q[ok][:n]


def measure(
    robot: Robot,
    q: Tensor,
    effects: list,
    base: Tensor,
    tool: Tensor,
    noise_mm: float,
    gen: torch.Generator,
    source: str = "degenerate.csv",
) -> MeasuredData:
    """Position-only measurements of ``q`` on the robot with ``effects`` and frames."""
    n = q.shape[0]
    cond = Conditions(payload=torch.zeros(n, dtype=q.dtype), direction=approach_direction(q))
    with torch.no_grad():
        T = ExtendedModel(robot, effects, base=base, tool=tool)(q, cond)
    noise = 1e-3 * noise_mm * torch.randn(n, 3, generator=gen, dtype=q.dtype)
    return MeasuredData(
        q=q,
        position=T[:, :3, 3] + noise,
        quat=None,
        joint_names=tuple(robot.joint_names),
        file_index=torch.zeros(n, dtype=torch.long),
        rows=torch.arange(1, n + 1),
        sources=(source,),
        payload=cond.payload,
    )

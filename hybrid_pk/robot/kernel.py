"""Pose and geometric Jacobian of a serial chain for the IK inner loop.

A snapshot of the robot's chain constants (``Robot.chain_terms``, the same as
:meth:`Robot.fk`'s), with optional base and tool frames folded into the first and last
origin, kept contiguous in float64 in the batch-last layout of
:func:`~hybrid_pk.robot.chain.pose_jacobian_batch_last`, the one implementation of pose
plus Jacobian that :meth:`Robot.jacobian` uses too. Build a new kernel after changing
the robot's parameters. No gradients flow through it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.robot.chain import BatchLastTerms, batch_last_terms, pose_jacobian_batch_last
from hybrid_pk.robot.robot import Robot

__all__ = ["ChainKernel"]


class ChainKernel:
    """``q (M, dof) -> (T (M, 4, 4), J (M, 6, dof))`` for one serial chain.

    Args:
        robot: the chain (its current kinematic parameters are copied).
        base: optional ``(4, 4)`` transform applied before the chain (``T_meas_root``).
        tool: optional ``(4, 4)`` transform after the end link (``T_end_point``).

    ``T = base @ robot.fk(q) @ tool``; ``J`` rows ``[v; omega]``: velocity of ``T``'s
    origin and angular velocity, both in ``base``'s (the output) frame. ``q`` holds the
    robot's joints; mimic joints follow them (``J = J_chain @ A``).
    """

    def __init__(self, robot: Robot, base: Tensor | None = None, tool: Tensor | None = None):
        f64 = torch.float64
        with torch.no_grad():
            t = robot.chain_terms(f64)
            M = torch.stack([t.M0, t.M1, t.M2])  # (3 terms, n, 4, 4)
            tip = t.tip
            if base is not None:  # the terms are linear: base @ (M0 + f1 M1 + f2 M2)
                M = torch.cat([base.to(f64) @ M[:, :1], M[:, 1:]], 1)
            if tool is not None:
                tip = tip @ tool.to(f64)
            t = t._replace(M0=M[0], M1=M[1], M2=M[2], tip=tip)
            C = batch_last_terms(t)
        self.dof = robot.dof
        self.revolute = robot.chain_revolute.clone()
        self._all_revolute = bool(self.revolute.all())
        self._C = BatchLastTerms(*(x.contiguous() for x in C))
        self._mimic = None
        if robot.has_mimic:
            self._mimic = (
                robot.source.clone(),
                robot.multiplier.to(f64)[:, None].clone(),
                robot.offset.to(f64)[:, None].clone(),
            )

    def soa(self, qt: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Batch-last evaluation at ``qt (dof, M)`` [rad or m].

        Returns:
            ``R (3, 3, M)``, ``p (3, M)`` [m] of the pose and ``J (6, dof, M)``.
        """
        if self._mimic is None:
            return pose_jacobian_batch_last(self._C, qt, self.revolute, self._all_revolute)
        src, mul, off = self._mimic
        qt = torch.addcmul(off, qt[src], mul)  # (n_chain, M)
        R, p, J = pose_jacobian_batch_last(self._C, qt, self.revolute, self._all_revolute)
        return R, p, J.new_zeros(6, self.dof, J.shape[-1]).index_add_(1, src, J * mul)

    def __call__(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Pose ``(M, 4, 4)`` and Jacobian ``(M, 6, dof)`` at ``q (M, dof)`` [rad or m]."""
        R, p, J = self.soa(q.detach().to(torch.float64).T)
        M = q.shape[0]
        T = torch.zeros(M, 4, 4, dtype=torch.float64, device=q.device)
        T[:, :3, :3] = R.permute(2, 0, 1)
        T[:, :3, 3] = p.T
        T[:, 3, 3] = 1.0
        return T, J.permute(2, 0, 1)

"""Pose and geometric Jacobian of a serial chain in batch-last layout, for IK.

The same chain constants as :meth:`Robot.fk` (``Robot.chain_terms``: ``M0, M1, M2``
per joint, see :mod:`hybrid_pk.robot.chain`), evaluated in the layout that suits
thousands of tiny 3×3 products on a CPU: batch last. A rotation is a ``(3, 3, M)``
tensor, so one product is three fused multiply-adds over contiguous memory instead of
a batched matmul of 3×3 blocks. Measured (``python bench/fk.py --jacobian``): faster
than the batch-first frames for pose plus Jacobian from a few dozen configurations
on, slower for a single one; ``Robot.fk`` (pose only) keeps the batch-first balanced
tree, which is faster at every batch size for the pose alone.

The constants are a snapshot of the robot's parameters (and of optional base and tool
frames folded into the first and last origin): build a new kernel after changing
them. No gradients flow through it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.geometry.batch_last import compose, rotate
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
            M = M[:, :, :3, :]  # (3, n, 3, 4): the last rows are constant
        self.dof, self.n = robot.dof, robot.chain_dof
        self.revolute = robot.chain_revolute.clone()
        self._all_revolute = bool(self.revolute.all())
        L = M.permute(0, 2, 3, 1)[..., None]  # (3, 3, 4, n, 1): term, row, column, joint
        self._R = L[:, :, :3].contiguous()  # (3 terms, 3, 3, n, 1)
        self._t = L[0, :, 3].contiguous()  # (3, n, 1); revolute joints do not move it
        self._d = L[1, :, 3].contiguous()  # prismatic: the translation per unit of q
        self._a = t.axis.to(f64).T[..., None].contiguous()  # (3, n, 1) in the joint frames
        self._R_tip = tip[:3, :3][..., None].contiguous()  # (3, 3, 1)
        self._t_tip = tip[:3, 3][:, None].contiguous()  # (3, 1)
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
        if self._mimic is not None:
            src, mul, off = self._mimic
            qt = torch.addcmul(off, qt[src], mul)  # (n, M) chain joint values
        if self._all_revolute:
            f1, f2 = torch.sin(qt), 1 - torch.cos(qt)
        else:
            rev = self.revolute[:, None]
            f1 = torch.where(rev, torch.sin(qt), qt)
            f2 = torch.where(rev, 1 - torch.cos(qt), 0.0)
        R_loc = torch.addcmul(self._R[0], f1, self._R[1])
        R_loc = torch.addcmul(R_loc, f2, self._R[2])  # (3, 3, n, M)
        t_loc = self._t if self._all_revolute else torch.addcmul(self._t, f1, self._d)
        R = R_loc[:, :, 0]
        p = t_loc[:, 0].expand(3, qt.shape[1])
        origins, axes = [p], [rotate(R, self._a[:, 0])]
        for i in range(1, self.n):
            p = p + rotate(R, t_loc[:, i])
            R = compose(R, R_loc[:, :, i])
            origins.append(p)
            axes.append(rotate(R, self._a[:, i]))
        p_end = p + rotate(R, self._t_tip)
        R_end = compose(R, self._R_tip)
        z = torch.stack(axes, 1)  # (3, n, M)
        w = p_end[:, None, :] - torch.stack(origins, 1)
        v = torch.stack(  # z x w, written out (linalg.cross is slow on this layout)
            [
                z[1] * w[2] - z[2] * w[1],
                z[2] * w[0] - z[0] * w[2],
                z[0] * w[1] - z[1] * w[0],
            ]
        )
        if not self._all_revolute:
            rev = self.revolute[None, :, None]
            v = torch.where(rev, v, z)
            z = torch.where(rev, z, 0.0)
        J = torch.cat([v, z], 0)  # (6, n, M)
        if self._mimic is not None:
            src, mul, _ = self._mimic
            J = J.new_zeros(6, self.dof, J.shape[-1]).index_add_(1, src, J * mul)
        return R_end, p_end, J

    def __call__(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Pose ``(M, 4, 4)`` and Jacobian ``(M, 6, dof)`` at ``q (M, dof)`` [rad or m]."""
        R, p, J = self.soa(q.detach().to(torch.float64).T)
        M = q.shape[0]
        T = torch.zeros(M, 4, 4, dtype=torch.float64, device=q.device)
        T[:, :3, :3] = R.permute(2, 0, 1)
        T[:, :3, 3] = p.T
        T[:, 3, 3] = 1.0
        return T, J.permute(2, 0, 1)

"""Pose and geometric Jacobian of a serial chain, fast, for the IK inner loop.

Same mathematics as :meth:`Robot.fk` / :meth:`Robot.jacobian` (and checked against
them in the tests), in a layout that suits thousands of tiny 3×3 products on a CPU:
batch last. A rotation is a ``(3, 3, M)`` tensor, so one product is three fused
multiply-adds over contiguous memory instead of a batched matmul of 3×3 blocks
(several times faster in PyTorch on CPU at IK batch sizes).

The chain's constants are a snapshot of the robot's parameters (and of optional base
and tool frames folded into the first and last origin): build a new kernel after
changing them. No gradients flow through it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.geometry import skew, transform
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
    origin and angular velocity, both in ``base``'s (the output) frame.
    """

    def __init__(self, robot: Robot, base: Tensor | None = None, tool: Tensor | None = None):
        f64 = torch.float64
        with torch.no_grad():
            p = robot.kinematic_params()
            O = transform(p.origin_rot.to(f64), p.origin_xyz.to(f64)).clone()  # (dof+1, 4, 4)
            if base is not None:
                O[0] = base.to(f64) @ O[0]
            if tool is not None:
                O[-1] = O[-1] @ tool.to(f64)
            a = p.axis.to(f64)
            a = a / a.norm(dim=-1, keepdim=True)
        dof = robot.dof
        self.dof = dof
        self.revolute = robot.revolute.clone()
        rev = self.revolute.to(f64)[:, None, None]
        R0, t = O[:dof, :3, :3], O[:dof, :3, 3]
        K = skew(a)
        # Local rotation R0 (I + sin K + (1 - cos) K^2) for revolute joints; prismatic
        # joints translate by q along R0 a.
        self._R0 = R0.permute(1, 2, 0)[..., None].contiguous()  # (3, 3, dof, 1)
        self._R1 = (rev * (R0 @ K)).permute(1, 2, 0)[..., None].contiguous()
        self._R2 = (rev * (R0 @ K @ K)).permute(1, 2, 0)[..., None].contiguous()
        self._t = t.T[..., None].contiguous()  # (3, dof, 1)
        self._d = ((1 - rev[..., 0]) * (R0 @ a[..., None])[..., 0]).T[..., None].contiguous()
        self._a = a.T[..., None].contiguous()  # (3, dof, 1) axis in the joint frame
        self._R_tip = O[dof, :3, :3][..., None].contiguous()  # (3, 3, 1)
        self._t_tip = O[dof, :3, 3][:, None].contiguous()  # (3, 1)
        self._all_revolute = bool(self.revolute.all())

    def soa(self, qt: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Batch-last evaluation at ``qt (dof, M)`` [rad or m].

        Returns:
            ``R (3, 3, M)``, ``p (3, M)`` [m] of the pose and ``J (6, dof, M)``.
        """
        s, c = torch.sin(qt), 1 - torch.cos(qt)
        R_loc = torch.addcmul(self._R0, s, self._R1)
        R_loc = torch.addcmul(R_loc, c, self._R2)  # (3, 3, dof, M)
        t_loc = self._t if self._all_revolute else torch.addcmul(self._t, qt, self._d)
        R = R_loc[:, :, 0]
        p = t_loc[:, 0].expand(3, qt.shape[1])
        origins, axes = [p], [rotate(R, self._a[:, 0])]
        for i in range(1, self.dof):
            p = p + rotate(R, t_loc[:, i])
            R = compose(R, R_loc[:, :, i])
            origins.append(p)
            axes.append(rotate(R, self._a[:, i]))
        p_end = p + rotate(R, self._t_tip)
        R_end = compose(R, self._R_tip)
        z = torch.stack(axes, 1)  # (3, dof, M)
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
        return R_end, p_end, torch.cat([v, z], 0)

    def __call__(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Pose ``(M, 4, 4)`` and Jacobian ``(M, 6, dof)`` at ``q (M, dof)`` [rad or m]."""
        R, p, J = self.soa(q.detach().to(torch.float64).T)
        M = q.shape[0]
        T = torch.zeros(M, 4, 4, dtype=torch.float64, device=q.device)
        T[:, :3, :3] = R.permute(2, 0, 1)
        T[:, :3, 3] = p.T
        T[:, 3, 3] = 1.0
        return T, J.permute(2, 0, 1)

"""Pose and geometric Jacobian of a serial chain for the IK inner loop.

A snapshot of the robot's chain constants (``Robot.chain_terms``, the same as
:meth:`Robot.fk`'s), with optional base and tool frames folded into the first origin
and the tip, in the z-aligned form of :func:`~hybrid_pk.robot.aligned.aligned_chain`: every
joint frame turned so that its axis is its z axis. Then the frame ``P_i`` of each joint
holds the joint's axis and origin as two of its columns, so the Jacobian columns
``[z_i x (p - o_i); z_i]`` (prismatic ``[z_i; 0]``) read them without further
products, and the whole evaluation is a few dozen tensor operations, batch-last: on a
CPU each costs a few microseconds of dispatch whatever its size, which sets the speed
of the IK's late iterations.

:func:`~hybrid_pk.robot.chain.pose_jacobian_batch_last` (``Robot.jacobian``, per-sample
and differentiable parameters) is the reference the tests compare this one with.
Build a new kernel after changing the robot's parameters (:meth:`ChainKernel.of` does:
it keeps one per robot while its parameters stay the same). No gradients flow through it.
"""

from __future__ import annotations

import weakref

import torch
from torch import Tensor

from hybrid_pk.robot.aligned import AlignedChain, aligned_chain, aligned_frames
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
            C = aligned_chain(robot.chain_terms(f64), base, tool)
        # float32 constants rounded from the float64 ones (the IK's first, coarse phase)
        cast = AlignedChain(C.first.float(), tuple(r.float() for r in C.rows), C.e3.float())
        self._C = {f64: C, torch.float32: cast}
        self.dof = robot.dof
        self.revolute = robot.chain_revolute.clone()
        self._all_revolute = bool(self.revolute.all())
        self._mimic = None
        if robot.has_mimic:
            self._mimic = (
                robot.source.clone(),
                robot.multiplier.to(f64)[:, None].clone(),
                robot.offset.to(f64)[:, None].clone(),
            )

    @classmethod
    def of(cls, robot: Robot) -> ChainKernel:
        """The kernel of ``robot`` without frames, made once while its parameters stay
        the same (its cached chain terms, renewed on every change, are the key): an IK
        call need not rebuild it (~0.3 ms, about 1 % of a 50-target call)."""
        with torch.no_grad():
            terms = robot.chain_terms(torch.float64)
        memo = _OWN.get(robot)
        if memo is None or memo[0] is not terms:
            memo = (terms, cls(robot))
            _OWN[robot] = memo
        return memo[1]

    def soa(self, qt: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Batch-last evaluation at ``qt (dof, M)`` [rad or m], float64 or float32.

        Returns:
            ``R (3, 3, M)``, ``p (3, M)`` [m] of the pose and ``J (6, dof, M)``.
        """
        if self._mimic is not None:
            src, mul, off = self._mimic
            qt = torch.addcmul(off.to(qt.dtype), qt[src], mul.to(qt.dtype))  # (n_chain, M)
        P = aligned_frames(self._C[qt.dtype], qt, self.revolute, self._all_revolute)
        n, M = qt.shape
        z, o = P[:n, 2], P[:n, 3]  # (n, 3, M)
        w = (P[n, 3] - o).unbind(1)  # end point relative to each joint origin
        zs = z.unbind(1)
        J = qt.new_empty(6, n, M)
        rows = J.unbind(0)
        for k in range(3):  # v = z x w, written out
            i, j = (k + 1) % 3, (k + 2) % 3
            torch.mul(zs[i], w[j], out=rows[k]).addcmul_(zs[j], w[i], value=-1)
        J[3:] = z.transpose(0, 1)
        if not self._all_revolute:
            rev = self.revolute[:, None]
            J[:3] = torch.where(rev, J[:3], J[3:])
            J[3:] = torch.where(rev, J[3:], 0.0)
        if self._mimic is not None:
            src, mul, _ = self._mimic
            J = J.new_zeros(6, self.dof, M).index_add_(1, src, J * mul.to(J.dtype))
        return P[n, :3].transpose(0, 1), P[n, 3], J

    def __call__(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Pose ``(M, 4, 4)`` and Jacobian ``(M, 6, dof)`` at ``q (M, dof)`` [rad or m]."""
        R, p, J = self.soa(q.detach().to(torch.float64).T)
        M = q.shape[0]
        T = torch.zeros(M, 4, 4, dtype=torch.float64, device=q.device)
        T[:, :3, :3] = R.permute(2, 0, 1)
        T[:, :3, 3] = p.T
        T[:, 3, 3] = 1.0
        return T, J.permute(2, 0, 1)


# Robot -> (the chain terms a kernel was made from, that kernel): ChainKernel.of's memo.
_OWN: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

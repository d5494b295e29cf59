"""Gravity torques and their joint derivative without autograd, batch last.

:meth:`Robot.gravity_torques` is differentiable (batch-first 4x4 frames, every step
autograd). Where only values are needed (the compliance fixed point of every fit, the
identification Jacobian) this evaluates the same statics in batch-last layout (a
rotation ``(3, 3, M)``, so each product is a few fused multiply-adds over contiguous
memory) and gives ``dg/dq`` in closed form, no forward-mode pass per joint:

- ``tau_i = z_i . (g x a_i)`` (revolute) or ``-m_i (z_i . g)`` (prismatic), where
  ``m_i`` is the mass chain joint ``i`` carries and ``a_i = sum_k m_k (c_k - o_i)``
  its first moment about the joint's origin ``o_i`` (axis ``z_i``, centres ``c_k``).
- Turning revolute joint ``j`` turns everything after it about ``z_j``: for
  ``j <= i`` the axis and moment of joint ``i`` turn together, ``d tau_i / dq_j =
  g . (z_j x (a_i x z_i))``; for ``j > i`` only the moment past ``j`` turns,
  ``d a_i = z_j x a_j``. Sliding prismatic joint ``j > i`` moves its mass along
  ``z_j``, ``d a_i = m_j z_j``; a prismatic joint's torque changes only as revolute
  joints before it turn its axis.

Chains with off-chain bodies (a gripper's fingers on their own joints) keep the
differentiable path. Oracle: ``tests/test_statics_mounting.py`` (pinocchio's RNEA and
autodiff of :meth:`Robot.gravity_torques`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.errors import ShapeError
from hybrid_pk.geometry.batch_last import compose, rotate
from hybrid_pk.geometry.shapes import broadcast_shapes
from hybrid_pk.robot.chain import ChainTerms, batch_last_terms, local_batch_last, plain_inputs

__all__ = ["gravity_values", "statics_batch_last"]


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """``a x b`` over the first dimension (3), any trailing shape (broadcast)."""
    return torch.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _loads(terms: ChainTerms, qt: Tensor, revolute: Tensor, mass: Tensor, com: Tensor):
    """Axes ``z (3, n, M)``, origins ``o (3, n, M)``, first moments ``m_k c_k (3, n, M)``
    of the segments and the end-link origin ``(3, M)``, root frame, at ``qt (n, M)``."""
    n, M = qt.shape
    batch = (M,) if terms.M0.dim() > 3 else ()
    C = batch_last_terms(terms, batch)
    R_loc, t_loc = local_batch_last(C, qt, revolute, bool(revolute.all()))
    Rs, ps = [R_loc[:, :, 0]], [t_loc[:, 0].expand(3, M)]
    for i in range(1, n):  # the chain's frames; the loads of all joints at once below
        ps.append(ps[-1] + rotate(Rs[-1], t_loc[:, i]))
        Rs.append(compose(Rs[-1], R_loc[:, :, i]))
    R, o = torch.stack(Rs, 2), torch.stack(ps, 1)  # (3, 3, n, M), (3, n, M)
    z = (R * C.axis[None]).sum(1)
    mc = mass[:, None] * (o + (R * com.T[None, :, :, None]).sum(1))
    return z, o, mc, ps[-1] + rotate(Rs[-1], C.t_tip)


def statics_batch_last(
    terms: ChainTerms,
    q_chain: Tensor,
    revolute: Tensor,
    mass: Tensor,
    com: Tensor,
    payload: float | Tensor,
    gravity: Tensor,
    derivative: bool = False,
) -> tuple[Tensor, Tensor | None]:
    """Holding torques of the chain joints and, on request, their derivative.

    Args:
        terms: the chain's constants (:meth:`Robot.chain_terms`, tip not folded),
            shared or per sample.
        q_chain: ``(M, n)`` chain joint values [rad or m].
        revolute: ``(n,)`` bool; ``mass (n,)`` [kg] and ``com (n, 3)`` [m] of the segment
            after each joint (in its frame).
        payload: [kg] at the end-link origin, float or ``(M,)``.
        gravity: ``(3,)`` or ``(M, 3)`` [m/s^2], root frame.

    Returns:
        ``tau (M, n)`` [Nm or N] and ``dtau/dq (M, n, n)`` (None unless ``derivative``).
    """
    qt = q_chain.T
    n = qt.shape[0]
    dt = qt.dtype
    z, o, mc, p_end = _loads(terms, qt, revolute, mass.to(dt), com.to(dt))
    pay = torch.as_tensor(payload, dtype=dt).reshape(-1)  # (1,) or (M,)
    g = gravity.to(dt).reshape(-1, 3).T[:, None, :]  # (3, 1, 1 or M)
    mass_out = mass.to(dt).flip(0).cumsum(0).flip(0)[:, None] + pay  # (n, 1 or M)
    arm = mc.flip(1).cumsum(1).flip(1) + pay * p_end[:, None, :] - mass_out * o  # (3, n, M)
    rev = revolute[:, None]
    tau = torch.where(rev, _dot(z, _cross(g, arm)), -mass_out * _dot(z, g))  # (n, M)
    if not derivative:
        return tau.T, None
    # G[i, j] = d tau_i / d q_j, (n, n, M); j indexes the last-but-one axis.
    zi, zj = z[:, :, None], z[:, None, :]
    before = _dot(g, _cross(zj, _cross(arm[:, :, None], zi)))  # j <= i, revolute i and j
    moved = torch.where(rev, _cross(z, arm), mass_out * z)  # d a_i per unit q_j (j > i)
    after = _dot(g, _cross(moved[:, None, :], zi))  # j > i, revolute i
    pri_i = -mass_out[:, None] * _dot(_cross(zj, zi), g)  # prismatic i, revolute j <= i
    lower = torch.ones(n, n, dtype=torch.bool).tril()[..., None]  # j <= i
    rev_i, rev_j = revolute[:, None, None], revolute[None, :, None]
    G = torch.where(
        rev_i,
        torch.where(lower, torch.where(rev_j, before, 0.0), after),
        torch.where(lower & rev_j, pri_i, 0.0),
    )
    return tau.T, G.permute(2, 0, 1)


def gravity_values(robot, q, payload, gravity, params=None, derivative: bool = False):
    """``(tau (*B, dof), dtau/dq (*B, dof, dof) or None)`` of ``robot`` (a
    :class:`~hybrid_pk.robot.Robot`) by :func:`statics_batch_last`, or None where that
    path does not apply: derivatives requested through the inputs (autograd, forward
    mode, torch.func), or off-chain bodies."""
    if isinstance(payload, Tensor) and isinstance(q, Tensor):  # both paths: said once here
        try:
            broadcast_shapes(payload.shape, q.shape[:-1])
        except RuntimeError:
            raise ShapeError(
                f"payload must be a float or (*B,) [kg] for q of batch {tuple(q.shape[:-1])}, "
                f"found {tuple(payload.shape)}"
            ) from None
    if robot.spec.branches or not isinstance(q, Tensor):
        return None
    own = (robot.origin_xyz, robot.origin_rotvec, robot.axis) if params is None else params
    extra = [t for t in (payload, gravity) if isinstance(t, Tensor)]
    if not plain_inputs(q, *own, *extra):
        return None
    dt = q.dtype
    g = torch.as_tensor(gravity, dtype=dt)
    if g.shape[-1:] != (3,):
        return None  # the differentiable path says what is wrong
    pay = torch.as_tensor(payload, dtype=dt)
    terms = robot.chain_terms(dt, params)
    per_sample = terms.M0.dim() > 3
    batch = broadcast_shapes(
        q.shape[:-1], g.shape[:-1], pay.shape, terms.tip.shape[:-2] if per_sample else ()
    )
    n = robot.chain_dof
    qc = robot.chain_q(q).expand(*batch, n).reshape(-1, n)
    if per_sample:
        core = (3, 3, 3, 2, 2)  # dimensions of M0, M1, M2, tip, axis after the batch
        terms = ChainTerms(
            *(
                t.expand(*batch, *t.shape[-k:]).reshape(-1, *t.shape[-k:])
                for t, k in zip(terms, core, strict=True)
            )
        )
    g = g.expand(*batch, 3).reshape(-1, 3) if g.dim() > 1 else g
    pay = pay.expand(batch).reshape(-1) if pay.dim() > 0 else pay
    tau, G = statics_batch_last(
        terms,
        qc,
        robot.chain_revolute,
        robot.segment_mass[1:],
        robot.segment_com[1:],
        pay,
        g,
        derivative,
    )
    if robot.has_mimic:
        A = robot.coupling_matrix.to(dt)
        tau = tau @ A
        G = None if G is None else A.T @ G @ A
    tau = tau.reshape(*batch, robot.dof)
    return tau, None if G is None else G.reshape(*batch, robot.dof, robot.dof)

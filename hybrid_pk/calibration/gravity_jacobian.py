"""The gravity torques' joint derivative ``dg/dq`` of the compliance's feedback, kept per
data set and reused while the true joint values stay within :data:`GRAVITY_REUSE_RAD`
of where it was computed (:mod:`~hybrid_pk.calibration.structured_jacobian`)."""

from __future__ import annotations

import weakref

import torch
from torch import Tensor

from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.robot.statics import gravity_values

__all__ = ["GRAVITY_REUSE_RAD", "compliance_feedback", "gravity_jacobian"]

# dg/dq kept for reuse: id(data q) -> (weakref to it, q_star (N, dof), G (N, dof, dof),
# valid (N,) bool), whatever the chunking of the problem that asks.
_GRAVITY_JACOBIANS: dict[int, tuple] = {}
# Reuse dg/dq while the true joint values moved less than this [rad] (max over rows).
GRAVITY_REUSE_RAD = 1e-4


def _detached(x):
    """``x`` without derivatives where it is a tensor (a payload, a gravity vector)."""
    return x.detach() if isinstance(x, Tensor) else x


def gravity_jacobian(robot, q_star: Tensor, payload, params, key, gravity):
    """``(g, dg/dq (n, dof, dof))`` at ``q_star``: ``dg/dq`` reused from an earlier call
    where valid, the torques ``g (n, dof)`` where they came with it (else None)."""
    store = None
    if key is not None:
        data_q, start, stop = key
        for k in [k for k, v in _GRAVITY_JACOBIANS.items() if v[0]() is None]:
            del _GRAVITY_JACOBIANS[k]  # data sets that no longer exist
        store = _GRAVITY_JACOBIANS.get(id(data_q))
        if store is None or store[0]() is not data_q or store[1].shape[-1] != q_star.shape[-1]:
            n, dof = data_q.shape[0], q_star.shape[-1]
            store = (
                weakref.ref(data_q),
                torch.zeros(n, dof, dtype=q_star.dtype),
                torch.zeros(n, dof, dof, dtype=q_star.dtype),
                torch.zeros(n, dtype=torch.bool),
            )
            _GRAVITY_JACOBIANS[id(data_q)] = store
        _, q_kept, G_kept, valid = store
        rows = slice(start, stop)
        if bool(valid[rows].all()):
            if float((q_kept[rows] - q_star).abs().max()) <= GRAVITY_REUSE_RAD:
                return None, G_kept[rows]

    tau = None
    # Values only (dg/dq enters the Jacobian as a constant): a parameter that requires
    # grad (the joint axes) sent the closed form to forward mode, ~10x slower.
    plain = None if params is None else type(params)(*(t.detach() for t in params))
    closed = gravity_values(
        robot, q_star.detach(), _detached(payload), _detached(gravity), plain, derivative=True
    )
    if closed is not None:
        tau, G = closed
    else:  # off-chain bodies: forward mode through the differentiable statics

        def grav(d: Tensor) -> Tensor:
            tau = robot.gravity_torques(q_star + d, payload=payload, gravity=gravity, params=params)
            return tau.reshape(-1)

        dof = q_star.shape[-1]
        G = jacobian(grav, torch.zeros(dof, dtype=q_star.dtype))[1].reshape(-1, dof, dof)
    if store is not None:
        q_kept[rows], G_kept[rows], valid[rows] = q_star, G, True
    return tau, G


def compliance_feedback(c, robot, q_star: Tensor, payload, params, key, gravity):
    """``(g, M)``: the compliance's feedback ``M = I + C dg/dq (n, dof, dof)`` at
    ``q_star`` (``q* = q_kin - C g(q*)  =>  M dq* = dq_kin - dC g``) and the gravity
    torques ``g (n, dof)`` where they came with ``dg/dq``; ``(None, None)`` where the
    compliances ``c (dof,)`` are None or all zero."""
    if c is None or not bool((c != 0).any()):
        return None, None
    g, G = gravity_jacobian(robot, q_star, payload, params, key, gravity)
    return g, torch.eye(q_star.shape[-1], dtype=q_star.dtype) + c.to(q_star.dtype)[:, None] * G

"""The arithmetic of one batched Levenberg–Marquardt iteration, batch-last.

Every function here works on ``A`` independent problems at once, each quantity a
tensor whose last dimension is ``A`` (``q (n, A)``, ``J (m, n, A)``, residual ``(m,
A)``), and is written for few tensor operations: on a CPU each costs a few
microseconds of dispatch whatever its size, which is most of an iteration once only a
few hundred problems are left (see ``bench/ik.py``).

- :func:`pose_residual`: ``[p_t - p, w log(R_t R^T)]``, its cost and errors;
- :func:`normal_equations`: ``[J^T J | J^T e]`` into one ``(n, n + 1, A)`` block;
- :func:`eliminate`: the damped system solved by Gaussian elimination without
  pivoting (the same as a Cholesky factorisation for a symmetric positive definite
  matrix, and as stable), rows normalised in place, then back substitution; a
  non-positive pivot marks the problem's step as failed instead of raising; for a
  few problems LAPACK's batched Cholesky instead (one call per matrix, but a few calls
  in all where the elimination makes ~65).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.geometry import axis_near_pi

__all__ = ["eliminate", "normal_equations", "pose_residual", "target_reach"]

# Rows of a flattened (3, 3) E = R_t R^T: E21, E02, E10 | E12, E20, E01 | diagonal.
_VEE_TRACE = {torch.device("cpu"): torch.tensor([7, 2, 3, 5, 6, 1, 0, 4, 8])}
# 2 cos(angle) below which the axis is taken from the symmetric part of E: the closed
# form's relative error grows like eps / sin(angle), 1e-14 at this angle (179.2 deg).
_NEAR_PI = -2 * 0.9999


def _vee_trace(device: torch.device) -> Tensor:
    if device not in _VEE_TRACE:
        _VEE_TRACE[device] = _VEE_TRACE[torch.device("cpu")].to(device)
    return _VEE_TRACE[device]


def target_reach(T_target: Tensor) -> float:
    """``1 +`` the largest distance [m] of the targets ``(P, 4, 4)`` from the origin (1
    for none): the scale of the round-off of their residuals. From a contiguous copy: a
    norm over the rows of the strided view ``T[:, :3, 3]`` takes ~10x as long."""
    p = T_target[:, :3, 3].contiguous()
    return 1.0 + float(p.norm(dim=-1).max()) if len(p) else 1.0


def pose_residual(
    R: Tensor, p: Tensor, R_t: Tensor, p_t: Tensor, weight: float, position_only: bool
) -> tuple[Tensor, Tensor | None, Tensor, Tensor, Tensor]:
    """Residual of poses ``R (3, 3, A)``, ``p (3, A)`` against targets ``R_t``, ``p_t``.

    Returns:
        ``dp (3, A)`` [m], weighted rotation residual ``(3, A)`` (None when position
        only) = ``weight`` times the rotation vector of ``R_t R^T``, and, each ``(1,
        A)``: ``cost = |dp|^2 + (weight angle)^2``, position error [m], angle [rad].
    """
    dp = p_t - p
    pos2 = (dp * dp).sum(0, keepdim=True)
    pos = pos2.sqrt()
    if position_only:
        return dp, None, pos2, pos, torch.zeros_like(pos)
    E = (R_t[:, None] * R[None]).sum(2)  # R_t R^T, (3, 3, A)
    sel = E.reshape(9, -1).index_select(0, _vee_trace(E.device))
    vee = sel[:3] - sel[3:6]  # 2 sin(angle) axis
    two_c = sel[6:].sum(0, keepdim=True) - 1
    two_s = (vee * vee).sum(0, keepdim=True).sqrt()
    angle = torch.atan2(two_s, two_c)
    w_angle = angle * weight
    # angle / (2 sin(angle)), accurate down to sin = 0 (atan2 keeps the ratio's digits)
    w = vee * (w_angle / two_s.clamp_min(torch.finfo(E.dtype).tiny))
    if float(two_c.amin()) < _NEAR_PI:  # one reduction and one sync in the usual case
        far = (two_c[0] < _NEAR_PI).nonzero()[:, 0]
        # so3_log's branch there, on these few columns (batch-first views)
        E_far, vee_far = E.index_select(2, far).permute(2, 0, 1), vee.index_select(1, far).T
        axis = axis_near_pi(E_far, vee_far, two_c.index_select(1, far).T * 0.5).T
        w.index_copy_(1, far, axis * w_angle.index_select(1, far))
    return dp, w, pos2 + w_angle * w_angle, pos, angle


# Problems up to which the normal equations are one broadcast product (three tensor
# operations and an (m, n, n + 1, A) temporary) instead of m row updates: below it the
# dispatch of the updates dominates, above it the temporary's memory traffic (one
# thread, n = m = 6: equal at ~400 problems in float64, ~600 in float32).
_BROADCAST_MAX = 256


def normal_equations(J: Tensor, e: Tensor) -> Tensor:
    """``G (n, n + 1, A)`` = ``[J^T J | J^T e]`` of ``J (m, n, A)`` and ``e (m, A)``."""
    m, n, A = J.shape
    if A <= _BROADCAST_MAX:
        Je = torch.cat([J, e[:, None]], 1)  # (m, n + 1, A)
        return (J[:, :, None] * Je[:, None]).sum(0)
    G = J.new_empty(n, n + 1, A)
    H = G[:, :n]
    cols, rows = J[:, :, None].unbind(0), J[:, None].unbind(0)
    torch.mul(cols[0], rows[0], out=H)
    for r in range(1, m):
        H.addcmul_(cols[r], rows[r])
    torch.sum(J * e[:, None], 0, out=G[:, n])
    return G


# Problems up to which the batched Cholesky is cheaper than the elimination: it costs
# ~45 us plus a LAPACK call per matrix (~0.45 us at n = 6), the elimination ~110 us
# (~65 tensor calls) whatever the batch (one quiet thread, 10 to 400 problems: equal
# between 100 and 200).
_CHOLESKY_MAX = 128


def _cholesky(G: Tensor) -> tuple[Tensor, Tensor]:
    n = G.shape[0]
    L, info = torch.linalg.cholesky_ex(G[:, :n].permute(2, 0, 1))
    x = torch.cholesky_solve(G[:, n].T[..., None], L)[..., 0].T
    return x, (info == 0) & torch.isfinite(x).all(0)


def eliminate(G: Tensor) -> tuple[Tensor, Tensor]:
    """Solve ``G[:, :n] x = G[:, n]`` for every problem (``G`` is overwritten).

    The matrix must be symmetric positive definite (damped normal equations) for the
    solution to be trusted: elimination without pivoting.

    Returns:
        ``x (n, A)`` and ``ok (A,)``: every pivot positive (a NaN pivot is not), and
        for the Cholesky route ``x`` finite.
    """
    n = G.shape[0]
    if G.shape[-1] <= _CHOLESKY_MAX:
        return _cholesky(G)
    rows = G.unbind(0)
    for k in range(n):
        tail = rows[k][k + 1 :]  # row k right of the pivot, right-hand side included
        tail.div_(rows[k][k])
        if k < n - 1:
            G[k + 1 :, k + 1 :].addcmul_(G[k + 1 :, k, None], tail[None], value=-1)
    x = G[:, n].clone()
    for j in range(n - 1, 0, -1):
        x[:j].addcmul_(G[:j, j], x[j], value=-1)
    ok = G.view(-1, G.shape[-1])[:: n + 2].amin(0) > 0  # every pivot
    return x, ok

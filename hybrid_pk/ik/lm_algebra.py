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
  non-positive pivot marks the problem's step as failed instead of raising.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.geometry import so3_log

__all__ = ["eliminate", "normal_equations", "pose_residual"]

# Rows of a flattened (3, 3) E = R_t R^T: E21, E02, E10 | E12, E20, E01 | diagonal.
_VEE_TRACE = {torch.device("cpu"): torch.tensor([7, 2, 3, 5, 6, 1, 0, 4, 8])}
# 2 cos(angle) below which the axis is taken from the symmetric part of E: the closed
# form's relative error grows like eps / sin(angle), 1e-14 at this angle (179.2 deg).
_NEAR_PI = -2 * 0.9999


def _vee_trace(device: torch.device) -> Tensor:
    if device not in _VEE_TRACE:
        _VEE_TRACE[device] = _VEE_TRACE[torch.device("cpu")].to(device)
    return _VEE_TRACE[device]


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
    rt = R_t.transpose(0, 1)[:, :, None].unbind(0)  # columns of R_t, (3, 1, A)
    rr = R.transpose(0, 1)[:, None].unbind(0)  # columns of R as rows, (1, 3, A)
    E = torch.mul(rt[0], rr[0]).addcmul_(rt[1], rr[1]).addcmul_(rt[2], rr[2])  # R_t R^T
    sel = E.reshape(9, -1).index_select(0, _vee_trace(E.device))
    vee = sel[:3] - sel[3:6]  # 2 sin(angle) axis
    two_c = sel[6:].sum(0, keepdim=True) - 1
    two_s = (vee * vee).sum(0, keepdim=True).sqrt()
    angle = torch.atan2(two_s, two_c)
    w_angle = angle * weight
    # angle / (2 sin(angle)), accurate down to sin = 0 (atan2 keeps the ratio's digits)
    w = vee * (w_angle / two_s.clamp_min(torch.finfo(E.dtype).tiny))
    far = two_c[0] < _NEAR_PI
    if bool(far.any()):
        w[:, far] = weight * so3_log(E[:, :, far].permute(2, 0, 1)).T
    return dp, w, pos2 + w_angle * w_angle, pos, angle


def normal_equations(J: Tensor, e: Tensor) -> Tensor:
    """``G (n, n + 1, A)`` = ``[J^T J | J^T e]`` of ``J (m, n, A)`` and ``e (m, A)``."""
    m, n, A = J.shape
    G = J.new_empty(n, n + 1, A)
    H = G[:, :n]
    cols, rows = J[:, :, None].unbind(0), J[:, None].unbind(0)
    torch.mul(cols[0], rows[0], out=H)
    for r in range(1, m):
        H.addcmul_(cols[r], rows[r])
    torch.sum(J * e[:, None], 0, out=G[:, n])
    return G


def eliminate(G: Tensor) -> tuple[Tensor, Tensor]:
    """Solve ``G[:, :n] x = G[:, n]`` for every problem (``G`` is overwritten).

    The matrix must be symmetric positive definite (damped normal equations) for the
    solution to be trusted: elimination without pivoting.

    Returns:
        ``x (n, A)`` and ``ok (A,)``: every pivot positive (a NaN pivot is not).
    """
    n = G.shape[0]
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

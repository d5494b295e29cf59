"""Distinct IK solutions, as contract section 6 defines them.

Two solutions of a target are the same when every revolute joint agrees within
``1e-3`` rad modulo ``2 pi`` and every prismatic joint within ``1e-6`` m. "The same"
is not transitive (a chain of close solutions), so the kept set depends on an order:
candidates are visited best first (smallest error), and one is kept unless it is the
same as a solution already kept.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["PRISMATIC_TOL", "REVOLUTE_TOL", "distinct_mask", "joint_difference", "same_solution"]

REVOLUTE_TOL = 1e-3  # [rad]
PRISMATIC_TOL = 1e-6  # [m]
_TWO_PI = 2 * math.pi
_CHUNK = 128  # targets per pairwise comparison block (memory ~ chunk * K^2 * dof)


def joint_difference(q_a: Tensor, q_b: Tensor, revolute: Tensor) -> Tensor:
    """``q_a - q_b`` with revolute joints wrapped to ``[-pi, pi]``; shapes broadcast.

    Args:
        q_a: ``(*B, dof)`` joint values [rad or m].
        q_b: ``(*B, dof)``.
        revolute: ``(dof,)`` bool.
    """
    d = q_a - q_b
    wrapped = d - _TWO_PI * torch.round(d / _TWO_PI)  # cheaper than remainder
    return torch.where(revolute, wrapped, d)


def same_solution(
    q_a: Tensor,
    q_b: Tensor,
    revolute: Tensor,
    revolute_tol: float = REVOLUTE_TOL,
    prismatic_tol: float = PRISMATIC_TOL,
) -> Tensor:
    """``(*B,)`` bool: whether two joint configurations are the same IK solution."""
    d = joint_difference(q_a, q_b, revolute).abs()
    tol = torch.where(revolute, revolute_tol, prismatic_tol).to(d.dtype)
    return (d <= tol).all(-1)


def distinct_mask(
    q: Tensor,
    candidate: Tensor,
    score: Tensor,
    revolute: Tensor,
    revolute_tol: float = REVOLUTE_TOL,
    prismatic_tol: float = PRISMATIC_TOL,
) -> Tensor:
    """Which candidates to keep so that every target's kept solutions are distinct.

    Args:
        q: ``(N, K, dof)`` candidate solutions of ``N`` targets [rad or m].
        candidate: ``(N, K)`` bool, which entries are candidates at all.
        score: ``(N, K)`` lower is better (e.g. pose error); decides which of several
            equal solutions is kept.
        revolute: ``(dof,)`` bool.

    Returns:
        ``(N, K)`` bool: a subset of ``candidate`` with no two entries of one target the
        same solution, and every dropped candidate the same as a kept one.
    """
    keep = torch.zeros_like(candidate)
    for start in range(0, q.shape[0], _CHUNK):
        sl = slice(start, start + _CHUNK)
        keep[sl] = _distinct_block(
            q[sl], candidate[sl], score[sl], revolute, revolute_tol, prismatic_tol
        )
    return keep


def _distinct_block(q, candidate, score, revolute, revolute_tol, prismatic_tol) -> Tensor:
    n = q.shape[0]
    # Best first; non-candidates last.
    key = torch.where(candidate, score, torch.inf)
    order = torch.argsort(key, dim=1, stable=True)
    qs = torch.take_along_dim(q, order[..., None], dim=1)
    left = torch.take_along_dim(candidate, order, dim=1)
    # The greedy visit of the module docstring, one kept solution per target per round:
    # the first candidate left is kept (every one before it was the same as one kept),
    # then every candidate the same as it leaves. Rounds: the most distinct solutions of
    # one target, not the number of candidates.
    kept = torch.zeros_like(left)
    rows = torch.arange(n, device=q.device)
    while bool(left.any()):
        first = left.to(torch.uint8).argmax(1)  # the first True of each row
        has = left[rows, first]
        kept[rows[has], first[has]] = True
        rep = qs[rows, first]
        left &= ~same_solution(qs, rep[:, None], revolute, revolute_tol, prismatic_tol)
    out = torch.zeros_like(candidate)
    out.scatter_(1, order, kept)
    return out

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

__all__ = [
    "PRISMATIC_TOL",
    "REVOLUTE_TOL",
    "cell_representatives",
    "distinct_mask",
    "joint_difference",
    "same_solution",
]

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
    c = int(candidate.sum(1).max()) if candidate.numel() else 0  # non-candidates: never kept
    order = order[:, :c]
    dof = q.shape[-1]
    # joints first, (dof, n, c): a round's test over the joints reduces over the leading
    # dimension, several times cheaper than over a trailing one of ~6
    qs = torch.take_along_dim(q, order[..., None], dim=1).permute(2, 0, 1).contiguous()
    left = torch.take_along_dim(candidate, order, dim=1)
    # The greedy visit of the module docstring, one kept solution per target per round:
    # the first candidate left is kept (every one before it was the same as one kept),
    # then every candidate the same as it leaves. Rounds: the most distinct solutions of
    # one target, not the number of candidates. Wrapping and tolerances of the joints are
    # set up once (period 2 pi or 0: a prismatic difference is left as it is).
    rev = revolute.to(q.device)
    period = (rev.to(q.dtype) * _TWO_PI)[:, None, None]
    tol = torch.where(rev, revolute_tol, prismatic_tol).to(q.dtype)[:, None, None]
    kept = torch.zeros(left.shape, dtype=torch.uint8, device=q.device)
    while bool(left.any()):
        first = left.to(torch.uint8).argmax(1, keepdim=True)  # (n, 1)
        has = left.gather(1, first).to(torch.uint8)
        kept.scatter_add_(1, first, has)  # adds 0 where a row is done
        d = qs - qs.gather(2, first.expand(dof, n, 1))
        d -= period * torch.round(d / _TWO_PI)
        left &= ~(d.abs() <= tol).all(0)
    kept = kept.bool()
    out = torch.zeros_like(candidate)
    out.scatter_(1, order, kept)
    return out


def cell_representatives(
    q: Tensor,
    group: Tensor,
    candidate: Tensor,
    score: Tensor,
    revolute: Tensor,
    revolute_cell: float,
    prismatic_cell: float,
) -> Tensor:
    """A cheap merge of near-equal candidates, without the greedy visit's rounds.

    Joint space is cut into cells (revolute joints taken modulo ``2 pi``); of the
    candidates of one group (target) in one cell, the lowest score is kept. Two merged
    candidates differ by less than a cell in every joint; two equal ones on either side
    of a cell border are both kept.

    Args:
        q: ``(P, dof)`` [rad or m].
        group: ``(P,)`` long, e.g. the target of each candidate.
        candidate: ``(P,)`` bool.
        score: ``(P,)`` lower is better.
        revolute: ``(dof,)`` bool.
        revolute_cell: [rad] cell width of revolute joints.
        prismatic_cell: [m] cell width of prismatic joints.

    Returns:
        ``(P,)`` long: for each candidate the index of the one kept for its cell
        (itself when kept; of equal scores the first), -1 for the others.
    """
    idx = candidate.nonzero()[:, 0]
    qc = q.index_select(0, idx)
    rev = revolute.to(qc.device)
    width = torch.where(rev, revolute_cell, prismatic_cell).to(qc.dtype)
    cell = torch.floor(torch.where(rev, torch.remainder(qc, _TWO_PI), qc) / width).long()
    cell = torch.cat([group.index_select(0, idx)[:, None], cell], 1)
    # One int64 per cell (a wrapping hash, far cheaper than unique rows); a member
    # whose cell differs from its representative's (a collision) is kept.
    _, which = torch.unique(cell @ _hash_weights(cell.shape[1], cell.device), return_inverse=True)
    order = torch.argsort(score.index_select(0, idx), stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(order), device=order.device)
    best = rank.new_full((len(order),), len(order)).scatter_reduce_(0, which, rank, "amin")
    rep = order.index_select(0, best.index_select(0, which))
    me = torch.arange(len(rep), device=rep.device)
    rep = torch.where((cell == cell[rep]).all(1), rep, me)  # a collision stands for itself
    out = torch.full_like(candidate, -1, dtype=torch.long)
    out[idx] = idx.index_select(0, rep)
    return out


def _hash_weights(k: int, device: torch.device) -> Tensor:
    """``(k,)`` int64 odd multipliers (fixed, from a seeded generator) of the cell hash."""
    gen = torch.Generator().manual_seed(k)
    w = torch.randint(-(2**62), 2**62, (k,), generator=gen, dtype=torch.int64)
    return (w | 1).to(device)

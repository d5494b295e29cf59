"""The batched LM in two precisions: float32 to near a solution, float64 to finish.

Most of an IK call is spent far from any solution (random seeds wander for several
iterations, many never arrive); there float32 is as good as float64 and costs about
half (half the memory traffic, twice the SIMD width). So where the model has the chain
kernel (``IKModel.batch_last``, which evaluates in either precision) the problems are
first solved in float32 down to a handover tolerance a hundred times float32's
resolution, and those that reach it are finished in float64 with the caller's
tolerances (two or three Gauss-Newton steps); the others are returned as the float32
phase left them (they had stalled, as they would have in float64). Many starts of one
target arrive at the same solution: given ``merge`` cells, only the best of each
target's arrivals in one cell of joint space is finished in float64 (the others are
returned as they arrived, with the index of the finished one: the solver checks
them only where that one fails its check, since the reduction to distinct solutions
would drop them in favour of it, the same solution). Once only a few problems are still
iterating in float32 (``_SWITCH``), float32 saves nothing (an iteration then costs its
dispatch whatever the precision): they go on in float64 in the same batch as the
arrived ones, so that the slow last problems and the finishing steps share iterations.
Every problem goes on with the damping it had (``LMOutput.damping``): restarting it at
``damping_init`` cost the slow ones three or four iterations to bring it down again.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from hybrid_pk.ik.batched_lm import LMOutput, LMSettings, batched_levenberg_marquardt
from hybrid_pk.ik.dedup import cell_representatives
from hybrid_pk.ik.lm_algebra import target_reach

__all__ = ["solve_two_precisions"]

# Handover: this many times float32's resolution (of 1 rad, of the target's distance
# from the origin), so that float32 rounding never decides whether a problem arrived.
_MARGIN = 100.0
# Problems below which float32 saves nothing: an iteration then costs its ~150 tensor
# operations' dispatch whatever the precision (one thread: f64/f32 time 1.0 at 8
# problems, 1.1 at 128, 2 at 3,200), so the last problems still iterating go on in
# float64 together with the arrived ones instead of after them.
_SWITCH = 128


def solve_two_precisions(
    evaluate,
    q0: Tensor,
    rows: Tensor,
    T_target: Tensor,
    lower,
    upper,
    s: LMSettings,
    revolute,
    merge: tuple[float, float] | None = None,
) -> tuple[LMOutput, Tensor | None]:
    """:func:`batched_levenberg_marquardt` (same arguments, ``evaluate`` accepting
    float32 and float64), float32 first and float64 from the handover tolerance.

    ``merge``: ``(revolute, prismatic)`` cell widths [rad, m] of
    :func:`~hybrid_pk.ik.dedup.cell_representatives` (needs ``revolute``); of a
    target's arrivals in one cell only the best is finished.

    Returns:
        The result and ``merged (P,)`` long: for an arrival not finished, the problem
        finished for its cell (whose result stands for it), else -1; None without
        ``merge``."""
    eps = torch.finfo(torch.float32).eps * _MARGIN
    reach = target_reach(T_target)
    loose_p, loose_r = max(eps * reach, s.accept_position), max(eps, s.accept_rotation)
    coarse = replace(
        s,
        accept_position=loose_p,
        accept_rotation=loose_r,
        keep_position=max(loose_p, s.keep_position),
        keep_rotation=max(loose_r, s.keep_rotation),
        polish_iterations=0,
        # no hand-over to the polish from float32 (measured: a few near-singular branches
        # fewer); problems crawling there go on in float64 and are handed over from it
        handoff_position=None,
        handoff_rotation=None,
    )
    f32 = torch.float32
    lo, hi = lower.to(f32), upper.to(f32)
    first = batched_levenberg_marquardt(
        evaluate, q0.to(f32), rows, T_target.to(f32), lo, hi, coarse, revolute, _SWITCH
    )
    q = first.q.to(q0.dtype)
    pos, rot = first.position_error.to(q0.dtype), first.rotation_error.to(q0.dtype)
    it = first.iterations.clone()
    arrived = (first.position_error <= loose_p) & (first.rotation_error <= loose_r)
    merged = None
    if merge is not None and revolute is not None and bool(arrived.any()):
        score = first.position_error + s.rotation_weight * first.rotation_error
        rep = cell_representatives(first.q, rows, arrived, score, revolute, *merge)
        me = torch.arange(len(rep), device=rep.device)
        arrived = rep == me
        merged = torch.where(arrived, -1, rep)
    if first.active is not None:
        arrived |= first.active
    go = arrived.nonzero()[:, 0]
    spent = int(first.iterations.max()) if len(go) else 0
    left = max(s.stall_window, s.max_iterations - spent)
    bounds = [b if b.ndim == 1 else b.index_select(0, go) for b in (lower, upper)]
    damping = first.damping.to(q0.dtype)
    fine = batched_levenberg_marquardt(
        evaluate,
        q.index_select(0, go),
        rows.index_select(0, go),
        T_target.index_select(0, go),
        *bounds,
        replace(s, max_iterations=left),
        revolute,
        damping=damping.index_select(0, go),
    )
    q.index_copy_(0, go, fine.q)
    pos.index_copy_(0, go, fine.position_error)
    rot.index_copy_(0, go, fine.rotation_error)
    it.index_add_(0, go, fine.iterations)
    damping = damping.index_copy(0, go, fine.damping)
    return LMOutput(q, pos, rot, it, damping, first.evaluations + fine.evaluations), merged

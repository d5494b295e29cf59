"""The batched LM in two precisions: float32 to near a solution, float64 to finish.

Most of an IK call is spent far from any solution (random seeds wander for several
iterations, many never arrive); there float32 is as good as float64 and costs about
half (half the memory traffic, twice the SIMD width). So where the model has the chain
kernel (``IKModel.batch_last``, which evaluates in either precision) the problems are
first solved in float32 down to a handover tolerance a hundred times float32's
resolution, and those that reach it are finished in float64 with the caller's
tolerances (two or three Gauss-Newton steps); the others are returned as the float32
phase left them (they had stalled, as they would have in float64).
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from hybrid_pk.ik.batched_lm import LMOutput, LMSettings, batched_levenberg_marquardt

__all__ = ["solve_two_precisions"]

# Handover: this many times float32's resolution (of 1 rad, of the target's distance
# from the origin), so that float32 rounding never decides whether a problem arrived.
_MARGIN = 100.0


def solve_two_precisions(
    evaluate, q0: Tensor, rows: Tensor, T_target: Tensor, lower, upper, s: LMSettings, revolute
) -> LMOutput:
    """:func:`batched_levenberg_marquardt` (same arguments, ``evaluate`` accepting
    float32 and float64), float32 first and float64 from the handover tolerance."""
    eps = torch.finfo(torch.float32).eps * _MARGIN
    reach = 1.0 + float(T_target[:, :3, 3].norm(dim=-1).max()) if len(T_target) else 1.0
    loose_p, loose_r = max(eps * reach, s.accept_position), max(eps, s.accept_rotation)
    coarse = replace(
        s,
        accept_position=loose_p,
        accept_rotation=loose_r,
        keep_position=max(loose_p, s.keep_position),
        keep_rotation=max(loose_r, s.keep_rotation),
        polish_iterations=0,
    )
    f32 = torch.float32
    lo, hi = lower.to(f32), upper.to(f32)
    first = batched_levenberg_marquardt(
        evaluate, q0.to(f32), rows, T_target.to(f32), lo, hi, coarse, revolute
    )
    q = first.q.to(q0.dtype)
    pos, rot = first.position_error.to(q0.dtype), first.rotation_error.to(q0.dtype)
    it = first.iterations.clone()
    go = ((first.position_error <= loose_p) & (first.rotation_error <= loose_r)).nonzero()[:, 0]
    spent = int(first.iterations.max()) if len(go) else 0
    left = max(s.stall_window, s.max_iterations - spent)
    bounds = [b if b.ndim == 1 else b[go] for b in (lower, upper)]
    fine = batched_levenberg_marquardt(
        evaluate, q[go], rows[go], T_target[go], *bounds, replace(s, max_iterations=left), revolute
    )
    q[go], pos[go], rot[go] = fine.q, fine.position_error, fine.rotation_error
    it[go] += fine.iterations
    return LMOutput(q, pos, rot, it, first.evaluations + fine.evaluations)

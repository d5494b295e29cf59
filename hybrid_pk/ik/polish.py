"""Polishing verified IK solutions onto their exact branch, before deduplication.

A solution within the tolerances is pinned only to ``tol / sigma`` in joint space, with
``sigma`` [m/rad] the smallest singular value of the (weighted) Jacobian there: at the
default 1e-3 mm that is below the 1e-3 rad that tells solutions apart only where
``sigma > 1e-3`` m/rad. Near a singular configuration (a wrist axis within ~1e-4 rad of
alignment, a stretched or folded elbow, a UR10 joint at its 2 pi limit that is also
wrist_2 = 0) the solver stops anywhere in a long, curved valley of small error: two
starts of one branch stop several mrad apart (the branch listed twice) and the branch
itself may be nowhere within 1e-3 rad (missed). The damped solver cannot follow such
a curved valley quickly (every step that leaves it raises the error and is refused);
plain Gauss-Newton steps can: the first leaves the valley, the next ones come back at
the exact branch with quadratic convergence (UR10, wrist_2 2e-5 rad from 0, sigma
6e-6 m/rad: 1.4e-2 rad from the branch, then 4e-5, 2e-9, 5e-12).

So every end the solver left within the tolerances, and every end it gave up on near
one (``NEAR_FACTOR``), gets a few undamped Gauss-Newton steps in float64 (joints
clamped into the box, a joint whose box spans 2 pi wrapped), and its best iterate
(least cost, the solver's weighting) replaces it where that is better and passes the
fresh check (an end outside the tolerances only once the steps settled); one fresh
check serves both, the polished value where there is one (a polished value that fails
falls back to the end as it was, checked in turn). A solution then sits within about
``1e-14 m / sigma`` of the exact branch, and the deduplication's 1e-3 rad separates
branches wherever ``sigma`` exceeds ~1e-10 m/rad. A start in no branch's reach (a
local minimum of the error within the tolerance, at a nearly singular Jacobian) stays
as it was, or lands on a branch another start found (then the reduction drops it as
the same solution).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from hybrid_pk.ik.batched_lm import LMOutput, LMSettings
from hybrid_pk.ik.dedup import PRISMATIC_TOL, REVOLUTE_TOL
from hybrid_pk.ik.forward_model import IKModel, no_autograd, plain
from hybrid_pk.ik.lm_algebra import pose_residual, target_reach

__all__ = ["NEAR_FACTOR", "gauss_newton", "polish", "within"]

F64 = torch.float64
_TWO_PI = 2 * math.pi
# Steps per solution: from 1e-2 rad off the branch along a curved valley, out, back and
# two quadratic steps reach float64's floor (see the module docstring); two more for a
# step clamped at a joint limit. A problem stops stepping once it is at the floor or
# settled.
_STEPS = 6
# Cost floor [m^2]: (a hundred times float64's resolution at the targets' distance from
# the origin)^2; below it a step only moves round-off.
_MARGIN = 100.0
# Relative singular-value cut of the least-squares step (non-square Jacobians: position
# only, redundant arms): directions weaker than this times the strongest are round-off.
_RCOND = 1e-12
# A last step below this fraction of the distinctness tolerances (1e-3 rad, 1e-6 m) in
# every joint: the iteration settled (on a branch, or on the least-squares point of a
# target a little out of reach), far below what the reduction to distinct solutions
# resolves.
_SETTLED = 1e-3
# Unverified ends within this many times the errors from which the solver polishes
# (LMSettings.accept_*: a tenth of the tolerances by default, so 100x the tolerances;
# in the two-stage solver's first stage the final ones, not its coarse tolerances) are
# polished too, and count once settled: near a singular configuration the damped solver
# gives up in a curved valley at a few to ~100 times the tolerances, within
# Gauss-Newton's reach of the branch; further out an end is no nearer a solution than a
# seed. (UR10 / RX160 with wrist_2 / joint_5 within 1e-5..1e-3 rad of 0, 1,187
# branches: 10x the tolerances finds 18 fewer than 100x, 1000x none more.)
NEAR_FACTOR = 1000.0


def within(out: LMOutput, position: float, rotation: float, position_only: bool) -> Tensor:
    """``(P,)`` bool: ends of ``out`` within ``position`` [m] and ``rotation`` [rad]."""
    near = out.position_error <= position
    if not position_only:
        near &= out.rotation_error <= rotation
    return near


def gauss_newton(
    ikm: IKModel,
    q: Tensor,
    rows: Tensor,
    T_target: Tensor,
    lower: Tensor,
    upper: Tensor,
    settings: LMSettings,
) -> tuple[Tensor, Tensor, Tensor, Tensor, int]:
    """Undamped Gauss-Newton steps from ``q (P, dof)`` towards ``T_target (P, 4, 4)``.

    Each problem steps until it has settled (then only the others go on: most settle
    after a step or two, the few near a singular configuration take more).

    Args:
        lower, upper: ``(dof,)`` or ``(P, dof)`` box [rad or m].
        settings: rotation weight and position-only flag of the solver.

    Returns:
        The best iterate ``(P, dof)`` (least cost, the start included), its cost and the
        start's cost ``(P,)`` [m^2], ``settled (P,)`` bool (at the cost floor, or the
        last step below ``_SETTLED`` of the distinctness tolerances), and the number of
        configurations evaluated.
    """
    P, dof = q.shape
    w, pos_only = settings.rotation_weight, settings.position_only
    lo, hi = (b[:, None] if b.ndim == 1 else b.T for b in (lower, upper))
    per = (hi - lo >= _TWO_PI) & ikm.revolute[:, None]
    floor = (torch.finfo(F64).eps * _MARGIN * target_reach(T_target)) ** 2
    settle = torch.where(ikm.revolute, _SETTLED * REVOLUTE_TOL, _SETTLED * PRISMATIC_TOL)
    settle = settle.to(q)[:, None]
    best = q.T.clone(memory_format=torch.contiguous_format)  # (dof, P), never q itself
    settled = torch.zeros(P, dtype=torch.bool, device=q.device)
    # the active problems: their indices, joint values, last step, targets and boxes
    act, qt = torch.arange(P, device=q.device), best.clone()
    last = torch.full_like(best, math.inf)
    R_t, p_t = T_target[:, :3, :3].permute(1, 2, 0), T_target[:, :3, 3].T
    evaluations = 0
    for step in range(_STEPS + 1):
        # Once every step settled only the cost is needed: the pose alone where the
        # Jacobian costs more (autograd: six reverse passes; the chain kernel gives both
        # at half the cost of the pose alone).
        final = step == _STEPS or bool((last <= settle).all())
        if final and ikm.batch_last is None:
            T = ikm.pose(qt.T, rows[act]).to(F64)
            R, p, J = T[:, :3, :3].permute(1, 2, 0), T[:, :3, 3].T, None
        else:
            R, p, J = ikm.evaluate(qt, rows[act])
        evaluations += act.numel()
        dp, dr, cost, _, _ = pose_residual(R, p, R_t, p_t, w, pos_only)
        cost = cost[0]
        if step == 0:
            start_cost, best_cost = cost, cost.clone()
        else:
            better = cost < best_cost[act]  # NaN compares False
            best[:, act] = torch.where(better, qt, best[:, act])
            best_cost[act] = torch.where(better, cost, best_cost[act])
        done = (best_cost[act] <= floor) | (last <= settle).all(0)
        settled[act] = done
        if final or bool(done.all()):
            break
        go = (~done).nonzero()[:, 0]
        act, qt, last, R_t, p_t = act[go], qt[:, go], last[:, go], R_t[..., go], p_t[:, go]
        dp, J = dp[:, go], J[..., go]
        dr = None if dr is None else dr[:, go]
        lo_a, hi_a = (b if b.shape[1] == 1 else b[:, act] for b in (lo, hi))
        per_a = per if per.shape[1] == 1 else per[:, act]
        e = dp if pos_only else torch.cat([dp, dr])
        Jw = J[:3] if pos_only else torch.cat([J[:3], w * J[3:]])
        A, b = Jw.permute(2, 0, 1), e.T[..., None]  # (A, m, dof), (A, m, 1)
        if A.shape[1] == dof:
            dq, info = torch.linalg.solve_ex(A, b)
            failed = (info != 0) | ~torch.isfinite(dq).all((1, 2))  # an exactly singular J
        else:
            dq = torch.linalg.lstsq(A, b, rcond=_RCOND, driver="gelsy").solution
            failed = ~torch.isfinite(dq).all((1, 2))
        q_new = qt + torch.where(failed, 0.0, dq[..., 0].T)
        clamped = torch.minimum(torch.maximum(q_new, lo_a), hi_a)
        wrapped = lo_a + torch.remainder(q_new - lo_a, _TWO_PI)  # same pose, into the box
        q_next = torch.where(per_a & (clamped != q_new), wrapped, clamped)
        last = torch.where(failed, math.inf, (q_next - qt).abs())  # a failed step never settles
        qt = q_next
    return best.T.contiguous(), best_cost, start_cost, settled, evaluations


def polish(
    ikm: IKModel,
    out: LMOutput,
    near: Tensor,
    inside: Tensor,
    stalled: Tensor,
    rows: Tensor,
    T_target: Tensor,
    bounds: tuple[Tensor, Tensor],
    settings: LMSettings,
    check: Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]],
) -> tuple[LMOutput, Tensor, Tensor, Tensor]:
    """The ends of ``out`` near a solution polished, then checked (module docstring).

    Args:
        ikm: the model; out: the solver's result for ``P`` problems, ``rows (P,)``
            their targets, ``T_target (P, 4, 4)`` their target poses.
        near: ``(P,)`` bool, ends the solver left within (about) the tolerances: each
            is checked, polished where the polish lowered its cost (and settled, or
            ``inside``), else as it is.
        inside: ``(P,)`` bool, ends within the tolerances by the solver's own errors
            (its verified ones, but for rounding): their polish counts unsettled too.
        stalled: ``(P,)`` bool, other ends to polish: one whose polish settles and
            passes the check becomes a solution.
        bounds: ``(lower, upper)``, ``(dof,)`` or ``(P, dof)``: the solver's box.
        settings: the solver's settings.
        check: ``(q (P, dof), candidate (P,)) -> (ok, pos, ori)``, the fresh check.

    Returns:
        ``(out, ok, pos, ori)`` as :func:`~hybrid_pk.ik.solver.solve_and_check`: ``ok``
        the ends that passed the check, each ``q`` polished where its polished value
        passed it (a polished value that fails falls back to the end as the solver left
        it, checked in turn).
    """
    sel = (near | stalled).nonzero()[:, 0]
    if sel.numel() == 0:
        return (out, *check(out.q, near))
    lo, hi = (b.to(F64) if b.ndim == 1 else b.index_select(0, sel).to(F64) for b in bounds)
    with no_autograd(ikm):
        q_sel, cost, cost0, settled, evaluations = gauss_newton(
            ikm,
            out.q.index_select(0, sel).to(F64),
            rows.index_select(0, sel),
            T_target.index_select(0, sel).to(F64),
            lo,
            hi,
            settings,
        )
    q_sel, cost, cost0, settled = plain(q_sel, cost, cost0, settled)
    moved = torch.zeros_like(near)
    moved[sel] = (cost < cost0) & (inside.index_select(0, sel) | settled)
    q_new = out.q.index_copy(0, sel, q_sel.to(out.q.dtype))
    # One fresh check for all: the polished value where the polish moved an end, the
    # end itself where it did not.
    q_try = torch.where(moved[:, None], q_new, out.q)
    ok, pos, ori = check(q_try, moved | near)
    # A lower cost need not lower both errors: a polished value failing the check
    # falls back to the end as it was, which may pass.
    back = moved & ~ok & near
    if bool(back.any()):
        ok_b, pos_b, ori_b = check(out.q, back)
        ok = ok | ok_b
        pos, ori = torch.where(back, pos_b, pos), torch.where(back, ori_b, ori)
    take = moved & ok & ~back
    mm, deg = pos * 1e-3, ori.nan_to_num(0.0).deg2rad()
    polished = out._replace(
        q=torch.where(take[:, None], q_new, out.q),
        position_error=torch.where(take, mm.to(out.position_error.dtype), out.position_error),
        rotation_error=torch.where(take, deg.to(out.rotation_error.dtype), out.rotation_error),
        evaluations=out.evaluations + evaluations,
    )
    return polished, ok, pos, ori

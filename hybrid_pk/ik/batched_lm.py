"""Batched, box-constrained Levenberg–Marquardt on pose residuals.

Each of ``P`` problems (a target and a start configuration) is solved independently,
all in one batch:

- residual ``e = [p_target - p, w · log(R_target R^T)]`` [m], with ``w`` the rotation
  weight [m/rad] (position only: the first three entries);
- step ``(J^T J + lambda I) dq = J^T e`` solved by elimination (a Cholesky
  factorisation in effect) that reports failure instead of raising (the step is then
  rejected and the damping raised), never by an undamped inverse;
  ``lambda = mu · |e|`` (+ a tiny floor) shrinks with the error, so the last
  iterations are Gauss–Newton steps (quadratic convergence) while far from a solution
  and near singular configurations the step stays damped;
- projection: the trial point is clamped into the box (joint limits, or a small box
  around an initial solution), and the step is accepted only if the cost went down;
  ``mu`` adapts per problem from the ratio of actual to predicted decrease (Nielsen);
- early exit: a problem leaves the batch when it has converged (a polishing step
  after reaching a tenth of the tolerance, or a far tighter tolerance at once), or
  when it stalls (too little decrease of the cost over a window, or damping
  exhausted, or a rate too slow to arrive within its budget), or
  (``handoff_position``) when it has stayed within the polish's reach for a window.
  The batch is compacted, so finished problems cost nothing.

Everything runs batch-last (``hybrid_pk.geometry.batch_last``) for the ``A`` problems
still active, and the state of a problem is one column of two packed tensors (what an
evaluation gives, what the iteration keeps), so that accepting steps and compacting
the batch are a few operations whatever the number of quantities
(:mod:`~hybrid_pk.ik.lm_algebra` has the arithmetic).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.ik.lm_algebra import eliminate, normal_equations, pose_residual

__all__ = ["LMOutput", "LMSettings", "batched_levenberg_marquardt"]

_TWO_PI = 2 * math.pi


@dataclass(frozen=True)
class LMSettings:
    """Iteration settings (lengths in m, angles in rad).

    Attributes:
        max_iterations: iteration budget per problem (one trial evaluation each).
        rotation_weight: [m/rad] weight of the rotation residual; ~ the arm's reach.
        position_only: ignore orientation (three residuals).
        accept_position: [m] errors below which a problem is "near" and gets polished.
        accept_rotation: [rad].
        keep_position: [m] a problem within this (and ``keep_rotation``) is never given
            up for slow progress (near-singular solutions converge slowly, and would
            otherwise be returned unpolished); usually the caller's tolerance.
        keep_rotation: [rad].
        polish_iterations: extra Gauss–Newton-like iterations once near.
        tight_factor: a problem below ``tight_factor`` times the accept tolerances
            leaves at once (nothing left to polish).
        damping_init: initial ``mu`` [1/m] (``lambda = mu |e|``).
        damping_max: ``mu`` beyond which a problem is given up.
        stall_window: iterations between progress checks.
        stall_ratio: a problem whose cost did not drop below ``stall_ratio`` times its
            cost at the previous check is given up (unless within the keep errors).
        reach_factor: a problem that, at two successive checks, would need more than
            this many times its remaining iterations to reach the accept errors at the
            rate of its last window is given up too (unless within the keep errors):
            it cannot arrive within its budget. A window's rate extrapolated is
            pessimistic (the iteration speeds up near a solution), hence the factor
            and the second check (UR10 / RX160, 20 target sets: 1 and one check lost
            branches, 2 and two checks none).
        handoff_position: [m] a problem within this and ``handoff_rotation`` at a
            progress check, and (by cost) at the check before or the start, leaves, to
            be finished by the caller's Gauss-Newton polish (:mod:`~hybrid_pk.ik.polish`,
            whose reach this is): there the damped iteration only crawls, near a
            singular configuration. None (default): no hand-off, for callers that do
            not polish.
        handoff_rotation: [rad]; given with ``handoff_position`` or not at all.
    """

    max_iterations: int = 60
    rotation_weight: float = 0.5
    position_only: bool = False
    accept_position: float = 1e-7
    accept_rotation: float = 1e-6
    keep_position: float = 1e-6
    keep_rotation: float = 1e-5
    polish_iterations: int = 1
    tight_factor: float = 1e-3
    damping_init: float = 0.3
    damping_max: float = 1e10
    stall_window: int = 4
    stall_ratio: float = 0.9
    reach_factor: float = 2.0
    handoff_position: float | None = None
    handoff_rotation: float | None = None

    def __post_init__(self) -> None:
        if (self.handoff_position is None) != (self.handoff_rotation is None):
            raise ValueError("LMSettings: give handoff_position and handoff_rotation together")


class LMOutput(NamedTuple):
    """Per problem: final ``q (P, dof)``, ``position_error (P,)`` [m], ``rotation_error
    (P,)`` [rad], ``iterations (P,)``, ``damping (P, 2)`` (the damping ``mu`` and its
    growth ``nu`` where each stopped: to continue its iteration); ``evaluations``: total
    number of configurations evaluated (pose + Jacobian); ``active (P,)`` bool: still
    iterating when the call returned early (``stop_at``), else None."""

    q: Tensor
    position_error: Tensor
    rotation_error: Tensor
    iterations: Tensor
    damping: Tensor
    evaluations: int
    active: Tensor | None = None


# Rows of the kept block: damping mu and its growth nu, iterations spent near, cost at
# the last progress check, problem index, too slow at the last check (1.0), target
# rotation (9) and position (3), then per-problem boxes (lower, upper, periodic; n
# each) when the problems have their own.
_MU, _NU, _NEAR, _CHECK, _IDX, _SLOW, _RT, _PT, _BOX = 0, 1, 2, 3, 4, 5, 6, 15, 18


class _Batch:
    """The problems still active. ``ev (K, A)``: rows ``q (n)``, weighted Jacobian
    ``(m n)``, weighted residual ``(m)``, cost, position and rotation error (what one
    evaluation gives); ``kept (_BOX [+ 3 n], A)``: the rest."""

    def __init__(
        self, evaluate, q0, rows, T_target, lower, upper, revolute, s: LMSettings, damping=None
    ):
        P, n = q0.shape
        self.evaluate, self.s, self.n, self.rows_all = evaluate, s, n, rows
        self.m = 3 if s.position_only else 6
        e0 = n + self.m * n  # rows of ev: q, J, e, then cost, pos, rot
        self._at = {"q": slice(0, n), "J": slice(n, e0), "e": slice(e0, e0 + self.m)}
        self._at.update(cost=e0 + self.m, pos=e0 + self.m + 1, rot=e0 + self.m + 2)
        self.shared = lower.ndim == 1 and upper.ndim == 1
        lo, hi = (lower[:, None], upper[:, None]) if self.shared else (lower.T, upper.T)
        lo, hi = lo.to(q0), hi.to(q0)
        per = hi - lo >= _TWO_PI
        if revolute is None:
            per = per & ~per
        else:
            per = per & revolute.to(per.device)[:, None]
        self.any_periodic, self.all_periodic = bool(per.any()), bool(per.all())
        kept = q0.new_zeros(_BOX if self.shared else _BOX + 3 * n, P)
        if damping is None:
            kept[_MU], kept[_NU] = s.damping_init, 2.0
        else:
            kept[_MU : _NU + 1] = damping.T.to(q0)
        kept[_IDX] = torch.arange(P, dtype=q0.dtype, device=q0.device)
        kept[_RT:_PT] = T_target[:, :3, :3].reshape(P, 9).T
        kept[_PT:_BOX] = T_target[:, :3, 3].T
        if self.shared:
            self.box = (lo.contiguous(), hi.contiguous(), per)
        else:
            kept[_BOX:] = torch.cat([lo, hi, per.to(q0.dtype)])
        self.kept, self.rows = kept, rows
        q = torch.minimum(torch.maximum(q0.T, lo), hi)
        self.ev = self.trial(q)
        self.kept[_CHECK] = self.ev[self.n + self.m * self.n + self.m]

    @property
    def size(self) -> int:
        return self.ev.shape[1]

    def field(self, name: str) -> Tensor:
        """``q``, ``J``, ``e``, ``cost``, ``pos`` or ``rot`` of the active problems."""
        out = self.ev[self._at[name]]
        return out.view(self.m, self.n, -1) if name == "J" else out

    def bounds(self) -> tuple[Tensor, Tensor, Tensor]:
        """``lower``, ``upper`` ``(n, 1 | A)`` and ``periodic`` (bool) of the box."""
        if self.shared:
            return self.box
        n, b = self.n, self.kept[_BOX:]
        return b[:n], b[n : 2 * n], b[2 * n :] > 0.5

    def trial(self, q: Tensor) -> Tensor:
        """The evaluated block ``(K, A)`` at ``q (n, A)``."""
        R, p, J = self.evaluate(q, self.rows)
        k = self.kept
        R_t = k[_RT:_PT].view(3, 3, -1)
        dp, dr, cost, pos, rot = pose_residual(
            R, p, R_t, k[_PT:_BOX], self.s.rotation_weight, self.s.position_only
        )
        A, n = q.shape[1], self.n
        if self.s.position_only:
            parts = [q, J[:3].reshape(3 * n, A), dp]
        else:
            Jr = (J[3:] * self.s.rotation_weight).reshape(3 * n, A)
            parts = [q, J[:3].reshape(3 * n, A), Jr, dp, dr]
        return torch.cat([*parts, cost, pos, rot])

    def keep(self, stay: Tensor) -> None:
        """Compact the batch to the problems ``stay`` (indices into the active ones)."""
        self.ev = self.ev.index_select(1, stay)
        self.kept = self.kept.index_select(1, stay)
        self.rows = self.rows_all.index_select(0, self.kept[_IDX].long())


def _projected_step(b: _Batch) -> tuple[Tensor, Tensor, Tensor]:
    """Damped Gauss-Newton trial point projected into the box: ``q_try (n, A)``,
    ``ok (A,)`` (the elimination worked) and the predicted cost decrease ``(A,)``."""
    q, J, e, cost = b.field("q"), b.field("J"), b.field("e"), b.field("cost")
    lo, hi, per = b.bounds()
    G = normal_equations(J, e)
    g = G[:, -1]
    # Joints on a bound that the descent direction pushes outward are held there
    # (projected LM): their rows and columns of the normal equations become the
    # identity, so the other joints do not move as if the held ones had.
    n = q.shape[0]
    diag = G.view(-1, G.shape[-1])[:: n + 2]  # (n, A) view of the diagonal
    held = None if b.all_periodic else ((q <= lo) & (g < 0)) | ((q >= hi) & (g > 0))
    if held is not None and b.any_periodic:
        held &= ~per
    if held is not None and bool(held.any()):
        free = (~held).to(q.dtype)
        G.mul_(free[:, None])  # rows, right-hand side included
        G[:, :-1].mul_(free[None])  # columns
        diag += 1 - free
    k = b.kept
    lam = torch.add(k[_MU] * cost.sqrt(), diag.amax(0).clamp_min(1.0), alpha=1e-14)
    diag += lam
    dq, ok = eliminate(G)
    q_new = q + dq
    q_try = torch.clamp(q_new, lo, hi)
    if b.any_periodic:
        # A periodic joint leaving its box re-enters 2 pi further: same pose, no clamp.
        out = per & (q_new != q_try)
        if bool(out.any()):
            q_try = torch.where(out, lo + torch.remainder(q_new - lo, _TWO_PI), q_try)
            dq = torch.where(out, dq, q_try - q)
        else:
            dq = q_try - q
    else:
        dq = q_try - q
    e_lin = e - (J * dq[None]).sum(1)
    return q_try, ok, cost - (e_lin * e_lin).sum(0)


# Problems from which the blend beats the select, its finiteness sum included (one
# thread, 51 rows: equal at ~1,000 problems in float32 and float64, 119 -> 68 us at
# 3,200 in float32).
_BLEND_MIN = 1024


def _accept(b: _Batch, trial: Tensor, ok: Tensor, predicted: Tensor) -> None:
    """Take the trial point where the cost went down; Nielsen's damping update."""
    cost, k = b.field("cost"), b.kept
    cost_try = trial[trial.shape[0] - 3]
    accept = ok & (cost_try < cost) & (predicted > 0)  # NaN compares False
    rho = (cost - cost_try).div_(predicted.clamp_min(torch.finfo(cost.dtype).tiny))
    shrink = (1 - rho.mul_(2).sub_(1).pow_(3)).clamp_min_(1 / 3)
    mu, nu = k[_MU], k[_NU]
    mu.mul_(torch.where(accept, shrink, nu)).clamp_(1e-12, b.s.damping_max)
    nu.mul_(2).masked_fill_(accept, 2.0)
    # One pass, no count of the rejected. Over many problems a blend by 0 / 1 weights:
    # exact for finite values (lerp returns its end at weight 1, its start at 0) and
    # ~2x cheaper than a select whose mask broadcasts over the rows; a non-finite trial
    # (a failed step's) would spread NaN into a rejected column, so it takes the select.
    if b.size >= _BLEND_MIN and bool(torch.isfinite(trial.sum())):
        b.ev = torch.lerp(b.ev, trial, accept.to(trial.dtype))
    else:
        b.ev = torch.where(accept, trial, b.ev)


def _cost(s: LMSettings, position: float, rotation: float) -> float:
    """The cost [m^2] of a pose ``position`` [m] and ``rotation`` [rad] off its target."""
    return position * position + (0.0 if s.position_only else (s.rotation_weight * rotation) ** 2)


def _too_slow(s: LMSettings, cost: Tensor, cost_before: Tensor, it: int) -> Tensor:
    """``(A,)`` bool: at the rate of the window from ``cost_before`` to ``cost``, the
    accept errors are more than ``reach_factor`` times the iterations left away."""
    rate = (cost / cost_before).clamp(torch.finfo(cost.dtype).tiny, 1.0)
    need = torch.log(_cost(s, s.accept_position, s.accept_rotation) / cost).clamp_max(0.0)
    windows_left = (s.max_iterations - it) / s.stall_window
    return need < s.reach_factor * windows_left * torch.log(rate)  # both sides <= 0


def _leaving(b: _Batch, it: int) -> Tensor:
    """``(A,)`` bool, the problems that leave the batch, decided on the accepted state."""
    s, k = b.s, b.kept
    pos, rot = b.field("pos"), b.field("rot")
    near_count = k[_NEAR]
    near_count += (pos <= s.accept_position) & (rot <= s.accept_rotation)
    leave = (near_count > s.polish_iterations) | (k[_MU] >= s.damping_max)
    tight_p, tight_r = s.tight_factor * s.accept_position, s.tight_factor * s.accept_rotation
    leave |= (pos <= tight_p) & (rot <= tight_r)
    if it > 0 and it % s.stall_window == 0:
        keep = (pos <= s.keep_position) & (rot <= s.keep_rotation)
        cost = b.field("cost")
        leave |= (cost > s.stall_ratio * k[_CHECK]) & ~keep
        slow = _too_slow(s, cost, k[_CHECK], it) & ~keep
        leave |= slow & (k[_SLOW] > 0)
        k[_SLOW] = slow
        if s.handoff_position is not None:  # in the band now and (by cost) at the last check
            hp, hr = s.handoff_position, s.handoff_rotation
            leave |= (pos <= hp) & (rot <= hr) & (k[_CHECK] <= _cost(s, hp, hr))
        k[_CHECK] = cost
    if it >= s.max_iterations:
        leave = torch.ones_like(leave)
    return leave


def batched_levenberg_marquardt(
    evaluate: Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]],
    q0: Tensor,
    rows: Tensor,
    T_target: Tensor,
    lower: Tensor,
    upper: Tensor,
    settings: LMSettings = LMSettings(),
    revolute: Tensor | None = None,
    stop_at: int = 0,
    damping: Tensor | None = None,
) -> LMOutput:
    """Solve ``P`` small pose problems from their start configurations, in one batch.

    (:func:`hybrid_pk.calibration.least_squares.levenberg_marquardt` is the other LM:
    one dense problem with many residuals, for the calibration fits.)

    Args:
        evaluate: ``(q (dof, M), rows (M,)) -> (R (3, 3, M), p (3, M), J (6, dof, M))``,
            batch-last pose and geometric Jacobian (``IKModel.evaluate``).
        q0: ``(P, dof)`` start configurations [rad or m] (clamped into the box first).
        rows: ``(P,)`` long, the target index of each problem (passed to ``evaluate``).
        T_target: ``(P, 4, 4)`` target pose of each problem [m].
        lower: ``(dof,)`` box lower bounds shared by all problems, or ``(P, dof)``
            (``-inf`` allowed).
        upper: ``(dof,)`` or ``(P, dof)`` box upper bounds.
        settings: see :class:`LMSettings`.
        revolute: ``(dof,)`` bool; a revolute joint whose box spans at least 2 pi is
            wrapped by 2 pi back into the box instead of clamped (same pose).
        stop_at: return as soon as at most this many problems are still iterating
            (``LMOutput.active`` marks them, their state as it is; default 0: run all
            to the end).
        damping: ``(P, 2)`` initial ``mu`` and ``nu`` of each problem (an earlier call's
            ``LMOutput.damping``: the iteration goes on where it stopped); default
            ``settings.damping_init`` and 2.

    Returns:
        :class:`LMOutput`; every ``q`` is inside the box and finite.
    """
    P, n = q0.shape
    if P == 0:
        empty = q0.new_zeros(0)
        return LMOutput(q0.clone(), empty, empty, empty.long(), q0.new_zeros(0, 2), 0)
    T_target = T_target.to(q0)
    # outputs, filled as problems leave the batch: q (n), position, rotation, iterations,
    # mu, nu
    out = torch.cat([q0.T, q0.new_full((2, P), torch.inf), q0.new_zeros(3, P)])
    b = _Batch(evaluate, q0, rows, T_target, lower, upper, revolute, settings, damping)
    evaluations, it = P, 0
    active = None
    while True:
        leave = _leaving(b, it)
        if 0 < b.size <= stop_at:  # hand the rest back as they are
            active = torch.zeros(P, dtype=torch.bool, device=q0.device)
            active[b.kept[_IDX][~leave].long()] = True
            leave = torch.ones_like(leave)
        if bool(leave.any()):
            gone = leave.nonzero()[:, 0]
            at = b.kept[_IDX].index_select(0, gone).long()
            done = b.ev.index_select(1, gone)
            e0 = n + b.m * n + b.m
            out[:n, at], out[n : n + 2, at], out[n + 2, at] = done[:n], done[e0 + 1 :], it
            out[n + 3 :, at] = b.kept[_MU : _NU + 1].index_select(1, gone)
            b.keep((~leave).nonzero()[:, 0])
        if b.size == 0:
            break
        it += 1
        q_try, ok, predicted = _projected_step(b)
        trial = b.trial(q_try)
        evaluations += b.size
        _accept(b, trial, ok, predicted)
    q = out[:n].T.contiguous()
    damp = out[n + 3 :].T.contiguous()
    return LMOutput(q, out[n], out[n + 1], out[n + 2].long(), damp, evaluations, active)

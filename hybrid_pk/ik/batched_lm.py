"""Batched, box-constrained Levenberg–Marquardt on pose residuals.

Each of ``P`` problems (a target and a start configuration) is solved independently,
all in one batch:

- residual ``e = [p_target - p, w · log(R_target R^T)]`` [m], with ``w`` the rotation
  weight [m/rad] (position only: the first three entries);
- step ``(J^T J + lambda I) dq = J^T e`` solved by a Cholesky factorisation (a
  pivoted LU for small batches) that reports failure instead of raising (the step is
  then rejected and the damping raised), never by an undamped inverse;
  ``lambda = mu · |e|`` (+ a tiny floor) shrinks with the error, so the last
  iterations are Gauss–Newton steps (quadratic convergence) while far from a solution
  and near singular configurations the step stays damped;
- projection: the trial point is clamped into the box (joint limits, or a small box
  around an initial solution), and the step is accepted only if the cost went down;
  ``mu`` adapts per problem from the ratio of actual to predicted decrease (Nielsen);
- early exit: a problem leaves the batch when it has converged (a polishing step
  after reaching a tenth of the tolerance, or a far tighter tolerance at once), or
  when it stalls (too little decrease of the cost over a window, or damping
  exhausted). The batch is compacted, so finished problems cost nothing.

Everything runs batch-last (``hybrid_pk.geometry.batch_last``): ``q (dof, A)``, ``J (6, dof, A)``
for the ``A`` problems still active.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.geometry import so3_log
from hybrid_pk.geometry.batch_last import compose, solve_spd

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


class LMOutput(NamedTuple):
    """Per problem: final ``q (P, dof)``, ``position_error (P,)`` [m], ``rotation_error
    (P,)`` [rad], ``iterations (P,)``; ``evaluations``: total number of configurations
    evaluated (pose + Jacobian)."""

    q: Tensor
    position_error: Tensor
    rotation_error: Tensor
    iterations: Tensor
    evaluations: int


def _rotation_error(E: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation vector ``(3, A)`` [rad] and angle ``(A,)`` of rotations ``E (3, 3, A)``.

    The closed form for every column, then :func:`so3_log` only where the angle is
    near pi (where the closed form loses the axis).
    """
    vee = torch.stack([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])  # 2 sin(t) a
    s = vee.norm(dim=0) / 2
    c = (E[0, 0] + E[1, 1] + E[2, 2] - 1) / 2
    theta = torch.atan2(s, c)
    small = s < 1e-4
    scale = torch.where(small, 0.5 + theta * theta / 12, theta / (2 * torch.where(small, 1.0, s)))
    w = scale * vee
    far = c < -0.9
    if bool(far.any()):
        w[:, far] = so3_log(E[:, :, far].permute(2, 0, 1)).T
    return w, theta


def _residual(
    R: Tensor, p: Tensor, R_t: Tensor, p_t: Tensor, s: LMSettings
) -> tuple[Tensor, Tensor, Tensor]:
    """Weighted residual ``(6 | 3, A)``, position error ``(A,)`` [m], rotation error [rad]."""
    dp = p_t - p
    pos = dp.norm(dim=0)
    if s.position_only:
        return dp, pos, torch.zeros_like(pos)
    dr, angle = _rotation_error(compose(R_t, R.transpose(0, 1)))  # R_t R^T
    return torch.cat([dp, s.rotation_weight * dr]), pos, angle


def _weighted(J: Tensor, s: LMSettings) -> Tensor:
    """Rows of ``J (6, dof, A)`` as the residual weighs them."""
    if s.position_only:
        return J[:3]
    return torch.cat([J[:3], s.rotation_weight * J[3:]])


class _Active:
    """The problems still in the batch; every tensor is batch-last (last dim ``A``)."""

    BATCHED = (
        *("idx", "rows", "R_t", "p_t", "q", "J", "e"),
        *("cost", "pos", "rot", "mu", "nu", "near_count", "checkpoint"),
    )

    def __init__(self, evaluate, q0, rows, T_target, lower, upper, revolute, s: LMSettings):
        f64 = {"dtype": q0.dtype, "device": q0.device}
        P = q0.shape[0]
        self.shared = lower.ndim == 1 and upper.ndim == 1
        lo, hi = (lower[:, None], upper[:, None]) if self.shared else (lower.T, upper.T)
        self.lo, self.hi = lo.to(**f64).contiguous(), hi.to(**f64).contiguous()  # (dof, 1|P)
        per = self.hi - self.lo >= _TWO_PI
        self.per = per & revolute.to(per.device)[:, None] if revolute is not None else per & ~per
        self.any_periodic = bool(self.per.any())
        self.idx = torch.arange(P, device=q0.device)
        self.rows = rows
        self.q = torch.minimum(torch.maximum(q0.T, self.lo), self.hi).contiguous()  # (dof, A)
        self.R_t = T_target[:, :3, :3].permute(1, 2, 0).contiguous()
        self.p_t = T_target[:, :3, 3].T.contiguous()
        self.J, self.e, self.pos, self.rot, self.cost = _evaluate(evaluate, self.q, self, s)
        self.mu = torch.full((P,), s.damping_init, **f64)
        self.nu = torch.full((P,), 2.0, **f64)
        self.near_count = torch.zeros(P, dtype=torch.long, device=q0.device)
        self.checkpoint = self.cost

    def keep(self, stay: Tensor) -> None:
        """Compact the batch to the problems ``stay`` (indices into the active ones)."""
        names = self.BATCHED if self.shared else (*self.BATCHED, "lo", "hi", "per")
        for name in names:
            setattr(self, name, getattr(self, name)[..., stay])


def _evaluate(evaluate, q: Tensor, a: _Active, s: LMSettings) -> tuple[Tensor, ...]:
    """Weighted Jacobian, residual, position / rotation error and cost at ``q (dof, A)``."""
    R, p, J = evaluate(q, a.rows)
    e, pos, rot = _residual(R, p, a.R_t, a.p_t, s)
    return _weighted(J, s), e, pos, rot, (e * e).sum(0)


def _leaving(a: _Active, it: int, s: LMSettings) -> Tensor:
    """``(A,)`` bool, the problems that leave the batch, decided on the accepted state."""
    near = (a.pos <= s.accept_position) & (a.rot <= s.accept_rotation)
    a.near_count += near.long()
    leave = (a.near_count > s.polish_iterations) | (a.mu >= s.damping_max)
    tight_p, tight_r = s.tight_factor * s.accept_position, s.tight_factor * s.accept_rotation
    leave |= (a.pos <= tight_p) & (a.rot <= tight_r)
    if it > 0 and it % s.stall_window == 0:
        keep = (a.pos <= s.keep_position) & (a.rot <= s.keep_rotation)
        leave |= (a.cost > s.stall_ratio * a.checkpoint) & ~keep
        a.checkpoint = a.cost
    if it >= s.max_iterations:
        leave = torch.ones_like(leave)
    return leave


def _projected_step(a: _Active) -> tuple[Tensor, Tensor, Tensor]:
    """Damped Gauss-Newton trial point projected into the box: ``q_try (dof, A)``,
    ``ok (A,)`` (the factorisation worked) and the predicted cost decrease ``(A,)``."""
    J, e, q, lo, hi, per = a.J, a.e, a.q, a.lo, a.hi, a.per
    g = (J * e[:, None, :]).sum(0)  # J^T e, (dof, A)
    A = J[0, :, None] * J[0, None, :]  # J^T J, (dof, dof, A)
    for k in range(1, J.shape[0]):
        A = torch.addcmul(A, J[k, :, None], J[k, None, :])
    # Joints on a bound that the descent direction pushes outward are held there
    # (projected LM): their rows and columns of the normal equations become the
    # identity, so the other joints do not move as if the held ones had.
    held = ~per & (((q <= lo) & (g < 0)) | ((q >= hi) & (g > 0)))
    diag = A.diagonal(0, 0, 1)  # (A, dof) view
    if bool(held.any()):
        free = (~held).to(q.dtype)
        A = A * free[:, None] * free[None, :]
        diag = A.diagonal(0, 0, 1)
        diag += (1 - free).T
        g = g * free
    scale = diag.amax(-1).clamp_min(1.0)
    lam = a.mu * a.cost.sqrt() + 1e-14 * scale
    diag += lam[:, None]
    dq, ok = solve_spd(A, g)
    dq = torch.where(ok, dq, 0.0)
    q_new = q + dq
    q_try = torch.minimum(torch.maximum(q_new, lo), hi)
    step = q_try - q
    if a.any_periodic:
        # A periodic joint leaving its box re-enters 2 pi further: same pose, no clamp.
        out = per & (q_new != q_try)
        if bool(out.any()):
            step = torch.where(out, dq, step)
            q_try = torch.where(out, lo + torch.remainder(q_new - lo, _TWO_PI), q_try)
    e_lin = e - (J * step[None]).sum(1)
    return q_try, ok, a.cost - (e_lin * e_lin).sum(0)


def _accept(a: _Active, q_try: Tensor, trial: tuple, ok: Tensor, predicted: Tensor, s) -> None:
    """Take the trial point where the cost went down; Nielsen's damping update."""
    J_try, e_try, pos_try, rot_try, cost_try = trial
    finite = torch.isfinite(cost_try + J_try.sum((0, 1)))  # NaN/inf anywhere
    accept = ok & finite & (cost_try < a.cost) & (predicted > 0)
    rho = (a.cost - cost_try) / predicted.clamp_min(torch.finfo(a.q.dtype).tiny)
    shrink = torch.clamp(1 - (2 * rho - 1) ** 3, min=1 / 3)
    a.mu = torch.where(accept, a.mu * shrink, a.mu * a.nu).clamp(1e-12, s.damping_max)
    a.nu = torch.where(accept, 2.0, a.nu * 2)
    a.q = torch.where(accept, q_try, a.q)
    a.J = torch.where(accept, J_try, a.J)
    a.e = torch.where(accept, e_try, a.e)
    a.cost = torch.where(accept, cost_try, a.cost)
    a.pos = torch.where(accept, pos_try, a.pos)
    a.rot = torch.where(accept, rot_try, a.rot)


def batched_levenberg_marquardt(
    evaluate: Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]],
    q0: Tensor,
    rows: Tensor,
    T_target: Tensor,
    lower: Tensor,
    upper: Tensor,
    settings: LMSettings = LMSettings(),
    revolute: Tensor | None = None,
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

    Returns:
        :class:`LMOutput`; every ``q`` is inside the box and finite.
    """
    s, P = settings, q0.shape[0]
    if P == 0:
        empty = q0.new_zeros(0)
        return LMOutput(q0.clone(), empty, empty, empty.long(), 0)
    q_out = q0.clone()  # outputs, filled as problems leave the batch
    pos_out, rot_out = q0.new_full((P,), torch.inf), q0.new_full((P,), torch.inf)
    it_out = torch.zeros(P, dtype=torch.long, device=q0.device)
    a = _Active(evaluate, q0, rows, T_target, lower, upper, revolute, s)
    evaluations, it = P, 0
    while True:
        leave = _leaving(a, it, s)
        if bool(leave.any()):
            gone = a.idx[leave]
            q_out[gone], pos_out[gone], rot_out[gone] = a.q[:, leave].T, a.pos[leave], a.rot[leave]
            it_out[gone] = it
            a.keep((~leave).nonzero()[:, 0])
        if a.idx.numel() == 0:
            break
        it += 1
        q_try, ok, predicted = _projected_step(a)
        trial = _evaluate(evaluate, q_try, a, s)
        evaluations += a.idx.numel()
        _accept(a, q_try, trial, ok, predicted, s)
    return LMOutput(q_out, pos_out, rot_out, it_out, evaluations)

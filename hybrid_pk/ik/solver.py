"""`solve_ik`: every distinct IK solution of a batch of targets on one model.

Targets × seeds are solved as one batch by
:func:`~hybrid_pk.ik.batched_lm.batched_levenberg_marquardt` (joint limits by
projection, per-problem damping and early exit; float32 down to near a solution and
float64 to finish where the model has the chain kernel,
:mod:`~hybrid_pk.ik.two_precision`). Every candidate is then checked by a fresh forward
evaluation of the model against the tolerances and the joint limits, polished onto its
exact branch (:mod:`~hybrid_pk.ik.polish`), and the survivors are reduced to distinct
solutions (contract section 6). A target none of whose seeds passes is a failure: the
solver never returns a solution it has not verified.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions
from hybrid_pk.errors import ShapeError
from hybrid_pk.evaluation.metrics import pose_error, position_error_mm
from hybrid_pk.geometry import transform
from hybrid_pk.ik.batched_lm import LMOutput, LMSettings, batched_levenberg_marquardt
from hybrid_pk.ik.conditions import Approach, resolve_conditions
from hybrid_pk.ik.dedup import PRISMATIC_TOL, REVOLUTE_TOL, distinct_mask
from hybrid_pk.ik.forward_model import (
    IKModel,
    as_ik_model,
    least_singular_values,
    no_autograd,
    plain,
)
from hybrid_pk.ik.packing import concat_padded, pack
from hybrid_pk.ik.polish import NEAR_FACTOR, polish, within
from hybrid_pk.ik.result import IKResult
from hybrid_pk.ik.seeds import quasi_random_seeds, seed_box
from hybrid_pk.ik.two_precision import solve_two_precisions

__all__ = [
    "IKOptions",
    "check_solutions",
    "closest_attempt",
    "make_result",
    "prepare_targets",
    "solve_and_check",
    "solve_ik",
]

F64 = torch.float64


@dataclass(frozen=True)
class IKOptions:
    """Settings of :func:`solve_ik` (and of the hybrid two-stage solver).

    Attributes:
        tol_mm: [mm] largest position error of a returned solution.
        tol_deg: [deg] largest orientation error of a returned solution.
        max_iterations: iteration budget of each (target, seed) problem.
        rotation_weight: [m/rad] weight of rotation against position residuals.
        seed_method: ``"sobol"``, ``"halton"`` or ``"uniform"``.
        seed: scrambling seed of the quasi-random seeds (same seed, same result).
        revolute_tol: [rad] two solutions are the same when all revolute joints agree
            within this modulo 2 pi (contract: 1e-3) ...
        prismatic_tol: [m] ... and all prismatic joints within this (contract: 1e-6).
        batch_size: (target, seed) problems solved in one batch (memory bound).
        polish_mm: [mm] position error from which on a problem gets its final
            Gauss-Newton polishing step and leaves; default a tenth of ``tol_mm``.
        polish_deg: [deg] the same for the orientation; default a tenth of ``tol_deg``.
    """

    tol_mm: float = 1e-3
    tol_deg: float = 1e-3
    max_iterations: int = 60
    rotation_weight: float = 0.5
    seed_method: str = "sobol"
    seed: int = 0
    revolute_tol: float = REVOLUTE_TOL
    prismatic_tol: float = PRISMATIC_TOL
    batch_size: int = 16384
    polish_mm: float | None = None
    polish_deg: float | None = None

    def __post_init__(self) -> None:
        if bad := [k for k in ("tol_mm", "tol_deg", "max_iterations") if not getattr(self, k) > 0]:
            raise ShapeError(f"IKOptions: {', '.join(bad)} must be > 0, got {self!r}")

    def lm_settings(self, position_only: bool) -> LMSettings:
        """Iteration settings of :func:`~hybrid_pk.ik.batched_lm.batched_levenberg_marquardt`."""
        polish_mm = 0.1 * self.tol_mm if self.polish_mm is None else self.polish_mm
        polish_deg = 0.1 * self.tol_deg if self.polish_deg is None else self.polish_deg
        return LMSettings(
            max_iterations=self.max_iterations,
            rotation_weight=self.rotation_weight,
            position_only=position_only,
            accept_position=polish_mm * 1e-3,
            accept_rotation=math.radians(polish_deg),
            keep_position=max(polish_mm, self.tol_mm) * 1e-3,
            keep_rotation=math.radians(max(polish_deg, self.tol_deg)),
        )


# ----------------------------------------------------------------------------- helpers


def prepare_targets(targets: Tensor) -> tuple[Tensor, tuple[int, ...], bool]:
    """``(*B, 4, 4)`` poses or ``(*B, 3)`` points [m] -> ``(N, 4, 4)`` float64, ``B``,
    position-only flag."""
    targets = torch.as_tensor(targets)
    if not targets.is_floating_point():
        raise ShapeError(f"IK targets must be floating point, found dtype {targets.dtype}")
    if targets.ndim >= 2 and targets.shape[-2:] == (4, 4):
        batch, position_only = tuple(targets.shape[:-2]), False
        T = targets.reshape(-1, 4, 4).to(F64)
    elif targets.ndim >= 1 and targets.shape[-1] == 3:
        batch, position_only = tuple(targets.shape[:-1]), True
        p = targets.reshape(-1, 3).to(F64)
        T = transform(torch.eye(3, dtype=F64).expand(p.shape[0], 3, 3), p)
    else:
        raise ShapeError(
            f"IK targets must be poses (*B, 4, 4) or points (*B, 3) [m], found "
            f"{tuple(targets.shape)}"
        )
    bad = ~torch.isfinite(T).all(-1).all(-1)
    if bool(bad.any()):
        raise ShapeError(f"IK target {int(bad.nonzero()[0])} (flat index) is not finite")
    if not position_only:
        _check_rotations(T)
    return T, batch, position_only


# [-] largest |R^T R - I| of a target rotation: float32 poses from a chain of products
# are orthonormal to ~1e-6, and a defect of 1e-5 rad is already half the default
# orientation tolerance (1e-3 deg = 1.7e-5 rad), which it would blur.
ROTATION_TOL = 1e-5


def _check_rotations(T: Tensor) -> None:
    """One-line error for target poses that are not rigid transforms."""
    R = T[:, :3, :3]
    eye = torch.eye(3, dtype=T.dtype)
    defect = (R.transpose(-1, -2) @ R - eye).abs().amax((-1, -2))
    bottom = (T[:, 3] - T.new_tensor([0.0, 0.0, 0.0, 1.0])).abs().amax(-1)
    for bad, what in (
        (
            defect > ROTATION_TOL,
            lambda i: f"|R^T R - I| = {float(defect[i]):.3g} > {ROTATION_TOL:g}",
        ),
        (torch.linalg.det(R) < 0, lambda i: "det R = -1 (a reflection)"),
        (bottom > ROTATION_TOL, lambda i: f"last row {T[i, 3].tolist()} is not [0, 0, 0, 1]"),
    ):
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            raise ShapeError(
                f"IK target {i} (flat index) is not a pose: its rotation must be a proper "
                f"rotation matrix and its last row [0, 0, 0, 1]; {what(i)} ({int(bad.sum())} "
                "such target(s))"
            )


def check_solutions(
    ikm: IKModel,
    q: Tensor,
    rows: Tensor,
    T_target: Tensor,
    position_only: bool,
    options: IKOptions,
    candidate: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Verify candidate solutions by a fresh forward evaluation.

    Args:
        q: ``(P, dof)``; rows: ``(P,)`` target index; T_target: ``(P, 4, 4)``.
        candidate: ``(P,)`` bool, which to evaluate at all (others fail).

    Returns:
        ``ok (P,)`` bool, position error ``(P,)`` [mm], orientation error ``(P,)``
        [deg] (NaN where not evaluated, orientation NaN when position-only).
    """
    P = q.shape[0]
    ok = torch.zeros(P, dtype=torch.bool, device=q.device)
    pos, ori = q.new_full((P,), math.nan), q.new_full((P,), math.nan)
    # The candidates only (often a few hundred of thousands of problems): finite and
    # within the limits, one reduction over the joints (each costs as much as the rest).
    sel = torch.arange(P, device=q.device) if candidate is None else candidate.nonzero()[:, 0]
    qs = q.index_select(0, sel)
    in_limits = (torch.isfinite(qs) & (qs >= ikm.lower) & (qs <= ikm.upper)).all(-1)
    sel, qs = (sel, qs) if bool(in_limits.all()) else (sel[in_limits], qs[in_limits])
    if sel.numel():
        with torch.no_grad():
            T = ikm.pose(qs, rows.index_select(0, sel)).to(F64)
        T_sel = T_target.index_select(0, sel)
        if position_only:
            pos[sel] = position_error_mm(T_sel[:, :3, 3], T[:, :3, 3])
            good = pos[sel] <= options.tol_mm
        else:
            err = pose_error(T_sel, T)
            pos[sel], ori[sel] = err.position_mm, err.orientation_deg
            good = (err.position_mm <= options.tol_mm) & (err.orientation_deg <= options.tol_deg)
        ok[sel] = good & torch.isfinite(pos[sel])
    return ok, pos, ori


def solve_and_check(
    ikm: IKModel,
    q0: Tensor,
    rows: Tensor,
    T_all: Tensor,
    bounds: tuple[Tensor, Tensor],
    settings: LMSettings,
    position_only: bool,
    options: IKOptions,
):
    """Batched LM from starts ``q0 (P, dof)`` towards the targets ``T_all[rows]``
    within ``bounds = (lower, upper)``, then the ends near a solution polished
    (:mod:`~hybrid_pk.ik.polish`) and checked (:func:`check_solutions`).

    Returns:
        ``(out, ok, pos, ori)``: the LM result with those ends polished, and the checks.
    """
    T_target = T_all[rows]
    # The chain kernel evaluates in float32 too: the coarse iterations in float32. Starts
    # that arrived at one solution agree to float32's handover accuracy (~1e-5 rad); cells
    # of half the distinctness tolerance merge only candidates the final reduction would
    # call the same (they differ by less than a cell).
    merge = (options.revolute_tol / 2, options.prismatic_tol / 2)
    # The polish's reach (hybrid_pk.ik.polish): a problem that stays within it is left to it.
    far = NEAR_FACTOR * settings.accept_position, NEAR_FACTOR * settings.accept_rotation
    lm = replace(settings, handoff_position=far[0], handoff_rotation=far[1])
    args, m = (ikm.evaluate, q0, rows, T_target, *bounds, lm, ikm.revolute), None
    with no_autograd(ikm):
        if ikm.batch_last is None:
            out = batched_levenberg_marquardt(*args)
        else:
            out, m = solve_two_precisions(*args, merge)
    out, (m,) = LMOutput(*plain(*out)), plain(m)
    # Only ends the iteration left within twice the tolerances (a margin for float32's
    # rounding) are checked afresh: the others fail anyway. Not in inference mode: the
    # model's caches (chain constants) must stay ordinary tensors, for autograd later.
    near = within(out, 2e-3 * options.tol_mm, 2 * math.radians(options.tol_deg), position_only)
    # Within the tolerances by the iteration's own errors; ends near a solution.
    inside = within(out, 1e-3 * options.tol_mm, math.radians(options.tol_deg), position_only)
    stalled = within(out, *far, position_only)

    def check(q: Tensor, candidate: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return check_solutions(ikm, q, rows, T_target, position_only, options, candidate)

    # Solutions are pinned to their branch only to tol / sigma: polished onto it before
    # the reduction to distinct solutions (hybrid_pk.ik.polish), then checked.
    args = (rows, T_target, bounds, settings, check)
    if m is None:
        return polish(ikm, out, near, inside, stalled, *args)
    # An arrival merged into another start of its target (same cell) is that start's
    # solution, which the reduction keeps: it is checked (polished) only where that fails.
    rep = m < 0
    out, ok, pos, ori = polish(ikm, out, near & rep, inside & rep, stalled & rep, *args)
    retry = near & (m >= 0) & ~ok.index_select(0, m.clamp_min(0))
    if bool(retry.any()):
        none = torch.zeros_like(retry)  # nothing else to polish
        out, ok2, pos2, ori2 = polish(ikm, out, retry, inside & retry, none, *args)
        ok |= ok2
        pos, ori = torch.where(retry, pos2, pos), torch.where(retry, ori2, ori)
    return out, ok, pos, ori


def closest_attempt(out: LMOutput, shape: tuple[int, int], options: IKOptions, position_only: bool):
    """``(N,)`` position [mm] and orientation [deg] errors of each target's start with
    the least Levenberg-Marquardt cost (the solver's own weighting), of ``S`` starts
    each (``shape = (N, S)``): how near the solver came, also where nothing passed."""
    pos = out.position_error.reshape(shape).to(F64)
    rot = out.rotation_error.reshape(shape).to(F64)
    cost = pos.square()
    if not position_only:
        cost = cost + (options.rotation_weight * rot).square()
    best = cost.nan_to_num(math.inf).argmin(-1, keepdim=True)
    mm = torch.take_along_dim(pos, best, 1)[:, 0] * 1e3
    deg = torch.rad2deg(torch.take_along_dim(rot, best, 1)[:, 0])
    return mm, torch.full_like(deg, math.nan) if position_only else deg


def make_result(
    parts: list[tuple[Tensor, ...]],
    batch: tuple[int, ...],
    ikm: IKModel,
    options: IKOptions,
    position_only: bool,
    info: dict,
    closest: tuple[Tensor, Tensor] | None = None,
) -> IKResult:
    q, pos, ori, valid = concat_padded(parts, ikm.dof)
    k = q.shape[1]
    if closest is None:  # refinement, baselines: the best solution (NaN where none)
        p, o = (torch.cat([x, x.new_full((x.shape[0], 1), math.nan)], 1) for x in (pos, ori))
        cost = (p * 1e-3).square() + (options.rotation_weight * o.deg2rad()).square()
        cost = p if position_only else cost
        best = cost.nan_to_num(math.inf).argmin(-1, keepdim=True)  # the NaN column if none
        closest = p.gather(1, best)[:, 0], o.gather(1, best)[:, 0]
    sigma = least_singular_values(ikm, q, valid, options.rotation_weight, position_only)
    return IKResult(
        q=q.reshape(*batch, k, ikm.dof),
        position_error_mm=pos.reshape(*batch, k),
        orientation_error_deg=ori.reshape(*batch, k),
        valid=valid.reshape(*batch, k),
        joint_names=ikm.joint_names,
        tol_mm=options.tol_mm,
        tol_deg=options.tol_deg,
        position_only=position_only,
        info=info,
        closest_mm=closest[0].reshape(batch),
        closest_deg=closest[1].reshape(batch),
        # within the tolerance the joints move by more than the distinctness tolerance
        near_singular=(sigma * options.revolute_tol < options.tol_mm * 1e-3).reshape(batch),
        smallest_singular_value=sigma.reshape(batch),
    )


def _start_configs(
    ikm: IKModel, n_targets: int, seeds: int | Tensor, extra: Tensor | None, options: IKOptions
) -> Tensor:
    """``(N, S, dof)`` start configurations: quasi-random seeds then the user's."""
    dof = ikm.dof
    if isinstance(seeds, int) and seeds == 0 and extra is not None:
        base = torch.zeros(0, dof, dtype=F64)  # the caller's start configurations only
    elif isinstance(seeds, int):
        base = quasi_random_seeds(
            ikm.lower, ikm.upper, ikm.revolute, seeds, method=options.seed_method, seed=options.seed
        )
    else:
        base = torch.as_tensor(seeds, dtype=F64)
        if base.ndim != 2 or base.shape[-1] != dof:
            raise ShapeError(f"seeds must be an int or a (S, {dof}) tensor, found {base.shape}")
    start = base.expand(n_targets, *base.shape)
    if extra is not None:
        extra = torch.as_tensor(extra, dtype=F64)
        if extra.ndim == 0 or extra.shape[-1] != dof:
            raise ShapeError(
                f"extra_seeds must be (dof,), (S, dof) or (*B, S, dof) with dof={dof}, "
                f"found {tuple(extra.shape)}"
            )
        if extra.ndim <= 2:
            extra = extra.reshape(1, -1, dof).expand(n_targets, -1, dof)
        elif math.prod(extra.shape[:-2]) != n_targets:
            raise ShapeError(
                f"extra_seeds {tuple(extra.shape)}: expected one (S, {dof}) block per target "
                f"({n_targets} targets)"
            )
        else:
            extra = extra.reshape(n_targets, -1, dof)
        lo, hi = seed_box(ikm.lower, ikm.upper, ikm.revolute)
        given = torch.isfinite(extra).all(-1, keepdim=True)
        extra = torch.where(given, extra, (lo + hi) / 2)  # NaN row: the middle of the box
        start = torch.cat([start, extra], 1)
    return torch.minimum(torch.maximum(start, ikm.lower), ikm.upper)


# ----------------------------------------------------------------------------- solver


def solve_ik(
    model,
    targets: Tensor,
    *,
    seeds: int | Tensor = 64,
    extra_seeds: Tensor | None = None,
    cond: Conditions | None = None,
    robot=None,
    jacobian: Callable | None = None,
    options: IKOptions | None = None,
    progress: Callable[[int], None] | None = None,
    approach: Approach = None,
) -> IKResult:
    """All distinct joint solutions of each target pose, within the joint limits.

    Args:
        model: ``Robot``, ``ExtendedModel``, callable ``q -> T`` (with ``robot=``) or
            :class:`~hybrid_pk.ik.forward_model.IKModel`; see :func:`~hybrid_pk.ik.as_ik_model`.
        targets: ``(*B, 4, 4)`` target poses, or ``(*B, 3)`` target points
            (position-only IK) [m], in the model's output frame.
        seeds: number of quasi-random seeds per target (0: only ``extra_seeds``), or
            an ``(S, dof)`` tensor of start configurations for every target.
        extra_seeds: more start configurations: ``(dof,)`` or ``(S2, dof)`` for all
            targets, or ``(*B, S2, dof)`` per target (e.g. the current joints); a row
            with NaN starts from the middle of the joint box.
        cond: operating conditions, each field ``(N, ...)`` with ``N`` the number of
            targets in flat (row-major) order (payload, temperature, ...).
        robot: limits and joint types of a callable model.
        jacobian: analytic Jacobian of a callable model (else autograd).
        options: tolerances and iteration settings (:class:`IKOptions`).
        progress: called with the number of targets finished after each batch.
        approach: backlash approach direction (:mod:`~hybrid_pk.ik.conditions`; default
            ``cond.direction``, else the mid-play model, said in an
            :class:`~hybrid_pk.ik.conditions.IKAssumption` warning).

    Returns:
        :class:`IKResult` of batch shape ``*B``; every returned solution is within the
        joint limits and within ``tol_mm`` / ``tol_deg`` of its target (checked by a
        forward evaluation). Targets without one are failures (``result.failed``).
    """
    options = options or IKOptions()
    T_all, batch, position_only = prepare_targets(targets)
    n = T_all.shape[0]
    cond, assumed = resolve_conditions([model], cond, n, approach)
    ikm = as_ik_model(model, cond=cond, robot=robot, jacobian=jacobian, n_targets=n)
    start = _start_configs(ikm, n, seeds, extra_seeds, options)
    s_per = start.shape[1]
    settings = options.lm_settings(position_only)
    per_batch = max(1, options.batch_size // s_per)
    parts, near, iterations, evaluations = [], [], 0, 0
    t0 = time.perf_counter()
    for lo in range(0, n, per_batch):
        hi = min(n, lo + per_batch)
        rows = torch.arange(lo, hi).repeat_interleave(s_per)
        q0 = start[lo:hi].reshape(-1, ikm.dof)
        bounds = (ikm.lower, ikm.upper)
        out, ok, pos, ori = solve_and_check(
            ikm, q0, rows, T_all, bounds, settings, position_only, options
        )
        shape = (hi - lo, s_per)
        score = pos / options.tol_mm + (0 if position_only else ori.nan_to_num() / options.tol_deg)
        q = out.q.reshape(*shape, -1)
        with no_autograd(ikm):
            keep = distinct_mask(
                q,
                ok.reshape(shape),
                score.reshape(shape),
                ikm.revolute,
                options.revolute_tol,
                options.prismatic_tol,
            )
            parts.append(plain(*pack(q, pos.reshape(shape), ori.reshape(shape), keep)))
        near.append(closest_attempt(out, shape, options, position_only))
        iterations += int(out.iterations.sum())
        evaluations += out.evaluations
        if progress is not None:
            progress(hi - lo)
    info = {
        "assumed": assumed,
        "seeds": s_per,
        "problems": n * s_per,
        "mean_iterations": iterations / max(1, n * s_per),
        "evaluations": evaluations,
        "seconds": time.perf_counter() - t0,
    }
    closest = tuple(torch.cat(c) for c in zip(*near, strict=True)) if near else None
    return make_result(parts, batch, ikm, options, position_only, info, closest)

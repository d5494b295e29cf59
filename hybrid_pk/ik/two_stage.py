"""IK on expensive (hybrid) models: the paper's two-stage solver and Wang et al.'s baseline.

Ojer et al. 2024, section 3 and Fig. 3: every branch is first found on a cheap model
(the nominal or calibrated kinematics, analytic Jacobian, many seeds), then each
branch is refined on the accurate model by bounded non-linear least squares, the
joints kept within a small box around the cheap solution. The refinement here is the
same projected Levenberg–Marquardt as the first stage, on the pose residual (position
and rotation vector, which near the solution is the paper's eq. 2 cost up to the
rotation weight, and better conditioned), with the accurate model's Jacobian from
autograd unless an analytic one is given.

Wang et al. (2019), as adapted in the paper's section 5: solve the cheap IK, correct
the target once by the difference between the accurate and the cheap model at that
solution, and solve the cheap IK again for the corrected target. Its error w.r.t.
the accurate model is what Tables IV and V compare against.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import HybridPKError, ShapeError
from hybrid_pk.ik.batched_lm import batched_levenberg_marquardt
from hybrid_pk.ik.conditions import Approach, resolve_conditions
from hybrid_pk.ik.dedup import distinct_mask
from hybrid_pk.ik.forward_model import IKModel, as_ik_model
from hybrid_pk.ik.packing import pack
from hybrid_pk.ik.result import IKResult
from hybrid_pk.ik.solver import (
    IKOptions,
    check_solutions,
    make_result,
    prepare_targets,
    solve_and_check,
    solve_ik,
)
from hybrid_pk.robot import Robot

__all__ = ["DEFAULT_BOX", "refine_ik", "solve_ik_two_stage", "wang_baseline"]

F64 = torch.float64
DEFAULT_BOX = 0.1  # [rad] (or m) half-width of the refinement box around a branch
COARSE_TOL_MM = 10.0  # first-stage tolerances: a branch of the cheap model only needs
COARSE_TOL_DEG = 1.0  # to be close to one of the accurate model


def _robot_of(model) -> Robot | None:
    if isinstance(model, Robot):
        return model
    if isinstance(model, ExtendedModel):
        return model.robot
    if isinstance(model, IKModel):
        return None
    return getattr(model, "robot", None)


def _initial(initial: IKResult | Tensor, n: int, dof: int) -> tuple[Tensor, Tensor]:
    """``(N, K, dof)`` start solutions and ``(N, K)`` mask from a result or a tensor."""
    if isinstance(initial, IKResult):
        q, valid = initial.q.to(F64), initial.valid
    else:
        q = torch.as_tensor(initial, dtype=F64)
        valid = torch.isfinite(q).all(-1)
    if q.ndim < 2 or q.shape[-1] != dof or math.prod(q.shape[:-2]) != n:
        raise ShapeError(
            f"initial solutions must be (*B, K, {dof}) for {n} targets, found {tuple(q.shape)}"
        )
    k = q.shape[-2]
    return q.reshape(n, k, dof), valid.reshape(n, k)


def _scatter(n: int, k: int, rows: Tensor, slots: Tensor, *values: Tensor) -> list[Tensor]:
    """Per-problem values back into ``(N, K, ...)`` padded arrays (NaN elsewhere)."""
    out = []
    for v in values:
        full = v.new_full((n, k, *v.shape[1:]), math.nan)
        full[rows, slots] = v
        out.append(full)
    return out


def _checked_box(box: float | Tensor) -> Tensor:
    """The refinement box half-width as a tensor; one line for one that is not > 0."""
    half = torch.as_tensor(box, dtype=F64)
    if not bool((half > 0).all()):  # NaN included
        raise ShapeError(
            f"box: the refinement box half-width must be > 0 [rad, m for prismatic joints], "
            f"got {box}"
        )
    return half


def refine_ik(
    model,
    targets: Tensor,
    initial: IKResult | Tensor,
    *,
    box: float | Tensor = DEFAULT_BOX,
    cond: Conditions | None = None,
    robot: Robot | None = None,
    jacobian: Callable | None = None,
    options: IKOptions | None = None,
    approach: Approach = None,
) -> IKResult:
    """Refine initial solutions on ``model`` within a box around each (paper Fig. 3).

    Args:
        model: the accurate model (``ExtendedModel``, callable ``q -> T`` such as a
            hybrid model with networks, ...); see :func:`~hybrid_pk.ik.as_ik_model`.
        targets: ``(*B, 4, 4)`` poses or ``(*B, 3)`` points [m].
        initial: a first-stage :class:`IKResult`, or ``(*B, K, dof)`` start solutions
            (NaN rows are empty slots).
        box: half-width of the search box around each initial solution [rad or m],
            scalar or ``(dof,)``; intersected with the joint limits.
        cond, robot, jacobian, approach: as for :func:`~hybrid_pk.ik.solve_ik`.
        options: tolerances and iteration budget.

    Returns:
        :class:`IKResult` w.r.t. ``model``: refined solutions within the joint limits
        and tolerances, deduplicated; branches that do not reach the tolerance inside
        their box are dropped.
    """
    options = options or IKOptions()
    T_all, batch, position_only = prepare_targets(targets)
    n = T_all.shape[0]
    cond, assumed = resolve_conditions([model], cond, n, approach)
    ikm = as_ik_model(model, cond=cond, robot=robot, jacobian=jacobian, n_targets=n)
    q_init, valid = _initial(initial, n, ikm.dof)
    rows, slots = valid.nonzero(as_tuple=True)
    q0 = q_init[rows, slots]
    half = _checked_box(box).expand(ikm.dof)
    lower = torch.maximum(q0 - half, ikm.lower)
    upper = torch.minimum(q0 + half, ikm.upper)
    t0 = time.perf_counter()
    settings = options.lm_settings(position_only)
    out, ok, pos, ori = solve_and_check(
        ikm, q0, rows, T_all, (lower, upper), settings, position_only, options
    )
    k = q_init.shape[1]
    q, pos, ori = _scatter(n, k, rows, slots, out.q, pos, ori)
    okf = torch.zeros(n, k, dtype=torch.bool)
    okf[rows, slots] = ok
    score = pos.nan_to_num(math.inf) / options.tol_mm
    if not position_only:
        score = score + ori.nan_to_num(math.inf) / options.tol_deg
    keep = distinct_mask(q, okf, score, ikm.revolute, options.revolute_tol, options.prismatic_tol)
    info = {
        "assumed": assumed,
        "branches": int(valid.sum()),
        "mean_iterations": float(out.iterations.double().mean()) if rows.numel() else 0.0,
        "evaluations": out.evaluations,
        "seconds": time.perf_counter() - t0,
        "autograd": not ikm.analytic,
    }
    return make_result([pack(q, pos, ori, keep)], batch, ikm, options, position_only, info)


def solve_ik_two_stage(
    cheap,
    expensive,
    targets: Tensor,
    *,
    seeds: int | Tensor = 64,
    extra_seeds: Tensor | None = None,
    box: float | Tensor = DEFAULT_BOX,
    coarse_tol_mm: float = COARSE_TOL_MM,
    coarse_tol_deg: float = COARSE_TOL_DEG,
    cond: Conditions | None = None,
    robot: Robot | None = None,
    jacobian: Callable | None = None,
    options: IKOptions | None = None,
    progress: Callable[[int], None] | None = None,
    fallback: bool = True,
    approach: Approach = None,
) -> IKResult:
    """All branches on ``cheap``, each refined on ``expensive`` (paper Fig. 3).

    Args:
        cheap: a model with an analytic Jacobian: ``Robot`` or ``ExtendedModel`` without
            networks (e.g. the nominal robot with the calibrated base/tool frames).
        expensive: the accurate model, in the same frames as ``cheap``.
        targets: ``(*B, 4, 4)`` poses or ``(*B, 3)`` points [m].
        seeds, extra_seeds: first-stage start configurations (see ``solve_ik``).
        box: refinement box half-width [rad or m] around each first-stage branch.
        coarse_tol_mm, coarse_tol_deg: first-stage tolerances [mm, deg]: a branch of
            the cheap model only has to be near the accurate model's.
        cond: conditions per flat target, passed to both models.
        robot: limits of a callable ``expensive`` (default: the cheap model's robot).
        jacobian: analytic Jacobian of ``expensive`` (default: autograd).
        options: final tolerances and iteration budget.
        progress: called with the number of targets finished by the first stage.
        fallback: solve the targets that the refinement leaves without any solution
            directly on ``expensive`` (all seeds plus the first-stage branches). Near
            singular configurations and at the border of the cheap model's workspace
            (a target the cheap model cannot reach exactly) the accurate solution can
            lie far outside the box of every cheap branch.
        approach: backlash approach direction of both models (:mod:`~hybrid_pk.ik.
            conditions`; default ``cond.direction``, else the mid-play model, said in
            an :class:`~hybrid_pk.ik.conditions.IKAssumption` warning).

    Returns:
        :class:`IKResult` w.r.t. ``expensive``; ``info["stage1"]`` describes stage one,
        ``info["fallback_targets"]`` counts the targets solved directly.
    """
    options = options or IKOptions()
    robot = robot or _robot_of(cheap)
    n_flat = prepare_targets(targets)[0].shape[0]
    cond, assumed = resolve_conditions([cheap, expensive], cond, n_flat, approach)
    if robot is None and not isinstance(expensive, Robot | ExtendedModel):
        raise HybridPKError("two-stage IK on a callable model needs robot= or a Robot cheap model")
    _checked_box(box)  # before the first stage's work
    coarse = _coarse_options(options, coarse_tol_mm, coarse_tol_deg)
    first = solve_ik(
        cheap,
        targets,
        seeds=seeds,
        extra_seeds=extra_seeds,
        cond=cond,
        robot=robot,
        options=coarse,
        progress=progress,
    )
    result = refine_ik(
        expensive,
        targets,
        first,
        box=box,
        cond=cond,
        robot=robot,
        jacobian=jacobian,
        options=options,
    )
    info = {**result.info, "stage1": {**first.info, "branches": int(first.valid.sum())}}
    info["assumed"] = assumed
    failed = result.failed.reshape(-1).nonzero()[:, 0]
    info["fallback_targets"] = int(failed.numel()) if fallback else 0
    if fallback and failed.numel():
        direct = _solve_directly(
            expensive, targets, failed, first, seeds=seeds, cond=cond, robot=robot,
            jacobian=jacobian, options=options,
        )  # fmt: skip
        result = _replace_targets(result, failed, direct)
    return replace(result, info=info)


def _coarse_options(options: IKOptions, tol_mm: float, tol_deg: float) -> IKOptions:
    """First-stage options: branches of the cheap model accepted up to the coarse
    tolerances, but polished as finely as the final ones (a sloppy branch would be a
    duplicate of another)."""
    polish = options.lm_settings(False)
    return replace(
        options,
        tol_mm=tol_mm,
        tol_deg=tol_deg,
        polish_mm=polish.accept_position * 1e3,
        polish_deg=math.degrees(polish.accept_rotation),
    )


def _solve_directly(expensive, targets, failed: Tensor, first: IKResult, **kwargs) -> IKResult:
    """The targets ``failed`` (flat indices) solved on ``expensive`` itself: all seeds
    plus the first-stage branches as start configurations."""
    T_all, _, position_only = prepare_targets(targets)
    n, k1, dof = T_all.shape[0], first.q.shape[-2], first.q.shape[-1]
    cond = kwargs.pop("cond")
    return solve_ik(
        expensive,
        T_all[failed, :3, 3] if position_only else T_all[failed],
        extra_seeds=first.q.reshape(n, k1, dof)[failed],
        cond=None if cond is None else cond.subset(failed),
        **kwargs,
    )


def _replace_targets(result: IKResult, index: Tensor, other: IKResult) -> IKResult:
    """``result`` with the flat targets ``index`` taken from ``other`` (same order)."""
    batch = result.batch_shape
    n = math.prod(batch)
    parts = []
    for mine, theirs in (
        (result.q, other.q),
        (result.position_error_mm, other.position_error_mm),
        (result.orientation_error_deg, other.orientation_error_deg),
        (result.valid, other.valid),
    ):
        tail = mine.shape[len(batch) + 1 :]
        a = mine.reshape(n, mine.shape[len(batch)], *tail)
        b = theirs.reshape(index.numel(), theirs.shape[-1 - len(tail)], *tail)
        k = max(a.shape[1], b.shape[1])
        fill = False if mine.dtype == torch.bool else math.nan
        out = a.new_full((n, k, *tail), fill)
        out[:, : a.shape[1]] = a
        out[index] = fill
        out[index, : b.shape[1]] = b
        parts.append(out.reshape(*batch, k, *tail))
    q, pos, ori, valid = parts
    closest = {}
    for name in ("closest_mm", "closest_deg", "near_singular", "smallest_singular_value"):
        mine, theirs = getattr(result, name), getattr(other, name)
        if mine is not None and theirs is not None:
            closest[name] = mine.reshape(n).index_copy(0, index, theirs.reshape(-1)).reshape(batch)
    return replace(
        result, q=q, position_error_mm=pos, orientation_error_deg=ori, valid=valid, **closest
    )


def wang_baseline(
    cheap,
    expensive,
    targets: Tensor,
    *,
    seeds: int | Tensor = 64,
    cond: Conditions | None = None,
    robot: Robot | None = None,
    options: IKOptions | None = None,
) -> IKResult:
    """Wang et al.'s method (paper section 5): one target correction, cheap IK twice.

    For each branch ``q0`` of the cheap IK, the target is corrected by the accurate
    model's deviation at ``q0`` (``p' = p - (p_acc(q0) - p_cheap(q0))``,
    ``R' = R_cheap(q0) R_acc(q0)^T R``) and the cheap IK is solved again for it from
    ``q0``.

    Returns:
        :class:`IKResult` whose ``valid`` slots are the branches whose second cheap IK
        converged, with their errors w.r.t. ``expensive`` (not filtered by the
        tolerances: ``within_tolerance`` says which meet them).
    """
    options = options or IKOptions()
    robot = robot or _robot_of(cheap)
    T_all, batch, position_only = prepare_targets(targets)
    n = T_all.shape[0]
    first = solve_ik(cheap, targets, seeds=seeds, cond=cond, robot=robot, options=options)
    cheap_m = as_ik_model(cheap, cond=cond, robot=robot, n_targets=n)
    acc_m = as_ik_model(expensive, cond=cond, robot=robot, n_targets=n)
    q_init, valid = _initial(first, n, cheap_m.dof)
    rows, slots = valid.nonzero(as_tuple=True)
    q0 = q_init[rows, slots]
    with torch.no_grad():
        T_cheap = cheap_m.pose(q0, rows).to(F64)
        T_acc = acc_m.pose(q0, rows).to(F64)
    T_t = T_all[rows]
    T_c = T_t.clone()
    T_c[:, :3, 3] = T_t[:, :3, 3] - (T_acc[:, :3, 3] - T_cheap[:, :3, 3])
    if not position_only:
        R_fix = T_cheap[:, :3, :3] @ T_acc[:, :3, :3].transpose(-1, -2)
        T_c[:, :3, :3] = R_fix @ T_t[:, :3, :3]
    with torch.no_grad():
        out = batched_levenberg_marquardt(
            cheap_m.evaluate,
            q0,
            rows,
            T_c,
            cheap_m.lower,
            cheap_m.upper,
            options.lm_settings(position_only),
            cheap_m.revolute,
        )
    solved, _, _ = check_solutions(cheap_m, out.q, rows, T_c, position_only, options)
    _, pos, ori = check_solutions(acc_m, out.q, rows, T_t, position_only, options, candidate=solved)
    k = q_init.shape[1]
    q, pos, ori = _scatter(n, k, rows, slots, out.q, pos, ori)
    kept = torch.zeros(n, k, dtype=torch.bool)
    kept[rows, slots] = solved
    info = {"branches": int(valid.sum()), "solved": int(solved.sum())}
    return make_result([pack(q, pos, ori, kept)], batch, acc_m, options, position_only, info)

"""Test statistics of the diagnosis: weighted sums of squares, structure (the F
distribution: :mod:`hybrid_pk.distributions`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybrid_pk.calibration.fit import FitResult, predicted_poses
from hybrid_pk.calibration.problem import Problem
from hybrid_pk.calibration.robust import robust_cost, row_distances
from hybrid_pk.calibration.work import count as count_work
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel

__all__ = [
    "along_joints",
    "along_joints_text",
    "holdout_score",
    "in_link_1",
    "neighbour_structure",
    "residual_vectors",
    "weighted_residual",
    "weighted_ssr",
]


def equivalent_angle_error(J: Tensor, r: Tensor, min_lever: float) -> tuple[Tensor, Tensor, Tensor]:
    """Per row, the angle error of one joint that best explains the residual ``r (N, 3)``
    from that joint's point Jacobian ``J (N, 3)``: ``e = J · r / |J|²`` (units of ``r``
    over those of ``J``), its weight ``|J|²``, and the rows where ``|J|`` is at least
    ``min_lever`` times its median (the others carry no information on the joint)."""
    w = (J * J).sum(-1)
    e = (J * r).sum(-1) / w.clamp_min(1e-300)
    return e, w, w > min_lever**2 * w.median()


def weighted_residual(
    model: ExtendedModel, data: MeasuredData, cond: Conditions, res: FitResult
) -> Tensor:
    """Residuals of ``model`` on ``data`` under ``res``'s noise weights (the poses kept
    where this point was evaluated on these rows: :func:`.fit.predicted_poses`)."""
    problem = Problem(model, data, cond, (), res.sigma_pos_mm, res.sigma_rot_rad or 1.0)
    count_work(data.n)  # a residual pass, kept poses or not: the budgets stay as they were
    return problem.residual_of_pose(predicted_poses(model, data.q, cond))


def weighted_ssr(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    res: FitResult,
    position_only: bool = False,
) -> float:
    """Sum of squared residuals of ``model`` on ``data`` under ``res``'s noise weights
    (``position_only``: of the position components alone); for a robust fit the robust
    cost of its loss, on the same scale (see :func:`~hybrid_pk.calibration.robust.robust_cost`)."""
    r = weighted_residual(model, data, cond, res)
    pose = data.quat is not None and not position_only
    if position_only:
        r = r[: 3 * data.n]  # the fit's layout: every row's position, then rotation
    if res.robust is not None:
        return robust_cost(row_distances(r, data.n), 6 if pose else 3, res.robust)
    return float(r @ r)


def holdout_score(
    model: ExtendedModel, test: MeasuredData, cond: Conditions, res: FitResult
) -> float:
    """Hold-out sum of squares per row under the fit's noise weights (position and
    rotation)."""
    return weighted_ssr(model, test, cond, res) / max(test.n, 1)


def residual_vectors(model: ExtendedModel, data: MeasuredData, cond: Conditions) -> Tensor:
    """``(N, 3)`` position [mm] (and rotation [mrad]: ``(N, 6)``) residuals per row."""
    problem = Problem(model, data, cond, (), 1.0, 1e-3)  # mm and mrad
    with torch.no_grad():
        r = problem.residual(torch.zeros(0, dtype=torch.float64))
    k = 6 if data.quat is not None else 3
    return r.reshape(k // 3, data.n, 3).permute(1, 0, 2).reshape(data.n, k)


def neighbour_structure(
    residual: Tensor, q: Tensor, lower: Tensor, upper: Tensor
) -> tuple[bool, float]:
    """Do neighbouring configurations share their residuals? (smooth leftover error)

    Returns ``(structured, correlation)``: the correlation of each row's residual with
    its nearest neighbour's in normalised joint space, and whether it exceeds both
    0.1 and 4 sigma of its no-structure distribution.
    """
    n = residual.shape[0]
    if n < 20:  # the 4-sigma bar 4 / sqrt(n k) is then 0.37 or more: too coarse a test
        return False, 0.0
    span = torch.where(torch.isfinite(upper - lower), upper - lower, 2 * math.pi)
    x = (q - lower.where(torch.isfinite(lower), -math.pi)) / span
    nn_idx = _nearest_other(x)
    a = residual.reshape(n, -1)
    a = a - a.mean(0)
    b = a[nn_idx]
    corr = float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-300))
    # Under no structure the correlation is ~N(0, 1/(n*k)); 4 sigma is "structured".
    threshold = 4.0 / math.sqrt(a.numel())
    # below 0.1 neighbours share under 1 % of the variance (r^2): significant on large
    # data, yet no smooth error worth naming
    return corr > max(threshold, 0.1), corr


# Rows of the distance matrix per block in the nearest-neighbour search: a block of
# 2048 x 50,000 float64 distances is 0.8 GB, what a calibration PC spares.
NEIGHBOUR_BLOCK = 2048


def _nearest_other(x: Tensor) -> Tensor:
    """Index of each row's nearest other row ``(n,)``, blocks of rows at a time (the
    ``n x n`` distance matrix of 50,000 rows would need 20 GB)."""
    n = x.shape[0]
    out = torch.empty(n, dtype=torch.long)
    for start in range(0, n, NEIGHBOUR_BLOCK):
        rows = slice(start, min(start + NEIGHBOUR_BLOCK, n))
        d = torch.cdist(x[rows], x)
        d[torch.arange(d.shape[0]), torch.arange(rows.start, rows.stop)] = math.inf
        out[rows] = d.argmin(1)
    return out


# Rows per bin of a joint when the left error is binned along it: the mean of 50 rows
# has a standard error of 1/7 of their spread, so a bin's mean shows a trend the size
# of the spread and pure noise adds (bins - 1) / n to the share (stated as "chance").
ROWS_PER_BIN = 50
# at most this many bins: 1/20 of a joint's range is what "along the joint" resolves
# (finer patterns are periodic errors, which the cyclic screen tests)
MAX_BINS = 20


def in_link_1(model: ExtendedModel, data: MeasuredData, cond: Conditions, residual: Tensor):
    """The position residuals ``residual (n, >= 3)`` (measurement frame) in the axes of
    the first link, the frame joint 1 turns: an error that turns with the arm is the
    same there at every joint-1 angle."""
    group = None if cond.group is None or model.base.sets == 1 else cond.group
    with torch.no_grad():
        R_base = model.base.matrix(group)[..., :3, :3].to(residual.dtype)
        R_1 = model.robot.link_frames(data.q)[..., 0, :3, :3].to(residual.dtype)
    R = R_base @ R_1  # one base rotation, or one per row: broadcast either way
    return (R.transpose(-1, -2) @ residual[:, :3, None])[..., 0]


def along_joints(residual: Tensor, q: Tensor, names) -> list[dict]:
    """How much of the left position error varies along each joint alone: the share of
    its variance (``residual (n, >= 3)``, position first, best in the first link's axes:
    :func:`in_link_1`) that the means of equal-count bins of that joint's angle explain,
    and the share pure noise would give ("chance", ``(bins - 1) / n``). Largest share
    first; empty with fewer than two bins' rows. A share far above chance on the first
    joint says the error is not the same at every turn of the arm (not equivariant to
    joint 1)."""
    n = residual.shape[0]
    bins = min(MAX_BINS, n // ROWS_PER_BIN)
    if bins < 2:
        return []
    r = residual[:, :3] - residual[:, :3].mean(0)
    total = float(r.pow(2).sum())
    # no spread beyond the mean's round-off (~1e-16 of the error, squared 1e-32; a real
    # spread of even 1e-12 of it clears 1e-24): nothing varies along any joint
    flat = total <= 1e-24 * float(residual[:, :3].pow(2).sum())
    out = []
    levels = torch.linspace(0, 1, bins + 1, dtype=q.dtype)[1:-1]
    for j, name in enumerate(names):
        # bins at the angle's quantiles; equal angles share a bin (a grid's repeated
        # values), a joint that does not move is one bin and explains nothing
        angle = q[:, j].contiguous()
        b = torch.bucketize(angle, torch.quantile(angle, levels), right=True)
        counts = torch.bincount(b, minlength=bins).to(r.dtype)
        sums = torch.zeros(bins, 3, dtype=r.dtype).index_add_(0, b, r)
        means = sums / counts.clamp_min(1)[:, None]
        explained = float((counts[:, None] * means.pow(2)).sum())
        used = int((counts > 0).sum())
        share = 0.0 if flat else explained / total
        out.append({"joint": name, "share": share, "chance": (used - 1) / n})
    return sorted(out, key=lambda e: -e["share"])


def along_joints_text(entries: list[dict] | None) -> str | None:
    """``joint 33 %, joint 20 %, ... of its variance (binned by each joint alone; noise
    alone ~1.4 %)`` from :func:`along_joints`' entries; None without them."""
    if not entries:
        return None
    shares = ", ".join(f"{e['joint']} {100 * e['share']:.0f} %" for e in entries)
    chance = max(e["chance"] for e in entries)
    return (
        f"{shares} of its variance (the means of each joint's angle bins alone; "
        f"noise alone ~{100 * chance:.1f} %)"
    )

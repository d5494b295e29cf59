"""A refit that starts next to a Jacobian already built (the diagnosis' score of the
candidate it adds), and the parameter covariance of a fit.

The diagnosis scores every candidate from one Jacobian at the current model, then
refits the best one from the Gauss–Newton start that Jacobian predicts. Its columns
of the current model and of that candidate are the refit's Jacobian at a point some
std away: the refit's first step is taken with it (a chord step: one residual
evaluation, no Jacobian), which ends where the Jacobian's change over the way
(1e-4 - 1e-3 relative on the UR10 series) puts it. One exact Jacobian there, the one
the covariance needs anyway, then checks the optimum: its Gauss–Newton step must
lower the cost by less than ``NEXT_STEP_STD^2`` per residual (move the parameters by
< 0.01 std) or be predicted to after that step, the rule that stops every LM fit;
if not, LM goes on from there with exact Jacobians (the check's the first).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.covariance import svd_covariance
from hybrid_pk.calibration.frames import PriorRows
from hybrid_pk.calibration.problem import ParamBlock, Problem
from hybrid_pk.calibration.robust import rotation_noise
from hybrid_pk.calibration.work import count as count_work

# Directions of a Jacobian (columns at unit norm) weaker than this share of the
# strongest are exact degeneracies: a QR leaves them at round-off, ~ sqrt(m) eps ~
# 1e-13; 1e-10 lies far above that and far below any direction data determine.
NULL_SHARE = 1e-10

__all__ = ["Linearisation", "chord_passes", "covariance_fields", "settled_factor"]


@dataclass
class Linearisation:
    """``[J r]`` chunks of a problem on the same rows (as :meth:`Problem.augmented_chunks`
    yields them, no ``extra`` rows), its blocks and the noise levels it was built under;
    ``pass_sigmas`` is set while the last LM pass of a fit is the one that used it."""

    chunks: list[Tensor]
    blocks: tuple[ParamBlock, ...]
    sigmas: tuple[float, float]
    pass_sigmas: tuple[float, float] | None = None  # those of the last pass it ran
    pass_drop: float = 0.0  # and how much that pass lowered its cost
    # the data residuals of the refit's start and the noise levels they are under (no
    # row weights): its first residual, rescaled (:func:`chord_passes`); None: computed
    start: tuple[Tensor, tuple[float, float]] | None = None

    @classmethod
    def kept_by(cls, problem: Problem, blocks: tuple[ParamBlock, ...]) -> Linearisation:
        """The chunks ``problem`` kept while it was linearised (``keep=True``), with
        ``blocks`` and the noise levels it was built under (those of the shared point
        the chunks came from, with all its columns, where they did)."""
        if problem.kept_blocks is not None:
            return cls(problem.kept, problem.kept_blocks, problem.kept_sigmas)
        return cls(problem.kept, blocks, (problem.sigma_pos_mm, problem.sigma_rot_rad))

    def columns(self, blocks: tuple[ParamBlock, ...]) -> Tensor | None:
        """Indices of ``blocks``' columns among the chunks' (None: one is missing)."""
        where, start = {}, 0
        for b in self.blocks:
            where[b.label] = (start, b.size)
            start += b.size
        idx = []
        for b in blocks:
            at = where.get(b.label)
            if at is None or at[1] != b.size:
                return None
            idx.append(torch.arange(at[0], at[0] + b.size))
        return torch.cat(idx) if idx else None


def chord_passes(problem: Problem, near: Linearisation):
    """``(residual, normal)`` for :func:`.least_squares.levenberg_marquardt`: the
    problem's own residuals, normal equations from ``near``'s Jacobian (rescaled to
    this problem's noise levels) and the exact residuals; None when ``near`` lacks a
    block of the problem or was built on other rows."""
    cols = near.columns(problem.blocks)
    per_row = 3 if problem.R_meas is None else 6
    near.pass_sigmas = None
    if cols is None or sum(M.shape[0] for M in near.chunks) != per_row * problem.data.n:
        return None
    near.pass_sigmas = (problem.sigma_pos_mm, problem.sigma_rot_rad)
    to_pos = near.sigmas[0] / problem.sigma_pos_mm  # columns scale as 1 / sigma
    to_rot = near.sigmas[1] / problem.sigma_rot_rad
    parts, start = [], 0  # (pos residual slice, rot residual slice, J rows)
    n_rows = problem.data.n
    for M in near.chunks:
        n_c = M.shape[0] // per_row
        J = M[:, cols]  # a copy: the columns gathered
        J[: 3 * n_c] *= to_pos
        J[3 * n_c :] *= to_rot
        rot = slice(3 * (n_rows + start), 3 * (n_rows + start + n_c)) if per_row == 6 else None
        parts.append((slice(3 * start, 3 * (start + n_c)), rot, J))
        start += n_c
    A0 = sum(J.T @ J for _, _, J in parts)
    last: list = [None, None]  # the latest (theta, residual): LM asks for it twice
    if near.start is not None and problem.row_weights is None:
        last[:] = [torch.zeros_like(problem.x0), _rescaled(problem, *near.start)]
        count_work(problem.data.n)  # counted as if evaluated: the budgets stay as they were
    near.start = None  # for this pass only
    costs: list[float] = [] if last[0] is None else [float(last[1] @ last[1])]
    near.pass_drop = 0.0

    def residual(theta: Tensor) -> Tensor:
        if last[0] is None or not torch.equal(last[0], theta):
            with torch.no_grad():  # values only (a frame left out may carry a gradient)
                last[0], last[1] = theta.clone(), problem.residual(theta)
            costs.append(float(last[1] @ last[1]))  # LM keeps the lowest: the pass's drop
            near.pass_drop = costs[0] - min(costs)
        return last[1]

    def normal(theta: Tensor) -> tuple[Tensor, Tensor, float]:
        r = residual(theta)
        g = torch.zeros_like(theta)
        for pos, rot, J in parts:
            rc = r[pos] if rot is None else torch.cat([r[pos], r[rot]])
            g.addmv_(J.T, rc)
        A = A0
        if problem.extra is not None:  # the prior's rows: exact and linear
            r_x, J_x = problem.extra(theta)
            A, g = A0 + J_x.T @ J_x, g + J_x.T @ r_x
        return A, g, float(r @ r)

    return residual, normal


def _rescaled(problem: Problem, r: Tensor, sigmas: tuple[float, float]) -> Tensor:
    """The problem's residuals at its start from the data residuals ``r`` there under
    noise levels ``sigmas`` (rows as :meth:`Problem.residual`, no extra rows):
    rescaled to the problem's levels, the extra rows appended."""
    n3 = 3 * problem.data.n
    out = r.clone()
    out[:n3] *= sigmas[0] / problem.sigma_pos_mm
    out[n3:] *= sigmas[1] / problem.sigma_rot_rad
    if problem.extra is not None:
        out = torch.cat([out, problem.extra(torch.zeros_like(problem.x0))[0]])
    return out


def settled_factor(
    problem: Problem, step_std: float, near: Linearisation, max_iter: int
) -> tuple[Tensor, bool]:
    """Gauss–Newton from the chord's end with exact Jacobians, each factored (``R`` of
    ``[J r]``, what the covariance needs), until the optimum of the chord's pass
    (noise levels ``near.pass_sigmas``) is reached within ``step_std`` std, at most
    ``max_iter`` Jacobians. Returns the last ``R`` (the problem's noise levels) and
    whether it settled (if not, LM goes on from where ``R`` was built; the point is
    written into the model either way).

    A Jacobian's Gauss–Newton step would lower the pass's cost by its decrement
    ``d``; below ``step_std^2`` per residual (the cost is ~1 per residual: a move <
    ``step_std`` std) the point stays. Else the step is taken (if it lowers the
    cost), and it is the last when the drop after it is predicted below that too, by
    the rule that stops an LM pass: drops shrink by the ratio of the last two, ``d``
    against the previous step's drop (the chord's first). The covariance keeps ``R``:
    a step < 1 std changes the Jacobian by ~1e-6 relative. (A fit keeps a pass's
    optimum when the re-estimated noise differs by < 5 %, and states its covariance
    under the re-estimate: ``R``'s levels.)"""
    sig_p, sig_r = near.pass_sigmas
    to_pass = (problem.sigma_pos_mm / sig_p, problem.sigma_rot_rad / sig_r)
    theta, previous, n = torch.zeros_like(problem.x0), near.pass_drop, problem.x0.numel()
    settled = False
    for _ in range(max_iter):
        R, R_pass = _factors(problem, theta, to_pass)
        at = theta  # where R was built
        z, cost = R_pass[:n, n], float(R_pass[:, n] @ R_pass[:, n])
        step = _gauss_newton(R_pass[:n, :n], z)
        left = z + R_pass[:n, :n] @ step
        decrement = float(z @ z - left @ left)  # what the linear step lowers the cost by
        tol = step_std**2 * cost / problem.n_residuals
        if decrement < tol:
            settled = True
            break
        with torch.no_grad():
            r = _scaled(problem, problem.residual(theta + step), to_pass)
        if float(r @ r) >= cost:
            break
        theta, last = theta + step, decrement**2 / max(previous, 1e-300)
        previous = cost - float(r @ r)
        if last < tol:
            settled = True
            break
    problem.write(theta if settled else at)
    return R, settled


def _gauss_newton(R: Tensor, z: Tensor) -> Tensor:
    """The step ``d`` minimising ``|z + R d|`` in the directions the columns determine:
    at unit column norm, singular values below ``NULL_SHARE`` of the largest are exact
    degeneracies (two parameters the data cannot tell apart), whose ``z`` is round-off
    and left alone."""
    norms = R.norm(dim=0)
    unit = torch.where(norms > 0, norms, torch.ones_like(norms))
    fit = torch.linalg.lstsq(R / unit, -z[:, None], rcond=NULL_SHARE, driver="gelsd")
    return fit.solution[:, 0] / unit


def _factors(problem: Problem, theta: Tensor, to_pass: tuple[float, float]):
    """``R`` of ``[J r]`` at ``theta`` under the problem's noise levels and under the
    pass's (rows scaled by ``to_pass``: position, rotation). The position rows, the
    rotation rows and the prior's (which do not scale with the noise) are factored
    apart, once: each level's ``R`` is then the factor of the three small ``R``s, scaled."""
    per_row = 3 if problem.R_meas is None else 6
    parts: list[Tensor | None] = [None, None, None]  # position, rotation, prior rows
    data_rows = per_row * problem.data.n
    for M in problem.augmented_chunks(theta):
        if data_rows > 0:
            n_c = M.shape[0] // per_row
            parts[0] = _appended(parts[0], M[: 3 * n_c])
            if per_row == 6:
                parts[1] = _appended(parts[1], M[3 * n_c :])
            data_rows -= M.shape[0]
        else:
            parts[2] = _appended(parts[2], M)

    def level(a: float, b: float) -> Tensor:
        scaled = [f * P for f, P in zip((a, b, 1.0), parts, strict=True) if P is not None]
        return torch.linalg.qr(torch.cat(scaled), mode="r").R

    return level(1.0, 1.0), level(*to_pass)


def _scaled(problem: Problem, r: Tensor, to_pass: tuple[float, float]) -> Tensor:
    """The problem's residuals ``r`` under the pass's noise levels."""
    n3 = 3 * problem.data.n
    out = r.clone()
    out[:n3] *= to_pass[0]
    if problem.R_meas is not None:
        out[n3 : 2 * n3] *= to_pass[1]
    return out


def first_passes(problem: Problem, start: Linearisation | Tensor):
    """``(residual, normal)`` of an LM pass that starts from ``start``: a nearby
    Jacobian (:func:`chord_passes`), or the factor ``R`` of ``[J r]`` at the start
    under this problem's noise levels, whose normal equations serve the first step
    (the rest exact); None: the problem's own."""
    if isinstance(start, Linearisation):
        return chord_passes(problem, start)
    n = problem.x0.numel()
    J, z = start[:, :n], start[:, n]
    first = [(J.T @ J, J.T @ z, float(z @ z))]

    def normal(theta: Tensor) -> tuple[Tensor, Tensor, float]:
        return first.pop() if first else problem.normal_equations(theta)

    return problem.residual, normal


def _appended(R: Tensor | None, M: Tensor) -> Tensor:
    """The triangular factor of ``R``'s rows and ``M``'s."""
    return torch.linalg.qr(M if R is None else torch.cat([R, M]), mode="r").R


def residual_variance(problem: Problem, zz: float, n_par: int) -> float:
    """The variance the covariance is scaled by: the weighted residuals' square sum
    ``zz`` per degree of freedom. Orientation rows whose noise level sits at its floor
    (:func:`~hybrid_pk.calibration.robust.rotation_noise`: orientations exact to the
    position noise over ``LEVER_M``, as a simulation without orientation noise gives)
    are left out: their weighted residuals are below one by the floor's making, and
    with as many orientation as position rows they would scale every position-made
    standard deviation by sqrt(1/2). (The directions only they determine keep the
    floor's larger variance: a bound, not an estimate.)"""
    n_obs, n = problem.n_residuals, problem.data.n
    floor = rotation_noise(0.0, problem.sigma_pos_mm)
    if problem.R_meas is None or problem.sigma_rot_rad > floor * (1 + 1e-9):
        return zz / max(n_obs - n_par, 1)
    with torch.no_grad():
        rot = problem.residual(torch.zeros_like(problem.x0))[3 * n : 6 * n]
    return (zz - float(rot @ rot)) / max(n_obs - 3 * n - n_par, 1)


def covariance_fields(problem: Problem, prior: PriorRows | None, R: Tensor | None) -> dict:
    """Standard deviations, correlations and singular values at the problem's point,
    and the normal matrix ``J^T J`` (scaled parameters) they come from; ``R``: the
    factor of ``[J r]`` there when already built."""
    if R is None:
        R = problem.r_factor(torch.zeros_like(problem.x0))
    n_par = problem.x0.numel()
    J, z = R[:, :n_par], R[:, n_par]
    n_obs = problem.n_residuals
    s2 = residual_variance(problem, float(z @ z), n_par)
    normal = J.T @ J
    svd = svd_covariance(J, n_obs, s2)
    std = svd["cov"].diagonal().clamp_min(0).sqrt() * problem.scale
    sv = svd["singular_values"]
    cost = float(z @ z)
    if prior is not None:  # the cost of the data alone (tests compare it with refits')
        r_prior = prior(torch.zeros_like(problem.x0))[0]
        cost -= float(r_prior @ r_prior)
    return {
        "std": std,
        "corr": svd["corr"],
        "singular_values": sv,
        "singular_vectors": svd["singular_vectors"],
        "condition": float(sv[0] / sv[-1].clamp_min(1e-300)),
        "n_obs": n_obs,
        "normal_matrix": normal,
        "cost": cost,
    }

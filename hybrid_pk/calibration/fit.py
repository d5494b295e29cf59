"""Identification: fit frames and effect values of an :class:`ExtendedModel` to data.

The residuals and their Jacobian are :class:`~hybrid_pk.calibration.problem.Problem`'s:
position [mm] and small-angle rotation [rad] differences, each divided by its noise
level so that mm and rad weigh by their evidence. Noise levels are estimated from the
fit itself (a second, re-weighted pass), which also makes the parameter covariance
``(J^T J)^-1`` meaningful (computed from the SVD of ``J``: :mod:`.covariance`).

Parameters are fitted in units of their ``scale`` (1 mm, 1 mrad, 1 µrad/Nm, …) so
the normal equations are well conditioned.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.chord import (
    Linearisation,
    covariance_fields,
    first_passes,
    settled_factor,
)
from hybrid_pk.calibration.covariance import correlated_pairs, parameter_names, undetermined_groups
from hybrid_pk.calibration.frame_hold import held_prior, join_rows
from hybrid_pk.calibration.frames import FramePriors, PriorRows, prior_centres, prior_residual
from hybrid_pk.calibration.identifiability import FrameReport, frame_report, skipped_frame_report
from hybrid_pk.calibration.least_squares import levenberg_marquardt
from hybrid_pk.calibration.poses import initialise_frames, model_errors, predicted_poses
from hybrid_pk.calibration.problem import ParamBlock, Problem, param_blocks
from hybrid_pk.calibration.robust import irls_update, reestimated_noise, row_weights_vector
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.threads import fit_work

__all__ = [
    "FitResult",
    "fit",
    "initialise_frames",
    "model_errors",
    "predicted_poses",
]

# First-pass noise levels, replaced by the estimates of the re-weighted pass.
DEFAULT_SIGMA_POS_MM = 0.05
DEFAULT_SIGMA_ROT_RAD = 1e-4
# A fit stops once its next LM step would lower the noise-normalised cost by < this^2:
# it would move the parameters by < 0.01 std (a drop d is sqrt(d) std), 10x below any test.
NEXT_STEP_STD = 0.01
# Most passes of a robust fit (each re-estimates the noise and re-weights the rows).
ROBUST_PASSES = 8


@dataclass(frozen=True)
class FitResult:
    """Outcome of :func:`fit` (values already written into the model).

    Attributes:
        blocks: fitted parameter tensors, in the order of ``x``.
        x, std: ``(n,)`` values and 1-sigma standard deviations (physical units).
        corr: ``(n, n)`` correlation matrix of the estimates.
        singular_values: of the Jacobian with unit-norm columns (identifiability).
        singular_vectors: ``(n, n)`` its right singular vectors, as rows.
        condition: ratio of largest to smallest singular value.
        sigma_pos_mm, sigma_rot_rad: per-coordinate noise estimated from residuals.
        position_mm, orientation_deg: per-sample errors after the fit.
        n_obs, n_params: residual and parameter counts.
        iterations, converged: LM iterations over all passes; the last pass converged.
        normal_matrix: ``(n, n)`` ``J^T J`` of the final weighted residuals in scaled
            parameters (``x / scale``): the information of linearised updates.
        robust: the robust loss of the fit, or None (least squares).
        weights: ``(N,)`` robust weights of the rows (None for least squares).
        frame_report: which frame components the data do not determine, and frame
            plausibility warnings (only with ``covariance`` and ``report_frames``).
        priors: the known frames and frame prior the fit used.
        cost: their sum of squares at the solution (with the covariance only).
    """

    blocks: tuple[ParamBlock, ...]
    x: Tensor
    std: Tensor
    corr: Tensor
    singular_values: Tensor
    condition: float
    sigma_pos_mm: float
    sigma_rot_rad: float | None
    position_mm: Tensor
    orientation_deg: Tensor | None
    n_obs: int
    n_params: int
    iterations: int
    converged: bool
    normal_matrix: Tensor | None = None
    cost: float | None = None
    robust: str | None = None
    weights: Tensor | None = None
    frame_report: FrameReport | None = None
    priors: FramePriors | None = None
    singular_vectors: Tensor | None = None

    def settings(self) -> dict:
        """``fit()`` keyword arguments that refit under this fit's frame prior and
        robust loss, starting from its row weights (same rows)."""
        return {"frames": self.priors, "robust": self.robust, "weights": self.weights}

    @property
    def ssr_weighted(self) -> float:
        """Sum of squared noise-normalised residuals (for F-tests and criteria)."""
        pos = (self.position_mm**2).sum() / self.sigma_pos_mm**2
        if self.orientation_deg is None or self.sigma_rot_rad is None:
            return float(pos)
        rot = (torch.deg2rad(self.orientation_deg) ** 2).sum() / self.sigma_rot_rad**2
        return float(pos + rot)

    def correlated_pairs(self, threshold: float) -> list[tuple[str, str, str, str, float]]:
        """Parameter pairs of different effects/frames whose estimates are correlated
        at ``|r| >= threshold`` or undetermined (NaN): ``(group_a, name_a, group_b,
        name_b, r)`` in parameter order, where a group is a block label up to its first
        ``.`` (``base_frame``) and a name adds the component (``link_length:joint_3[2]``)."""
        return correlated_pairs(*parameter_names(self.blocks), self.corr, threshold)

    def undetermined(self, max_condition: float) -> list[list[str]]:
        """Names of the parameter groups these data cannot separate (a trade-off whose
        singular value is below ``s_max / max_condition``; :mod:`.covariance`)."""
        if self.singular_vectors is None:
            return []
        names = parameter_names(self.blocks)[0]
        found = undetermined_groups(self.singular_values, self.singular_vectors, max_condition)
        return [[names[i] for i in g] for g in found]

    def block_slice(self, label: str) -> slice:
        start = 0
        for b in self.blocks:
            if b.label == label:
                return slice(start, start + b.size)
            start += b.size
        raise KeyError(label)


@fit_work
def fit(
    model: ExtendedModel,
    data: MeasuredData,
    *,
    free: Sequence[str] | None = None,
    cond: Conditions | None = None,
    sigma_pos_mm: float | None = None,
    sigma_rot_rad: float | None = None,
    max_iter: int = 50,
    near: Linearisation | None = None,
    initial_sigma: tuple[float, float | None] | None = None,
    covariance: bool = True,
    report_frames: bool = True,
    row_weights: Tensor | None = None,
    extra: Callable[[Tensor], tuple[Tensor, Tensor]] | None = None,
    progress: Callable[[str], None] | None = None,
    frames: FramePriors | None = None,
    robust: str | None = None,
    weights: Tensor | None = None,
    stop: Callable[[ExtendedModel], bool] | None = None,
) -> FitResult:
    """Least-squares fit of the model's frames and effect values to measured data.

    It starts where ``model`` is: call :func:`initialise_frames` first (as every command
    does), since from identity frames a fit can end in another minimum (one draw in 20 of
    a simulated RX160 campaign, 80 mm off).

    Args:
        model: model to fit in place (the robot's own parameters are kept).
        data: measured rows.
        free: labels (``"joint_offset:joint_2"``, ``"base_frame.rotation"``) or module
            paths of the parameter blocks to fit; default frames + every effect.
        cond: operating conditions (default :func:`conditions_from_data`).
        sigma_pos_mm, sigma_rot_rad: noise levels; estimated from the data if omitted.
        max_iter: LM iterations per pass.
        near: a Jacobian of these rows a few std from the start (the diagnosis' score
            of the effect it adds): the first pass steps with it, one exact Jacobian
            checks the end (:mod:`.chord`).
        initial_sigma: ``(sigma_pos_mm, sigma_rot_rad)`` to start the noise
            re-estimation from (e.g. a previous fit's), which saves passes.
        covariance: compute standard deviations, correlations, singular values and the
            frames' identifiability report (one more Jacobian); without it those
            fields are empty. ``report_frames=False`` leaves out the report alone (a
            refit whose report nobody reads: the diagnosis' trials).
        row_weights: ``(N,)`` weight of each row's residuals (see :class:`Problem`).
        extra: extra residual rows (priors, constraints; see :class:`Problem`).
        progress: called with a short text at every LM iteration, and at most every
            few seconds while a large Jacobian is built.
        frames: known frames (fixed components are not fitted) and the prior that holds
            what the data do not determine (:mod:`hybrid_pk.calibration.frames`).
        robust: ``"huber"`` or ``"cauchy"``: rows with gross errors are down-weighted
            (iteratively re-weighted, noise from the median); None: least squares.
        weights: ``(N,)`` robust row weights to start from (e.g. a previous fit's).
        stop: a test of the model at each accepted LM step; where it holds, the fit
            raises :class:`~.least_squares.StoppedFit` (model at its pass's start).
    """
    cond = cond or conditions_from_data(data, robot=model.robot)
    # the start's error even without a report: the compliance's warm starts stay the same
    blocks, prior, start = _frame_setup(model, data, cond, free, frames, covariance)
    rows_extra = join_rows(prior, extra)
    if robust is not None and weights is None:
        weights = torch.ones(data.n, dtype=model.robot.dtype)

    def problem_at(sig_p: float, sig_r: float, w: Tensor | None = None) -> Problem:
        rw = row_weights
        if w is not None:  # IRLS weights scale the squared residuals
            rw = w.sqrt() if rw is None else rw * w.sqrt()
        return Problem(
            model, data, cond, blocks, sig_p, sig_r, row_weights=rw, extra=rows_extra,
            progress=progress,
        )  # fmt: skip

    start_p, start_r = initial_sigma or (None, None)
    sigmas = (sigma_pos_mm or start_p or DEFAULT_SIGMA_POS_MM,
              sigma_rot_rad or start_r or DEFAULT_SIGMA_ROT_RAD)  # fmt: skip
    fixed = (sigma_pos_mm, sigma_rot_rad)
    sig_p, sig_r, iterations, converged, weights = _solve_reweighted(
        problem_at, data, sigmas, fixed, max_iter, progress, robust, weights, near, stop
    )
    given = frames is not None and (frames.tool, frames.base) != (None, None)  # hold there
    held = held_prior(model, data, cond, blocks, prior, given)  # at this optimum
    R, R_start = None, None  # the factors of [J r] where the chord's check settled / not
    if held is prior:
        R, R_start = _checked_chord(problem_at(sig_p, sig_r, weights), near, max_iter)
        converged = converged or R is not None
    if held is not prior or R_start is not None:  # LM from here
        prior, rows_extra = held, join_rows(held, extra)
        sig_p, sig_r, more, converged, weights = _solve_reweighted(
            problem_at, data, (sig_p, sig_r), fixed, max_iter, progress, robust, weights,
            R_start, stop,
        )  # fmt: skip
        iterations += more
    problem = problem_at(sig_p, sig_r, weights)  # the solution, under the final weights
    solved = (sig_p, sig_r, iterations, converged, robust, weights)
    report = report_frames if covariance else None
    return _result(problem, solved, (prior, frames, start, R), report)


def _result(problem: Problem, solved: tuple, priors: tuple, report: bool | None) -> FitResult:
    """The :class:`FitResult` of ``problem`` at its solution: ``solved`` is ``(sigma_pos_mm,
    sigma_rot_rad, iterations, converged, robust, weights)``, ``priors`` ``(prior rows,
    frame priors, start, R)``; ``report``: None (no covariance), else whether the frame
    report is made."""
    model, data, cond, blocks = problem.model, problem.data, problem.cond, problem.blocks
    sig_p, sig_r, iterations, converged, robust, weights = solved
    prior, frames, start, R = priors
    pos, ori = model_errors(model, data, cond)
    common = dict(
        blocks=blocks, x=problem.x0, sigma_pos_mm=sig_p,
        sigma_rot_rad=None if data.quat is None else sig_r, position_mm=pos, orientation_deg=ori,
        n_params=problem.x0.numel(), iterations=iterations, converged=converged,
        robust=robust, weights=weights, priors=frames,
    )  # fmt: skip
    if report is None:
        return FitResult(**common, **_no_covariance(problem, data))
    made = skipped_frame_report(data, blocks) if not report else frame_report(
        model, data, cond, blocks, sigma_pos_mm=sig_p, sigma_rot_rad=common["sigma_rot_rad"],
        prior=prior, priors=frames, start=start, rms_mm=float(pos.pow(2).mean().sqrt()),
    )  # fmt: skip
    return FitResult(**common, **covariance_fields(problem, prior, R), frame_report=made)


def _checked_chord(problem: Problem, near: Linearisation | None, max_iter: int):
    """``(R, None)`` where the fit's last pass stepped with ``near`` and the exact check
    at its end settled (:func:`.chord.settled_factor`; ``R`` there), ``(None, R)``
    where LM must go on from there (its first step from ``R``), ``(None, None)``
    without a chord."""
    if near is None or near.pass_sigmas is None:  # no chord, or a later pass was exact
        return None, None
    R, settled = settled_factor(problem, NEXT_STEP_STD, near, max_iter)
    return (R, None) if settled else (None, R)


def _no_covariance(problem: Problem, data: MeasuredData) -> dict:
    """The covariance fields of a fit without covariance: empty or NaN."""
    empty = torch.zeros(0, dtype=problem.x0.dtype)
    return {
        "std": torch.full_like(problem.x0, float("nan")),
        "corr": empty,
        "singular_values": empty,
        "condition": float("nan"),
        "n_obs": 3 * data.n * (1 if data.quat is None else 2),
    }


def _frame_setup(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    free: Sequence[str] | None,
    frames: FramePriors | None,
    covariance: bool = True,
) -> tuple[tuple[ParamBlock, ...], PriorRows | None, dict]:
    """The blocks to fit (known frames' components left out), the frame prior's rows
    (centred where the fit starts, or at the known values) and that start (base frames
    and, for a fit with ``covariance``, rms position error [mm]) for the plausibility
    of the result."""
    fixed_frames = set((frames or FramePriors()).fixed_labels())
    blocks = param_blocks(model, free, data.quat is None)
    blocks = tuple(b for b in blocks if b.label not in fixed_frames)
    prior = prior_residual(model, blocks, prior_centres(model, blocks, frames))
    start = {"base": model.base.matrix().detach().clone()}
    if covariance:  # only the frame report (with the covariance) reads it
        start["rms_mm"] = float(model_errors(model, data, cond)[0].pow(2).mean().sqrt())
    return blocks, prior, start


def _solve_reweighted(
    problem_at: Callable[..., Problem],
    data: MeasuredData,
    sigmas: tuple[float, float],
    fixed: tuple[float | None, float | None],
    max_iter: int,
    progress: Callable[[str], None] | None,
    robust: str | None = None,
    weights: Tensor | None = None,
    near: Linearisation | Tensor | None = None,
    stop: Callable[[ExtendedModel], bool] | None = None,
) -> tuple[float, float, int, bool, Tensor | None]:
    """LM fit, noise re-estimated from the residuals and refitted (at most 3 passes;
    robust fits re-weight their rows each pass too, at most ``ROBUST_PASSES``).

    ``problem_at(sigma_pos_mm, sigma_rot_rad, weights)`` is the problem under those
    noise levels and robust weights; ``sigmas`` are the starting levels, ``fixed``
    those given by the caller (not re-estimated); ``near``: the first pass starts from
    that Jacobian (:func:`.chord.first_passes`); ``stop``: :func:`fit`'s. Returns the
    final noise levels, LM iterations, convergence and the robust weights.
    """
    sig_p, sig_r = sigmas
    sigma_pos_mm, sigma_rot_rad = fixed
    position_only = data.quat is None
    iterations, converged = 0, False
    fixed_noise = sigma_pos_mm is not None and (sigma_rot_rad is not None or position_only)
    for k in range(3 if robust is None else ROBUST_PASSES):
        problem = problem_at(sig_p, sig_r, weights)
        passes = first_passes(problem, near) if near is not None and k == 0 else None
        if isinstance(near, Linearisation) and k > 0:
            near.pass_sigmas = None  # a later pass took exact steps
        fun, normal = passes or (problem.residual, problem.normal_equations)
        chord = isinstance(near, Linearisation) and passes is not None  # an exact check follows
        result = levenberg_marquardt(
            fun,
            torch.zeros_like(problem.x0),
            max_iter=1 if chord else max_iter,
            normal=normal,
            progress=progress,
            drop_tol=NEXT_STEP_STD**2 / problem.n_residuals,  # cost ~ 1 per residual
            stop=None if stop is None else _model_test(problem, stop),
        )
        problem.write(result.x)
        iterations += result.iterations
        converged = result.converged
        if fixed_noise and robust is None:
            break
        r = result.residual[: 3 * data.n * (1 if position_only else 2)]
        if weights is not None:  # the rows' own residuals, without the robust weights
            r = r / row_weights_vector(weights.sqrt().clamp_min(1e-150), r.numel() // (3 * data.n))
        if robust is None:
            new_p, new_r = reestimated_noise(
                r, data.n, result.x.numel(), (sig_p, sig_r), fixed, position_only
            )
            change = max(abs(new_p / sig_p - 1), abs(new_r / sig_r - 1))
        else:
            new_p, new_r, weights, change = irls_update(
                r, data.n, result.x.numel(), (sig_p, sig_r), fixed, robust, weights
            )
        sig_p, sig_r = new_p, new_r
        if change < 0.05:
            break
    return sig_p, sig_r, iterations, converged, weights


def _model_test(problem: Problem, stop: Callable[[ExtendedModel], bool]):
    """LM's test of a point ``theta`` of ``problem``: ``stop`` of the model with the
    point written in, the model restored after (``theta = 0`` is where it was)."""

    def test(theta: Tensor) -> bool:
        problem.write(theta)
        try:
            return bool(stop(problem.model))
        finally:
            problem.write(torch.zeros_like(theta))

    return test

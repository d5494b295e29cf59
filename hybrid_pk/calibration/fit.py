"""Identification: fit frames and effect values of an :class:`ExtendedModel` to data.

The residuals and their Jacobian are :class:`~hybrid_pk.calibration.problem.Problem`'s:
position [mm] and small-angle rotation [rad] differences, each divided by its noise
level so that mm and rad weigh by their evidence. Noise levels are estimated from the
fit itself (a second, re-weighted pass), which also makes the parameter covariance
``(J^T J)^-1`` meaningful.

Parameters are fitted in units of their ``scale`` (1 mm, 1 mrad, 1 µrad/Nm, …) so
the normal equations are well conditioned.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.least_squares import levenberg_marquardt
from hybrid_pk.calibration.problem import ParamBlock, Problem, param_blocks
from hybrid_pk.data.table import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.evaluation.metrics import pose_error, position_error_mm
from hybrid_pk.geometry import quat_to_matrix
from hybrid_pk.geometry.registration import register_frames

__all__ = ["FitResult", "fit", "initialise_frames", "model_errors"]

# First-pass noise levels, replaced by the estimates of the re-weighted pass.
DEFAULT_SIGMA_POS_MM = 0.05
DEFAULT_SIGMA_ROT_RAD = 1e-4


@dataclass(frozen=True)
class FitResult:
    """Outcome of :func:`fit` (values already written into the model).

    Attributes:
        blocks: fitted parameter tensors, in the order of ``x``.
        x, std: ``(n,)`` values and 1-sigma standard deviations (physical units).
        corr: ``(n, n)`` correlation matrix of the estimates.
        singular_values: of the Jacobian with unit-norm columns (identifiability).
        condition: ratio of largest to smallest singular value.
        sigma_pos_mm, sigma_rot_rad: per-coordinate noise estimated from residuals.
        position_mm, orientation_deg: per-sample errors after the fit.
        n_obs, n_params: residual and parameter counts.
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
        names, groups = [], []
        for b in self.blocks:
            for k in range(b.size):
                names.append(f"{b.label}[{k}]" if b.size > 1 else b.label)
                groups.append(b.label.split(".")[0])
        corr = self.corr
        pairs = []
        for i in range(corr.shape[0]):
            for j in range(i + 1, corr.shape[0]):
                r = float(corr[i, j])
                if groups[i] != groups[j] and not abs(r) < threshold:
                    pairs.append((groups[i], names[i], groups[j], names[j], r))
        return pairs

    def block_slice(self, label: str) -> slice:
        start = 0
        for b in self.blocks:
            if b.label == label:
                return slice(start, start + b.size)
            start += b.size
        raise KeyError(label)


@torch.no_grad()
def initialise_frames(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    which: str = "frames",
) -> None:
    """Set base and/or tool frames to the closed-form registration of ``data``.

    Args:
        which: ``"frames"`` (both), ``"base"`` or ``"tool"``.

    With gravity from a levelled tracker the loaded end pose depends on the base frame
    itself, so the registration is repeated once from the first one's base.
    """
    R_meas = None if data.quat is None else quat_to_matrix(data.quat)
    groups = [None] if model.base.sets == 1 or cond.group is None else range(model.base.sets)
    loaded = any(e.stage in ("compliance", "deflection") for e in model.effects)
    passes = 2 if model.gravity.levelled and loaded and which != "tool" else 1
    for _ in range(passes):
        T_end = model.end_pose(data.q, cond)
        for g in groups:
            rows = slice(None) if g is None else cond.group == g
            if g is not None and not bool(rows.any()):
                continue
            base, tool = register_frames(
                T_end[rows], data.position[rows], None if R_meas is None else R_meas[rows]
            )
            if which in ("frames", "base"):
                model.base.reset_to(base, g)
            if which in ("frames", "tool"):
                model.tool.reset_to(tool, g)


def fit(
    model: ExtendedModel,
    data: MeasuredData,
    *,
    free: Sequence[str] | None = None,
    cond: Conditions | None = None,
    sigma_pos_mm: float | None = None,
    sigma_rot_rad: float | None = None,
    max_iter: int = 50,
    initial_sigma: tuple[float, float | None] | None = None,
    covariance: bool = True,
) -> FitResult:
    """Least-squares fit of the model's frames and effect values to measured data.

    Args:
        model: model to fit in place (the robot's own parameters are kept).
        data: measured rows.
        free: labels (``"joint_offset:joint_2"``, ``"base_frame.rotation"``) or module
            paths of the parameter blocks to fit; default frames + every effect.
        cond: operating conditions (default :func:`conditions_from_data`).
        sigma_pos_mm, sigma_rot_rad: noise levels; estimated from the data if omitted.
        max_iter: LM iterations per pass.
        initial_sigma: ``(sigma_pos_mm, sigma_rot_rad)`` to start the noise
            re-estimation from (e.g. a previous fit's), which saves passes.
        covariance: compute standard deviations, correlations and singular values
            (one more Jacobian); without it those fields are empty.
    """
    cond = cond or conditions_from_data(data)
    position_only = data.quat is None
    blocks = param_blocks(model, free, position_only)
    start_p, start_r = initial_sigma or (None, None)
    sigmas = (
        sigma_pos_mm or start_p or DEFAULT_SIGMA_POS_MM,
        sigma_rot_rad or start_r or DEFAULT_SIGMA_ROT_RAD,
    )
    fixed = (sigma_pos_mm, sigma_rot_rad)
    sig_p, sig_r, iterations, converged = _solve_reweighted(
        model, data, cond, blocks, sigmas, fixed, max_iter
    )
    # Residuals and Jacobian at the solution with the final weights.
    problem = Problem(model, data, cond, blocks, sig_p, sig_r)
    pos, ori = model_errors(model, data, cond)
    common = {
        "blocks": blocks,
        "x": problem.x0,
        "sigma_pos_mm": sig_p,
        "sigma_rot_rad": None if position_only else sig_r,
        "position_mm": pos,
        "orientation_deg": ori,
        "n_params": problem.x0.numel(),
        "iterations": iterations,
        "converged": converged,
    }
    if not covariance:
        empty = torch.zeros(0, dtype=problem.x0.dtype)
        return FitResult(
            std=torch.full_like(problem.x0, float("nan")),
            corr=empty,
            singular_values=empty,
            condition=float("nan"),
            n_obs=3 * data.n * (1 if position_only else 2),
            **common,
        )
    return FitResult(**common, **_covariance(problem))


def _solve_reweighted(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    blocks: tuple[ParamBlock, ...],
    sigmas: tuple[float, float],
    fixed: tuple[float | None, float | None],
    max_iter: int,
) -> tuple[float, float, int, bool]:
    """LM fit, noise re-estimated from the residuals and refitted (at most 3 passes).

    ``sigmas`` are the starting noise levels, ``fixed`` those given by the caller (not
    re-estimated). Returns the final noise levels, LM iterations and convergence.
    """
    sig_p, sig_r = sigmas
    sigma_pos_mm, sigma_rot_rad = fixed
    position_only = data.quat is None
    iterations, converged = 0, False
    fixed_noise = sigma_pos_mm is not None and (sigma_rot_rad is not None or position_only)
    for _ in range(3):  # fit, re-estimate the noise, refit (at most twice)
        problem = Problem(model, data, cond, blocks, sig_p, sig_r)
        result = levenberg_marquardt(
            problem.residual, torch.zeros_like(problem.x0), max_iter=max_iter, jac=problem.jacobian
        )
        problem.write(result.x)
        iterations += result.iterations
        converged = result.converged
        if fixed_noise:
            break
        r, n_pos = result.residual, 3 * data.n
        dof_factor = r.numel() / max(r.numel() - result.x.numel(), 1)
        new_p = sigma_pos_mm or max(
            sig_p * float((r[:n_pos] ** 2).mean() * dof_factor) ** 0.5, 1e-6
        )
        new_r = sig_r
        if not position_only and sigma_rot_rad is None:
            new_r = max(sig_r * float((r[n_pos:] ** 2).mean() * dof_factor) ** 0.5, 1e-9)
        change = max(abs(new_p / sig_p - 1), abs(new_r / sig_r - 1))
        sig_p, sig_r = new_p, new_r
        if change < 0.05:
            break
    return sig_p, sig_r, iterations, converged


def _covariance(problem: Problem) -> dict:
    """Standard deviations, correlations and singular values at the problem's point."""
    r, J = problem.jacobian(torch.zeros_like(problem.x0))
    n_obs, n_par = r.numel(), problem.x0.numel()
    s2 = float(r @ r) / max(n_obs - n_par, 1)
    cov_scaled = torch.linalg.pinv(J.T @ J) * s2
    std = cov_scaled.diagonal().clamp_min(0).sqrt() * problem.scale
    d = cov_scaled.diagonal().clamp_min(1e-300).sqrt()
    corr = cov_scaled / (d[:, None] * d[None, :])
    sv = torch.linalg.svdvals(J / J.norm(dim=0).clamp_min(1e-300))
    return {
        "std": std,
        "corr": corr,
        "singular_values": sv,
        "condition": float(sv[0] / sv[-1].clamp_min(1e-300)),
        "n_obs": n_obs,
    }


@torch.no_grad()
def model_errors(
    model: ExtendedModel, data: MeasuredData, cond: Conditions | None = None
) -> tuple[Tensor, Tensor | None]:
    """Per-row position [mm] and orientation [deg] errors (None without orientation)."""
    T = model(data.q, cond or conditions_from_data(data))
    if data.quat is None:
        return position_error_mm(data.position, T[:, :3, 3]), None
    return pose_error(data.T_measured(), T)

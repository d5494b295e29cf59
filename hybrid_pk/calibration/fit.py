"""Identification: fit frames and effect values of an :class:`ExtendedModel` to data.

Residuals per measured pose: position difference [mm] and the small-angle rotation
difference ``vee(E - E^T) / 2`` (``E = R_meas R_model^T``, = ``sin(angle) · axis``)
[rad], each divided by its noise level so that mm and rad weigh by their evidence.
Noise levels are estimated from the fit itself (a second, re-weighted pass), which
also makes the parameter covariance ``(J^T J)^-1`` meaningful.

Parameters are fitted in units of their ``scale`` (1 mm, 1 mrad, 1 µrad/Nm, …) so
the normal equations are well conditioned.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.lm import jacobian, levenberg_marquardt
from hybrid_pk.calibration.registration import register_frames
from hybrid_pk.data.table import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, approach_direction
from hybrid_pk.geometry import quat_to_matrix
from hybrid_pk.metrics import pose_error, position_error_mm

__all__ = [
    "FitResult",
    "ParamBlock",
    "Problem",
    "conditions_from_data",
    "fit",
    "initialise_frames",
    "model_errors",
]

# First-pass noise levels, replaced by the estimates of the re-weighted pass.
DEFAULT_SIGMA_POS_MM = 0.05
DEFAULT_SIGMA_ROT_RAD = 1e-4


@dataclass(frozen=True)
class ParamBlock:
    """One fitted parameter tensor: module path, report label, size, scale, unit."""

    name: str
    label: str
    size: int
    scale: float
    unit: str


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

    def block_slice(self, label: str) -> slice:
        start = 0
        for b in self.blocks:
            if b.label == label:
                return slice(start, start + b.size)
            start += b.size
        raise KeyError(label)


def conditions_from_data(data: MeasuredData, frames_per_file: bool = False) -> Conditions:
    """Operating conditions of every row: payload, temperature, approach direction, and
    (with ``frames_per_file``) the file's own base/tool frame set."""
    return Conditions(
        payload=data.payload,
        temperature=data.temperature,
        direction=approach_direction(data.q, data.file_index),
        group=data.file_index if frames_per_file else None,
    )


def _blocks(model: ExtendedModel, free: Sequence[str] | None, position_only: bool):
    blocks = []
    frames = {
        "base.dp": ("base_frame.translation", "m"),
        "base.rotvec": ("base_frame.rotation", "rad"),
        "tool.dp": ("tool_frame.translation", "m"),
        "tool.rotvec": ("tool_frame.rotation", "rad"),
    }
    for name, (label, unit) in frames.items():
        if position_only and name == "tool.rotvec":
            continue  # the tool's orientation is unobservable from points
        blocks.append(ParamBlock(name, label, 3 * model.base.sets, model.base.scale, unit))
    for i, e in enumerate(model.effects):
        blocks.append(ParamBlock(f"effects.{i}.value", e.label, e.value.numel(), e.scale, e.unit))
    if free is not None:
        wanted = set(free)
        blocks = [b for b in blocks if b.label in wanted or b.name in wanted]
    return tuple(blocks)


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
    """
    T_end = model.end_pose(data.q, cond)
    R_meas = None if data.quat is None else quat_to_matrix(data.quat)
    groups = [None] if model.base.sets == 1 or cond.group is None else range(model.base.sets)
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


class Problem:
    """The weighted least-squares problem of fitting ``blocks`` of ``model`` to ``data``.

    ``residual(theta)`` maps the scaled parameter offsets ``theta`` (zero = the model's
    current values) to noise-normalised residuals: ``3 N`` position [mm / sigma_pos]
    then, with orientation data, ``3 N`` rotation [rad / sigma_rot].
    """

    def __init__(
        self,
        model: ExtendedModel,
        data: MeasuredData,
        cond: Conditions,
        blocks: tuple[ParamBlock, ...],
        sigma_pos_mm: float,
        sigma_rot_rad: float,
    ) -> None:
        self.model, self.data, self.cond, self.blocks = model, data, cond, blocks
        self.sigma_pos_mm, self.sigma_rot_rad = sigma_pos_mm, sigma_rot_rad
        self.params = dict(model.named_parameters())
        dtype = model.robot.dtype
        self.x0 = torch.cat(
            [torch.zeros(0, dtype=dtype)]
            + [self.params[b.name].detach().reshape(-1) for b in blocks]
        )
        self.scale = torch.cat(
            [torch.zeros(0, dtype=dtype)]
            + [torch.full((b.size,), b.scale, dtype=dtype) for b in blocks]
        )
        self.R_meas = None if data.quat is None else quat_to_matrix(data.quat)

    def unpack(self, theta: Tensor) -> dict[str, Tensor]:
        values, start = {}, 0
        for b in self.blocks:
            chunk = self.x0[start : start + b.size] + theta[start : start + b.size] * b.scale
            values[b.name] = chunk.reshape(self.params[b.name].shape)
            start += b.size
        return values

    def residual(self, theta: Tensor) -> Tensor:
        T = torch.func.functional_call(self.model, self.unpack(theta), (self.data.q, self.cond))
        res = [((self.data.position - T[:, :3, 3]) * (1000.0 / self.sigma_pos_mm)).reshape(-1)]
        if self.R_meas is not None:
            E = self.R_meas @ T[:, :3, :3].transpose(-1, -2)
            vee = torch.stack(
                [E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], -1
            )
            res.append((0.5 / self.sigma_rot_rad) * vee.reshape(-1))
        return torch.cat(res)

    @torch.no_grad()
    def write(self, theta: Tensor) -> None:
        """Store ``theta`` into the model's parameters."""
        for name, v in self.unpack(theta).items():
            self.params[name].copy_(v)


def fit(
    model: ExtendedModel,
    data: MeasuredData,
    *,
    free: Sequence[str] | None = None,
    cond: Conditions | None = None,
    sigma_pos_mm: float | None = None,
    sigma_rot_rad: float | None = None,
    max_iter: int = 50,
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
    """
    cond = cond or conditions_from_data(data)
    position_only = data.quat is None
    blocks = _blocks(model, free, position_only)
    sig_p = sigma_pos_mm or DEFAULT_SIGMA_POS_MM
    sig_r = sigma_rot_rad or DEFAULT_SIGMA_ROT_RAD
    iterations, converged = 0, False
    fixed_noise = sigma_pos_mm is not None and (sigma_rot_rad is not None or position_only)
    for _ in range(3):  # fit, re-estimate the noise, refit (at most twice)
        problem = Problem(model, data, cond, blocks, sig_p, sig_r)
        result = levenberg_marquardt(
            problem.residual, torch.zeros_like(problem.x0), max_iter=max_iter
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
    # Residuals and Jacobian at the solution with the final weights.
    problem = Problem(model, data, cond, blocks, sig_p, sig_r)
    r, J = jacobian(problem.residual, torch.zeros_like(problem.x0))
    n_obs, n_par = r.numel(), problem.x0.numel()
    s2 = float(r @ r) / max(n_obs - n_par, 1)
    cov_scaled = torch.linalg.pinv(J.T @ J) * s2
    std = cov_scaled.diagonal().clamp_min(0).sqrt() * problem.scale
    d = cov_scaled.diagonal().clamp_min(1e-300).sqrt()
    corr = cov_scaled / (d[:, None] * d[None, :])
    sv = torch.linalg.svdvals(J / J.norm(dim=0).clamp_min(1e-300))
    pos, ori = model_errors(model, data, cond)
    return FitResult(
        blocks=blocks,
        x=problem.x0,
        std=std,
        corr=corr,
        singular_values=sv,
        condition=float(sv[0] / sv[-1].clamp_min(1e-300)),
        sigma_pos_mm=sig_p,
        sigma_rot_rad=None if position_only else sig_r,
        position_mm=pos,
        orientation_deg=ori,
        n_obs=n_obs,
        n_params=n_par,
        iterations=iterations,
        converged=converged,
    )


@torch.no_grad()
def model_errors(
    model: ExtendedModel, data: MeasuredData, cond: Conditions | None = None
) -> tuple[Tensor, Tensor | None]:
    """Per-row position [mm] and orientation [deg] errors (None without orientation)."""
    T = model(data.q, cond or conditions_from_data(data))
    if data.quat is None:
        return position_error_mm(data.position, T[:, :3, 3]), None
    return pose_error(data.T_measured(), T)

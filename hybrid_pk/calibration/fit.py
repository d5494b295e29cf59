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
from hybrid_pk.geometry import quat_to_matrix, so3_exp, transform
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


class _EndPose(torch.nn.Module):
    """``model.end_pose`` as a module forward, for ``functional_call``."""

    def __init__(self, model: ExtendedModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, q: Tensor, cond: Conditions) -> Tensor:
        return self.model.end_pose(q, cond)


def _frame_matrix(frame, values: dict, prefix: str, group: Tensor | None) -> Tensor:
    """A RigidFrame's matrices with parameters taken from ``values`` where present."""
    dp = values.get(f"{prefix}.dp", frame.dp)
    rotvec = values.get(f"{prefix}.rotvec", frame.rotvec)
    T = transform(frame.T0[:, :3, :3] @ so3_exp(rotvec), frame.T0[:, :3, 3] + dp)
    return T[0] if group is None else T[group]


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
        return self.residual_of_pose(T)

    def residual_of_pose(self, T: Tensor) -> Tensor:
        """Noise-normalised residuals of predicted poses ``T (N, 4, 4)``."""
        res = [((self.data.position - T[:, :3, 3]) * (1000.0 / self.sigma_pos_mm)).reshape(-1)]
        if self.R_meas is not None:
            E = self.R_meas @ T[:, :3, :3].transpose(-1, -2)
            vee = torch.stack(
                [E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], -1
            )
            res.append((0.5 / self.sigma_rot_rad) * vee.reshape(-1))
        return torch.cat(res)

    def jacobian(self, theta: Tensor) -> tuple[Tensor, Tensor]:
        """Residual ``(m,)`` and Jacobian ``(m, n)`` at ``theta``.

        Frame parameters only compose with the end pose, ``T = B · E · X``, so their
        columns come from a cheap forward-mode pass over that product with ``E`` held
        fixed; only effect parameters are pushed through the whole model.
        """
        values = self.unpack(theta)
        frame_cols, effect_cols, start = [], [], 0
        for b in self.blocks:
            cols = list(range(start, start + b.size))
            (frame_cols if b.name.startswith(("base.", "tool.")) else effect_cols).extend(cols)
            start += b.size
        model, q, cond = self.model, self.data.q, self.cond
        group = cond.group if model.base.sets > 1 else None
        frame_values = {k: v for k, v in values.items() if k.startswith(("base.", "tool."))}
        effect_values = {k: v for k, v in values.items() if k not in frame_values}
        end = _EndPose(model)
        with torch.no_grad():
            E = torch.func.functional_call(
                end, {f"model.{k}": v for k, v in effect_values.items()}, (q, cond)
            )

        def compose(theta_f: Tensor) -> Tensor:
            full = theta.index_copy(0, torch.tensor(frame_cols), theta_f)
            vals = self.unpack(full)
            B = _frame_matrix(model.base, vals, "base", group)
            X = _frame_matrix(model.tool, vals, "tool", group)
            return self.residual_of_pose(B @ E @ X)

        def through_model(theta_e: Tensor) -> Tensor:
            full = theta.index_copy(0, torch.tensor(effect_cols), theta_e)
            return self.residual(full)

        J = torch.zeros(0)
        r = None
        parts = {}
        if frame_cols:
            r, parts["f"] = jacobian(compose, theta[frame_cols])
        if effect_cols:
            r, parts["e"] = jacobian(through_model, theta[effect_cols])
        J = torch.zeros(r.numel(), theta.numel(), dtype=theta.dtype)
        if frame_cols:
            J[:, frame_cols] = parts["f"]
        if effect_cols:
            J[:, effect_cols] = parts["e"]
        return r, J

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
    blocks = _blocks(model, free, position_only)
    start_p, start_r = initial_sigma or (None, None)
    sig_p = sigma_pos_mm or start_p or DEFAULT_SIGMA_POS_MM
    sig_r = sigma_rot_rad or start_r or DEFAULT_SIGMA_ROT_RAD
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
    # Residuals and Jacobian at the solution with the final weights.
    problem = Problem(model, data, cond, blocks, sig_p, sig_r)
    pos, ori = model_errors(model, data, cond)
    if not covariance:
        empty = torch.zeros(0, dtype=problem.x0.dtype)
        return FitResult(
            blocks=blocks,
            x=problem.x0,
            std=torch.full_like(problem.x0, float("nan")),
            corr=empty,
            singular_values=empty,
            condition=float("nan"),
            sigma_pos_mm=sig_p,
            sigma_rot_rad=None if position_only else sig_r,
            position_mm=pos,
            orientation_deg=ori,
            n_obs=3 * data.n * (1 if position_only else 2),
            n_params=problem.x0.numel(),
            iterations=iterations,
            converged=converged,
        )
    r, J = problem.jacobian(torch.zeros_like(problem.x0))
    n_obs, n_par = r.numel(), problem.x0.numel()
    s2 = float(r @ r) / max(n_obs - n_par, 1)
    cov_scaled = torch.linalg.pinv(J.T @ J) * s2
    std = cov_scaled.diagonal().clamp_min(0).sqrt() * problem.scale
    d = cov_scaled.diagonal().clamp_min(1e-300).sqrt()
    corr = cov_scaled / (d[:, None] * d[None, :])
    sv = torch.linalg.svdvals(J / J.norm(dim=0).clamp_min(1e-300))
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

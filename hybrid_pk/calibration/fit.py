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

from hybrid_pk.calibration.gravity_coupling import levelled_gravity_columns
from hybrid_pk.calibration.least_squares import jacobian, levenberg_marquardt
from hybrid_pk.data.table import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.evaluation.metrics import pose_error, position_error_mm
from hybrid_pk.geometry import quat_to_matrix, so3_exp, transform
from hybrid_pk.geometry.registration import register_frames

__all__ = [
    "FitResult",
    "ParamBlock",
    "Problem",
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


class _GeometricPose(torch.nn.Module):
    """End pose with geometric and deflection effects at given true joint values, the
    static wrenches of the deflection held fixed (see :func:`loaded_state`)."""

    def __init__(self, model: ExtendedModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, q_true: Tensor, cond: Conditions, wrenches: Tensor | None) -> Tensor:
        params = self.model.kinematic_params(cond)
        params = self.model.deflected_params(q_true, params, cond, wrenches=wrenches)
        return self.model.robot.fk(q_true, params=params)


@torch.no_grad()
def loaded_state(model: ExtendedModel, q: Tensor, cond: Conditions):
    """Everything the structured Jacobian linearises about, at the current values:
    ``(params, gravity, q_star, wrenches, params_deflected)``.

    ``gravity`` is the root-frame vector (per row with a levelled tracker and several
    base frames); ``wrenches`` the joint-frame static wrenches at ``q_star`` (None
    without deflection effects); ``params_deflected`` the parameters the pose uses.
    """
    params = model.kinematic_params(cond)
    gravity = model.gravity_root(cond)
    q_star = model.joint_values(q, cond, params, gravity)
    wrenches = None
    if any(e.stage == "deflection" for e in model.effects):
        wrenches = model.static_wrenches(q_star, params, cond, gravity)
    return (
        params,
        gravity,
        q_star,
        wrenches,
        model.deflected_params(q_star, params, cond, gravity, wrenches),
    )


class _KinematicJoints(torch.nn.Module):
    """``model.kinematic_joint_values`` as a module forward, for ``functional_call``."""

    def __init__(self, model: ExtendedModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, q: Tensor, cond: Conditions) -> Tensor:
        return self.model.kinematic_joint_values(q, cond)


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
        """Residual ``(m,)`` and Jacobian ``(m, n)`` at ``theta``, by structure.

        - Frames compose with the end pose, ``T = B · E · X``: forward mode over that
          product with ``E`` fixed.
        - Joint-space effects (and compliance) act through the true joint values
          ``q*``, the fixed point of ``q = q_kin(theta) - C g(q)``. By the implicit
          function theorem ``dq*/dtheta = (I + C dg/dq)^-1 (dq_kin/dtheta - dC/dtheta g)``,
          and the pose follows through the geometric Jacobian at ``q*``.
        - Geometric effects: forward mode through FK at fixed ``q*`` (their coupling
          through the gravity torques is second order, ~1e-3 relative, and dropped).
        - Deflection effects: forward mode through the same pass, at fixed ``q*`` and
          fixed static wrenches (exact: neither depends on a deflection value). The
          wrenches' own dependence on the joint and geometric parameters (a deflection
          of ~1e-3 rad changing by ~1e-3 relative per mrad) is dropped with the rest.
        - Gravity from a levelled tracker (``Gravity.level_tracker``): turning the base
          frame turns gravity in the root frame too, which changes sag and deflection
          (~1e-3 of the base-rotation columns on a compliant robot): added by
          :func:`~hybrid_pk.calibration.gravity_coupling.levelled_gravity_columns`.
        """
        model, cond = self.model, self.cond
        saved = {k: v.detach().clone() for k, v in self.params.items()}
        self.write(theta)
        try:
            return self._jacobian_at_current(model, cond)
        finally:
            with torch.no_grad():
                for k, v in saved.items():
                    self.params[k].copy_(v)

    def _jacobian_at_current(self, model: ExtendedModel, cond: Conditions):
        q = self.data.q
        group = cond.group if model.base.sets > 1 else None
        robot = model.robot
        with torch.no_grad():
            params, gravity, q_star, wrenches, params_bent = loaded_state(model, q, cond)
            E = robot.fk(q_star, params=params_bent)
            B = _frame_matrix(model.base, {}, "base", group)
            X = _frame_matrix(model.tool, {}, "tool", group)
            T = B @ E @ X
            r = self.residual_of_pose(T)
        n = self.x0.numel()
        J = torch.zeros(r.numel(), n, dtype=r.dtype)
        cols: dict[str, list[int]] = {"frame": [], "joint": [], "geometry": []}
        kinds: dict[str, list] = {"joint": [], "geometry": []}
        start = 0
        effects = {f"effects.{i}.value": e for i, e in enumerate(model.effects)}
        for blk in self.blocks:
            idx = list(range(start, start + blk.size))
            start += blk.size
            if blk.name.startswith(("base.", "tool.")):
                cols["frame"].extend(idx)
                continue
            stage = "geometry" if effects[blk.name].stage in ("geometry", "deflection") else "joint"
            cols[stage].extend(idx)
            kinds[stage].append((blk, effects[blk.name]))

        if cols["frame"]:
            frame_blocks = [b for b in self.blocks if b.name.startswith(("base.", "tool."))]

            def compose(theta_f: Tensor) -> Tensor:
                vals = self._sub_params(frame_blocks, theta_f)
                Bf = _frame_matrix(model.base, vals, "base", group)
                Xf = _frame_matrix(model.tool, vals, "tool", group)
                return self.residual_of_pose(Bf @ E @ Xf)

            _, J[:, cols["frame"]] = jacobian(
                compose, torch.zeros(len(cols["frame"]), dtype=r.dtype)
            )
            self._add_gravity_coupling(J, model, cond, q, B, X)

        if cols["joint"]:
            dq = self._joint_derivatives(model, cond, q, q_star, params, kinds["joint"], gravity)
            J[:, cols["joint"]] = self._pose_columns(robot, q_star, params_bent, E, B, X, T, dq)

        if cols["geometry"]:
            geo_blocks = [b for b, _ in kinds["geometry"]]
            wrapper = _GeometricPose(model)

            def through_fk(theta_g: Tensor) -> Tensor:
                vals = self._sub_params(geo_blocks, theta_g, prefix="model.")
                pose = torch.func.functional_call(wrapper, vals, (q_star, cond, wrenches))
                return self.residual_of_pose(B @ pose @ X)

            _, J[:, cols["geometry"]] = jacobian(
                through_fk, torch.zeros(len(cols["geometry"]), dtype=r.dtype)
            )
        return r, J

    def _add_gravity_coupling(self, J, model, cond, q, B, X) -> None:
        """Levelled-tracker gravity turns with the base frame (gravity_coupling.py)."""
        start = 0
        for b in self.blocks:
            if b.name == "base.rotvec":
                extra = levelled_gravity_columns(model, q, cond, B, X, self.residual_of_pose)
                if extra is not None:
                    J[:, start : start + b.size] += extra * b.scale  # theta units
            start += b.size

    def _sub_params(self, blocks, theta_sub: Tensor, prefix: str = "") -> dict[str, Tensor]:
        """Parameter values of ``blocks`` at scaled offsets ``theta_sub`` from current."""
        vals, s0 = {}, 0
        for b in blocks:
            x = self.params[b.name].detach().reshape(-1)
            chunk = x + theta_sub[s0 : s0 + b.size] * b.scale
            vals[prefix + b.name] = chunk.reshape(self.params[b.name].shape)
            s0 += b.size
        return vals

    def _joint_derivatives(self, model, cond, q, q_star, params, blocks, gravity) -> Tensor:
        """``dq*/dtheta (N, dof, k)`` for joint-space and compliance parameters."""
        robot = model.robot
        n, dof = q.shape
        payload = 0.0 if cond.payload is None else cond.payload
        with torch.no_grad():
            g = robot.gravity_torques(q_star, payload=payload, gravity=gravity, params=params)
        kin = [(b, e) for b, e in blocks if e.stage == "joint"]
        dq_kin = None
        if kin:
            wrapper = _KinematicJoints(model)
            kin_blocks = [b for b, _ in kin]

            def q_kin(theta_k: Tensor) -> Tensor:
                vals = self._sub_params(kin_blocks, theta_k, prefix="model.")
                return torch.func.functional_call(wrapper, vals, (q, cond)).reshape(-1)

            size = sum(b.size for b in kin_blocks)
            _, Jk = jacobian(q_kin, torch.zeros(size, dtype=q.dtype))
            dq_kin = Jk.reshape(n, dof, size)
        columns, k_col = [], 0
        for b, e in blocks:  # assemble in block order
            if e.stage == "compliance":
                col = torch.zeros(n, dof, 1, dtype=q.dtype)
                col[:, e.joint_index, 0] = -g[:, e.joint_index] * b.scale  # d(-c g)/dc
                columns.append(col)
            else:
                columns.append(dq_kin[..., k_col : k_col + b.size])
                k_col += b.size
        dq = torch.cat(columns, -1)
        c = model._compliance()
        if c is not None and bool((c != 0).any()):
            # q* = q_kin - C g(q*)  =>  (I + C dg/dq) dq* = dq_kin - dC g
            def grav(d: Tensor) -> Tensor:
                tau = robot.gravity_torques(
                    q_star + d, payload=payload, gravity=gravity, params=params
                )
                return tau.reshape(-1)

            _, Jg = jacobian(grav, torch.zeros(dof, dtype=q.dtype))
            G = Jg.reshape(n, dof, dof)
            M = torch.eye(dof, dtype=q.dtype) + c.detach().to(q.dtype)[:, None] * G
            dq = torch.linalg.solve(M, dq)
        return dq

    def _pose_columns(self, robot, q_star, params, E, B, X, T, dq) -> Tensor:
        """Residual columns ``(m, k)`` from joint-value derivatives ``dq (N, dof, k)``."""
        with torch.no_grad():
            Jg = robot.jacobian(q_star, params=params)  # (N, 6, dof): end link, root frame
            v_end, w = Jg[:, :3, :], Jg[:, 3:, :]
            lever = ((E @ X)[:, :3, 3] - E[:, :3, 3])[:, :, None]  # end origin -> point
            v_point = v_end + torch.linalg.cross(w, lever.expand_as(w), dim=1)
            R_B = B[..., :3, :3]
            k = dq.shape[-1]
            cols = [((-1000.0 / self.sigma_pos_mm) * (R_B @ v_point @ dq)).reshape(-1, k)]
            if self.R_meas is not None:
                # rotating the model by w: d vee(E - E^T) = -vee(E [w] + [w] E^T)
                #                                         = -(tr(E) I - E^T) w
                Er = self.R_meas @ T[:, :3, :3].transpose(-1, -2)
                tr = Er.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
                A = tr * torch.eye(3, dtype=Er.dtype) - Er.transpose(-1, -2)
                w_meas = R_B @ w @ dq
                cols.append(((-0.5 / self.sigma_rot_rad) * (A @ w_meas)).reshape(-1, k))
            return torch.cat(cols, 0)

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

"""The weighted least-squares problem of a fit: residuals and their structured Jacobian.

Residuals per measured pose: position difference [mm] and the small-angle rotation
difference ``vee(E - E^T) / 2`` (``E = R_meas R_model^T``, = ``sin(angle) · axis``)
[rad], each divided by its noise level so that mm and rad weigh by their evidence.
Parameters are offsets in units of their block's ``scale`` (1 mm, 1 mrad,
1 µrad/Nm, …) so that the normal equations are well conditioned.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.calibration.loaded_jacobian import (
    LoadedPose,
    levelled_gravity_columns,
    loaded_state,
)
from hybrid_pk.data.table import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import quat_to_matrix, so3_exp, transform

__all__ = ["ParamBlock", "Problem", "param_blocks"]


@dataclass(frozen=True)
class ParamBlock:
    """One fitted parameter tensor: module path, report label, size, scale, unit."""

    name: str
    label: str
    size: int
    scale: float
    unit: str


def param_blocks(
    model: ExtendedModel, free: Sequence[str] | None, position_only: bool
) -> tuple[ParamBlock, ...]:
    """The parameter blocks of ``model`` to fit: frames first, then every effect.

    Args:
        free: labels (``"joint_offset:joint_2"``, ``"base_frame.rotation"``) or module
            paths of the blocks to keep; ``None`` keeps all.
        position_only: drop the tool rotation (unobservable from points).
    """
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


def _frame_matrix(frame, values: dict, prefix: str, group: Tensor | None) -> Tensor:
    """A RigidFrame's matrices with parameters taken from ``values`` where present."""
    dp = values.get(f"{prefix}.dp", frame.dp)
    rotvec = values.get(f"{prefix}.rotvec", frame.rotvec)
    T = transform(frame.T0[:, :3, :3] @ so3_exp(rotvec), frame.T0[:, :3, 3] + dp)
    return T[0] if group is None else T[group]


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
        - Deflection effects and a levelled tracker's gravity: see
          :mod:`~hybrid_pk.calibration.loaded_jacobian`.
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
            params, gravity, q_star, wrenches, bent = loaded_state(model, q, cond)
            E = robot.fk(q_star, params=bent)
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
            shape_only = effects[blk.name].stage in ("geometry", "deflection")
            stage = "geometry" if shape_only else "joint"
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
            J[:, cols["joint"]] = self._pose_columns(robot, q_star, bent, E, B, X, T, dq)

        if cols["geometry"]:
            geo_blocks = [b for b, _ in kinds["geometry"]]
            wrapper = LoadedPose(model)

            def through_fk(theta_g: Tensor) -> Tensor:
                vals = self._sub_params(geo_blocks, theta_g, prefix="model.")
                pose = torch.func.functional_call(wrapper, vals, (q_star, cond, wrenches))
                return self.residual_of_pose(B @ pose @ X)

            _, J[:, cols["geometry"]] = jacobian(
                through_fk, torch.zeros(len(cols["geometry"]), dtype=r.dtype)
            )
        return r, J

    def _add_gravity_coupling(self, J, model, cond, q, B, X) -> None:
        """A levelled tracker's gravity turns with the base frame (loaded_jacobian.py)."""
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
        kw = {"payload": payload, "gravity": gravity, "params": params}
        with torch.no_grad():
            g = robot.gravity_torques(q_star, **kw)  # (N, dof)
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
                return robot.gravity_torques(q_star + d, **kw).reshape(-1)

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

"""The residual Jacobian of one chunk of rows, by structure, as twists per parameter.

- Frames compose with the end pose, ``T = B · E · X``: twists in closed form.
- Joint-space effects (and compliance) act through the true joint values ``q*``, the
  fixed point of ``q = q_kin(theta) - C g(q)``. By the implicit function theorem
  ``dq*/dtheta = (I + C dg/dq)^-1 (dq_kin/dtheta - dC/dtheta g)``, and the pose
  follows through the geometric Jacobian at ``q*``.
- Geometric effects: forward mode on the few kinematic parameters (the chain origins
  they perturb), then the closed-form twists of the perturbed origins at fixed ``q*``
  (their coupling through the gravity torques is second order, ~1e-3 relative, and
  dropped). An effect that turns a joint axis goes through FK in forward mode.
- Deflection effects and a levelled tracker's gravity: closed-form twists about the
  loaded state, :mod:`~hybrid_pk.calibration.loaded_jacobian`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.calibration.gravity_jacobian import GRAVITY_REUSE_RAD, compliance_feedback
from hybrid_pk.calibration.joint_jacobian import joint_effect_jacobian
from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.calibration.loaded_jacobian import (
    deflection_twists,
    levelled_gravity_twists,
    loaded_state,
)
from hybrid_pk.calibration.twists import (
    frame_twists,
    geometry_twists,
    origin_twist_maps,
    point_joint_twists,
    vee,
)
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry.tangents import carried
from hybrid_pk.robot import KinematicParams

__all__ = [
    "GRAVITY_REUSE_RAD",
    "PoseTwists",
    "StructuredJacobian",
    "compliance_feedback",
    "point_jacobian",
    "settled_twists",
]


class _KinematicJoints(torch.nn.Module):
    """``model.kinematic_joint_values`` as a module forward, for ``functional_call``."""

    def __init__(self, model: ExtendedModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, q: Tensor, cond: Conditions) -> Tensor:
        return self.model.kinematic_joint_values(q, cond)


class _KinematicParams(torch.nn.Module):
    """``model.kinematic_params`` as a module forward, for ``functional_call``."""

    def __init__(self, model: ExtendedModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, cond: Conditions) -> tuple[Tensor, Tensor, Tensor]:
        return tuple(self.model.kinematic_params(cond))


class PoseTwists:
    """Predicted poses ``T (n, 4, 4)`` of a chunk and their twists ``(n, 6, n_params)``."""

    def __init__(self, T: Tensor, twists: Tensor) -> None:
        self.T, self.twists = T, twists


class StructuredJacobian:
    """Twists of every parameter of ``blocks`` at the model's current values.

    The gravity-torque derivative ``dg/dq`` at ``q*`` (compliance models only) is
    kept per data set and chunk and reused while ``q*`` stays within
    :data:`GRAVITY_REUSE_RAD` of where it was computed (later LM iterations, the next
    fits of a diagnosis): the term ``C dg/dq`` is ~1e-3, so the reuse changes the
    Jacobian by < 1e-6 relative, the residuals not at all.
    """

    def __init__(self, model: ExtendedModel, blocks) -> None:
        self.model, self.blocks = model, blocks
        self.params = dict(model.named_parameters())
        effects = {f"effects.{i}.value": e for i, e in enumerate(model.effects)}
        self.effects = effects
        stage = {b.name: effects[b.name].stage for b in blocks if b.name in effects}
        self.joint = [b for b in blocks if stage.get(b.name) in ("joint", "compliance")]
        self.geometry = [b for b in blocks if stage.get(b.name) == "geometry"]
        self.deflection = [b for b in blocks if stage.get(b.name) == "deflection"]
        self._turns_axis: dict[str, bool] = {}  # geometric blocks that turn a joint axis
        self._origins: tuple | None = None  # (key, derivatives) of the last chunk's origins

    def _sub_params(self, blocks, theta_sub: Tensor, prefix: str = "") -> dict[str, Tensor]:
        """Parameter values of ``blocks`` at scaled offsets ``theta_sub`` from current."""
        vals, s0 = {}, 0
        for b in blocks:
            x = self.params[b.name].detach().reshape(-1)
            step = theta_sub[s0 : s0 + b.size]  # constants carried: see geometry.tangents
            chunk = carried(x, step) + step * carried(b.scale, step)
            vals[prefix + b.name] = chunk.reshape(self.params[b.name].shape)
            s0 += b.size
        return vals

    def pose_twists(self, q: Tensor, cond: Conditions, key=None) -> PoseTwists:
        """Poses and twists of rows ``q (n, dof)`` under ``cond``.

        Args:
            key: ``(data_q, start, stop)``, the data set's joint tensor and the chunk's
                rows, under which ``dg/dq`` is kept for reuse (None: not kept).
        """
        model, robot = self.model, self.model.robot
        group = cond.group if model.base.sets > 1 else None
        with torch.no_grad():
            params, gravity, q_star, wrenches, bent, frames = loaded_state(model, q, cond)
            E = robot.fk(q_star, params=bent)
            if group is None:
                B, X = model.base.matrix()[0], model.tool.matrix()[0]
            else:
                B, X = model.base.matrix(group), model.tool.matrix(group)
            T_BE = B @ E
            T = T_BE @ X
        R_B = B[..., :3, :3]
        cols: dict[str, Tensor] = {}
        if any(b.name.startswith(("base.", "tool.")) for b in self.blocks):
            own = frame_twists(model.base, model.tool, group, T_BE, T)
            gravity_path = levelled_gravity_twists(model, q, cond, B, X, T)
            if gravity_path is not None:  # a levelled tracker's gravity turns with the base
                own["base.rotvec"] = own["base.rotvec"] + gravity_path
            scale = {b.name: b.scale for b in self.blocks}
            cols.update({k: v * scale.get(k, 1.0) for k, v in own.items()})
        if self.joint:
            dq, feedback = self._joint_derivatives(q, cond, q_star, params, key, gravity)
            lever = (E @ X)[:, :3, 3] - E[:, :3, 3]
            P = point_joint_twists(robot.jacobian(q_star, params=bent), lever, R_B)
            cols.update(self._split(self.joint, settled_twists(P, dq, feedback)))
        # the link frames at q*, for the geometric and the deflection blocks alike (those
        # of the static wrenches where nothing bends)
        if (self.geometry or self.deflection) and frames is None:
            frames = robot.link_frames(q_star, params=bent)
        if self.geometry:
            state = (q_star, params, E, B, X, T, bent, wrenches)
            cols.update(self._geometry_twists(cond, state, frames))
        if self.deflection:
            point = (E @ X)[:, :3, 3]
            cols.update(
                deflection_twists(
                    model, self.deflection, q_star, wrenches, bent, point, R_B, frames=frames
                )
            )
        n = q.shape[0]
        pieces = _runs([cols[b.name] for b in self.blocks])
        twists = torch.cat([q.new_zeros(n, 6, 0), *pieces], -1)
        return PoseTwists(T, twists)

    @staticmethod
    def _split(blocks, tw: Tensor) -> dict[str, Tensor]:
        out, start = {}, 0
        for b in blocks:
            out[b.name] = tw[..., start : start + b.size]
            start += b.size
        return out

    def _geometry_twists(self, cond, state: tuple, frames: Tensor) -> dict[str, Tensor]:
        """Twists of the geometric blocks; ``state``: ``(q_star, params, E, B, X, T,
        bent, wrenches)`` of the chunk, ``frames`` its link frames at ``q_star``."""
        q_star, params, E, B, X, T, _, wrenches = state
        maps = origin_twist_maps(frames, params.origin_xyz, (E @ X)[:, :3, 3], B[..., :3, :3])
        out: dict[str, Tensor] = {}
        # Effects that read a condition per row (a temperature) make the origins' derivatives
        # per row; the others' stay shared by every row when taken apart from them.
        for per_row in (False, True):
            blocks = [b for b in self.geometry if (self.effects[b.name].needs is None) != per_row]
            if blocks:
                out.update(self._origin_twists(blocks, cond, q_star, params, maps))
        for b in self.geometry:  # effects that turn a joint axis: forward mode through FK
            if self._turns_axis[b.name]:
                out[b.name] = self._fk_twists(b, cond, q_star, B, X, T, wrenches)
        return out

    def _origin_twists(self, blocks, cond, q_star, params, maps) -> dict[str, Tensor]:
        """Twists of geometric ``blocks`` through the chain origins they move (forward
        mode on the origins, closed form from there); notes which turn a joint axis."""
        size = sum(b.size for b in blocks)
        wrapper = _KinematicParams(self.model)

        def origins(theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            vals = self._sub_params(blocks, theta, prefix="model.")
            return torch.func.functional_call(wrapper, vals, (cond,))

        theta0 = torch.zeros(size, dtype=q_star.dtype)

        def along(v: Tensor):
            return torch.func.jvp(origins, (theta0,), (v,))[1]

        eye = torch.eye(size, dtype=q_star.dtype)
        key = self._origins_key(blocks)
        if self._origins is not None and _same_values(self._origins[0], key):
            d_xyz, d_rot, d_axis = self._origins[1]  # every chunk's, at these values
        else:
            with torch.no_grad():  # values of the other effects plain: shared where they can be
                if size == 1:  # one direction (an expansion per row): no batching to pay for
                    d_xyz, d_rot, d_axis = (d[None] for d in along(eye[0]))
                else:
                    d_xyz, d_rot, d_axis = torch.func.vmap(along)(eye)
            if (d_xyz.dim(), d_rot.dim(), d_axis.dim()) == (3, 4, 3):  # no row dimension
                self._origins = (key, (d_xyz, d_rot, d_axis))
        tw = geometry_twists(maps, params.origin_rot, d_xyz, d_rot)
        turns_axis = d_axis.reshape(size, -1).abs().amax(1) > 0
        start = 0
        for b in blocks:
            self._turns_axis[b.name] = bool(turns_axis[start : start + b.size].any())
            start += b.size
        return self._split(blocks, tw)

    def _origins_key(self, blocks) -> tuple:
        """What the origins' derivatives along ``blocks`` depend on where they are the
        same for every row (no row dimension: no effect that reads a row's conditions,
        a temperature, takes part at its values): the blocks and every parameter value."""
        values = [p.detach().clone() for p in self.params.values()]
        return tuple(b.name for b in blocks), values

    def _fk_twists(self, block, cond, q_star, B, X, T, wrenches) -> Tensor:
        """Twists of one geometric block by forward mode through FK (generic path),
        the deflection's wrenches held fixed."""
        wrapper = _KinematicParams(self.model)
        model, robot = self.model, self.model.robot

        def pose(theta: Tensor) -> Tensor:
            vals = self._sub_params([block], theta, prefix="model.")
            p = KinematicParams(*torch.func.functional_call(wrapper, vals, (cond,)))
            p = model.deflected_params(q_star, p, cond, wrenches=wrenches)
            return B @ robot.fk(q_star, params=p) @ X

        theta0 = torch.zeros(block.size, dtype=q_star.dtype)
        eye = torch.eye(block.size, dtype=q_star.dtype)
        dT = torch.func.vmap(lambda v: torch.func.jvp(pose, (theta0,), (v,))[1])(eye)
        w = vee(dT[..., :3, :3] @ T[:, :3, :3].transpose(-1, -2))  # (k, n, 3)
        return torch.cat([dT[..., :3, 3], w], -1).permute(1, 2, 0)

    def _compliance(self) -> Tensor | None:
        comp = [e for e in self.model.effects if e.stage == "compliance"]
        if not comp:
            return None
        c = torch.zeros(self.model.robot.dof, dtype=comp[0].value.dtype)
        for e in comp:
            c[e.joint_index] += e.value.detach()
        return c

    def _joint_derivatives(self, q, cond, q_star, params, key, gravity):
        """``(dq, M)``: the joint-space and compliance parameters' ``dq_kin/dtheta - dC/dtheta
        g`` ``(n, dof, k)`` and the compliance's feedback ``M = I + C dg/dq`` ``(n, dof,
        dof)`` (None without compliance), ``dq*/dtheta = M^-1 dq``: :func:`settled_twists`."""
        model, robot = self.model, self.model.robot
        n, dof = q.shape
        payload = 0.0 if cond.payload is None else cond.payload
        # the torques come with dg/dq where that is computed afresh
        g, feedback = compliance_feedback(self._compliance(), robot, q_star, payload, params,
                                          key, gravity)  # fmt: skip
        if g is None:
            with torch.no_grad():
                g = robot.gravity_torques(q_star, payload=payload, gravity=gravity, params=params)
        kin = [b for b in self.joint if self.effects[b.name].stage == "joint"]
        size = sum(b.size for b in self.joint)
        # compliance columns zero, filled below
        dq = joint_effect_jacobian(model, q, cond, self.joint) if kin else q.new_zeros(n, dof, size)
        if dq is not None:
            start = 0
            for b in self.joint:
                e = self.effects[b.name]
                if e.stage == "compliance":  # d(-c g)/dc
                    dq[:, e.joint_index, start] = -g[:, e.joint_index] * b.scale
                start += b.size
        else:  # some effect couples joints: every direction through all
            dq = self._coupled_derivatives(q, cond, kin, g)
        return dq, feedback

    def _coupled_derivatives(self, q, cond, kin, g) -> Tensor:
        """``dq_kin/dtheta (n, dof, k)`` by forward mode through every joint effect."""
        model, (n, dof) = self.model, q.shape
        if kin:
            wrapper = _KinematicJoints(model)

            def q_kin(theta_k: Tensor) -> Tensor:
                vals = self._sub_params(kin, theta_k, prefix="model.")
                return torch.func.functional_call(wrapper, vals, (q, cond)).reshape(-1)

            size = sum(b.size for b in kin)
            _, Jk = jacobian(q_kin, torch.zeros(size, dtype=q.dtype), chunk_size=None)
            dq_kin = Jk.reshape(n, dof, size)
        columns, k_col = [], 0
        for b in self.joint:  # assemble in block order
            e = self.effects[b.name]
            if e.stage == "compliance":
                col = torch.zeros(n, dof, 1, dtype=q.dtype)
                col[:, e.joint_index, 0] = -g[:, e.joint_index] * b.scale  # d(-c g)/dc
                columns.append(col)
            else:
                columns.append(dq_kin[..., k_col : k_col + b.size])
                k_col += b.size
        return torch.cat(columns, -1)


def settled_twists(P: Tensor, dq: Tensor, feedback: Tensor | None) -> Tensor:
    """``P M^-1 dq``: the twists ``(n, r, k)`` of joint-space derivatives ``dq (n, dof,
    k)`` mapped by ``P (n, r, dof)`` through the compliance's feedback ``M (n, dof,
    dof)`` (None: none). The feedback is solved on ``P``'s ``r`` rows (6 twist rows, 3
    point rows) rather than on every one of the ``k`` columns: the same product in
    exact arithmetic, a few times less work where ``k`` is the candidates' columns."""
    if feedback is None:
        return P @ dq
    return torch.linalg.solve(feedback.mT, P.mT).mT @ dq  # P M^-1 = (M^-T P^T)^T


def _same_values(a: tuple, b: tuple) -> bool:
    """Whether two :meth:`StructuredJacobian._origins_key` are equal."""
    return a[0] == b[0] and all(torch.equal(x, y) for x, y in zip(a[1], b[1], strict=True))


def _runs(pieces: list[Tensor]) -> list[Tensor]:
    """``pieces`` (``(n, 6, k)`` each) with neighbours that lie side by side in one
    tensor (blocks split from one source's twists, in order) joined into one view: the
    same concatenation, copied from a few strided views instead of one per block."""
    out: list[Tensor] = []
    for p in pieces:
        if out and _follows(out[-1], p):
            a = out[-1]
            size = (*a.shape[:-1], a.shape[-1] + p.shape[-1])
            out[-1] = a.as_strided(size, a.stride(), a.storage_offset())
        else:
            out.append(p)
    return out


def _follows(a: Tensor, b: Tensor) -> bool:
    """Whether ``b`` continues ``a`` along the last dimension in the same storage (a
    plain value: no derivative is traced through the joined view)."""
    return (
        not (a.requires_grad or b.requires_grad)
        and a.dim() == b.dim()
        and a.shape[:-1] == b.shape[:-1]
        and a.stride() == b.stride()
        and a.dtype == b.dtype
        and a.untyped_storage().data_ptr() == b.untyped_storage().data_ptr()
        and b.storage_offset() == a.storage_offset() + a.shape[-1] * a.stride(-1)
    )


# [rad or m] difference step of the joint effects' derivative in point_jacobian: its
# truncation is ~1e-6 of their slope's change, its round-off ~1e-16 / 1e-6 = 1e-10.
_JOINT_STEP = 1e-6


@torch.no_grad()
def point_jacobian(model: ExtendedModel, q: Tensor, cond: Conditions) -> Tensor:
    """``(n, 3, dof)`` motion of the measured point (measurement frame) per unit of each
    commanded joint value ``q (n, dof)``, every effect included: the joint effects'
    derivative (differences in joint space), the compliance's feedback
    ``(I + C dg/dq)^-1`` and the geometric Jacobian at the true joint values (the
    deflection's bending held, a second-order term)."""
    robot = model.robot
    params, gravity, q_star, _, bent, _ = loaded_state(model, q, cond)
    E = robot.fk(q_star, params=bent)
    group = cond.group if model.base.sets > 1 else None
    B = model.base.matrix()[0] if group is None else model.base.matrix(group)
    X = model.tool.matrix()[0] if group is None else model.tool.matrix(group)
    lever = (E @ X)[:, :3, 3] - E[:, :3, 3]
    tw = point_joint_twists(robot.jacobian(q_star, params=bent), lever, B[..., :3, :3])

    # the joint effects' derivative by differences in joint space (no FK, no forward
    # mode: vmap over some effects' index updates would load torch's compiler, ~1 s)
    base = model.kinematic_joint_values(q, cond)
    dq = torch.stack(
        [(model.kinematic_joint_values(q + _JOINT_STEP * e, cond) - base) / _JOINT_STEP
         for e in torch.eye(q.shape[-1], dtype=q.dtype)],
        -1,
    )  # fmt: skip
    c = StructuredJacobian(model, ())._compliance()
    payload = 0.0 if cond.payload is None else cond.payload
    _, feedback = compliance_feedback(c, robot, q_star, payload, params, None, gravity)
    return settled_twists(tw[:, :3, :], dq, feedback)

"""Geometric effects: perturbations of the kinematic parameters.

Origin ``k`` (see :class:`~hybrid_pk.robot.ChainSpec`) is the fixed transform in front
of chain joint ``k + 1``, so the effect named by chain joint ``j`` (index ``i`` along the
chain, mimic joints included) perturbs origin ``i``: the link that carries joint ``j``.
Origin 0 (in front of the first joint) and the tip are indistinguishable from the base
and tool frames, which every fit estimates, so the first joint has no geometric
candidates.

- ``link_length``:       origin translation + dp                  value dp (3,) [m]
- ``axis_misalignment``: origin rotation · exp(w)                 value w (3,) [rad]
- ``thermal_expansion``: every origin translation * (1 + alpha (T - T_ref))   [1/K]
"""

from __future__ import annotations

import math

import torch

from hybrid_pk.effects.base import Effect, register, sds_below
from hybrid_pk.effects.conditions import Conditions
from hybrid_pk.effects.limits import MAX_ROTATION_DEG, MAX_TRANSLATION_M, WARNED_TRANSLATION_M
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import so3_exp
from hybrid_pk.geometry.tangents import carried
from hybrid_pk.robot import KinematicParams
from hybrid_pk.robot.chain import plain_inputs

__all__ = ["REFERENCE_TEMPERATURE", "AxisMisalignment", "LinkLength", "ThermalExpansion"]

REFERENCE_TEMPERATURE = 20.0  # [°C] ISO 1 reference temperature of dimensional metrology


def _onehot_rows(n: int, index: int, like: torch.Tensor) -> torch.Tensor:
    e = torch.zeros(n, 1, dtype=like.dtype, device=like.device)
    e[index] = 1
    return e


@register
class LinkLength(Effect):
    kind, unit, stage, scale, shape = "link_length", "m", "geometry", 1e-3, (3,)
    joint_set, limit, evidence = "chain", MAX_TRANSLATION_M, "pose"
    simulate_random = first_joint_is_frame = True  # origin 0 is the base frame's
    equation = "error vector of a fixed joint-origin translation"
    description = "translation error of the origin in front of the joint (vector)"

    @classmethod
    def implausible(cls, value: float | list[float], std=None) -> list[str]:
        size = math.hypot(*(value if isinstance(value, list) else [value]))
        if size <= WARNED_TRANSLATION_M:
            return []
        return [
            f"a link-length correction of {1e3 * size:.3g} mm is beyond what machining and "
            f"assembly leave (sub-mm; warned above {1e3 * WARNED_TRANSLATION_M:g} mm): it "
            "likely trades off with another cause along a direction the data barely see"
        ]

    def apply_params(self, params: KinematicParams, cond: Conditions) -> KinematicParams:
        xyz = params.origin_xyz
        value = self.value.to(xyz.dtype)  # constants carried: see geometry.tangents
        shift = carried(_onehot_rows(xyz.shape[-2], self.joint_index, xyz), value) * value
        return params._replace(origin_xyz=carried(xyz, shift) + shift)


@register
class AxisMisalignment(Effect):
    """Small rotation ``w`` of the origin in front of the joint, perpendicular to the
    joint's axis (a rotation about the axis itself is exactly a ``joint_offset``).

    Stored as two components on a basis ``e1, e2`` perpendicular to the axis (joint
    frame coordinates); reported as the rotation vector ``w = u e1 + v e2`` [rad].
    """

    kind, unit, stage, scale, shape = "axis_misalignment", "rad", "geometry", 1e-3, (2,)
    joint_set, limit, evidence = "chain", math.radians(MAX_ROTATION_DEG), "pose"
    simulate_random = first_joint_is_frame = True  # origin 0 is the base frame's
    equation = "small rotation vector of a fixed joint-origin rotation"
    description = (
        "rotation error of that origin, perpendicular to the joint axis (a rotation about "
        "the axis *is* a joint offset)"
    )

    def __init__(self, robot, joint: str | None = None, value=None) -> None:
        super().__init__(robot, joint, None)
        a = torch.as_tensor(robot.spec.axes[self.joint_index], dtype=robot.dtype)
        helper = torch.eye(3, dtype=robot.dtype)[int(a.abs().argmin())]
        e1 = torch.linalg.cross(a, helper)
        e1 = e1 / e1.norm()
        self.register_buffer("basis", torch.stack([e1, torch.linalg.cross(a, e1)]))  # (2, 3)
        if value is not None:
            v = torch.as_tensor(value, dtype=robot.dtype).reshape(-1)
            if v.numel() == 3:
                axial = float(v @ a)
                if abs(axial) > 1e-12 + 1e-9 * float(v.norm()):
                    raise HybridPKError(
                        f"axis_misalignment:{joint} = {v.tolist()} has a component "
                        f"{axial:.3g} rad about the joint's own axis {a.tolist()}: that is a "
                        "joint_offset; give only the perpendicular part"
                    )
                v = self.basis @ v
            elif v.numel() != 2:
                raise HybridPKError(
                    f"axis_misalignment:{joint} takes a rotation vector of 3 values [rad], "
                    f"got {v.numel()}"
                )
            with torch.no_grad():
                self.value.copy_(v)

    def rotation_vector(self) -> torch.Tensor:
        """``(3,)`` the misalignment as a rotation vector in the joint frame [rad]."""
        return self.value @ self.basis.to(self.value.dtype)

    def report_value(self) -> list[float]:
        return [float(x) for x in self.rotation_vector().detach().to(torch.float64)]

    def magnitude(self) -> float:
        return float(self.value.detach().norm())

    def apply_params(self, params: KinematicParams, cond: Conditions) -> KinematicParams:
        R = params.origin_rot
        dR = so3_exp(self.rotation_vector().to(R.dtype))
        e = _onehot_rows(R.shape[-3], self.joint_index, R)[..., None]
        eye = carried(torch.eye(3, dtype=R.dtype, device=R.device), dR)  # see geometry.tangents
        change = carried(e, dR) * (dR - eye)
        return params._replace(origin_rot=R @ (carried(eye, change) + change))


# Largest credible linear expansion coefficient [1/K]: structural metals are 1e-5..2.5e-5,
# polymers reach ~1e-4.
MAX_CREDIBLE_EXPANSION = 5e-5
# Most negative one [1/K]: twice that of the only structures that shrink as they warm,
# carbon-fibre laminates along the fibre (-0.5e-6 .. -1e-6 1/K); a laser tracker's
# uncompensated air refraction scales its distances by ~1e-6 1/K, inside the same range.
MIN_CREDIBLE_EXPANSION = -2e-6


@register
class ThermalExpansion(Effect):
    kind, unit, stage, scale, needs = "thermal_expansion", "1/K", "geometry", 1e-5, "temperature"
    per_joint, joints, evidence = False, "none", "temperature"
    # ten times the largest credible coefficient (five times a polymer's): beyond it a
    # fit stands in for something else (a wrong URDF, rows of another robot), as the
    # other effects' limits do at ten times their credible sizes
    limit, floor = 10 * MAX_CREDIBLE_EXPANSION, MIN_CREDIBLE_EXPANSION
    equation = "link translations × (1 + α (T − T_ref)), T_ref = 20 °C"
    description = "all link translations × (1 + α(T − 20 °C))"
    unplannable = (
        "its information comes from the temperature spread over the campaign, not from the poses"
    )

    @classmethod
    def refused(cls, value: float | list[float], std=None) -> list[str]:
        """A robot that shrinks as it warms by more than any structure does (below
        ``floor`` by more than ``SIGN_SIGMAS`` of its std): the coefficient then
        stands in for something else that changes with the temperature, e.g. the
        instrument drifting over the hours the room warmed."""
        if not cls.below_zero(value, std, cls.floor):
            return []
        alpha = float(value)  # type: ignore[arg-type]
        return [
            f"alpha = {alpha:.3g} 1/K{sds_below(value, std)} is not a thermal expansion: no "
            f"structure shrinks as it warms by more than {-cls.floor:.0e} 1/K; it likely "
            "absorbs an error that drifts with time or temperature (the instrument, the set-up)"
        ]

    @classmethod
    def implausible(cls, value: float | list[float], std=None) -> list[str]:
        alpha = float(value)  # type: ignore[arg-type]
        if cls.floor <= alpha <= MAX_CREDIBLE_EXPANSION:
            return []
        return cls.refused(value, std) or [
            f"alpha = {alpha:.3g} 1/K is outside any structural material "
            f"({cls.floor:.0e} .. {MAX_CREDIBLE_EXPANSION:.0e})"
        ]

    def apply_params(self, params: KinematicParams, cond: Conditions) -> KinematicParams:
        if cond.temperature is None:
            raise HybridPKError(
                "thermal_expansion needs the temperature of each row [°C]: a temperature "
                "column in the data, or cond=Conditions(temperature=...)"
            )
        if plain_inputs(self.value) and not bool(self.value.detach().any()):
            # zero (a candidate being scored): every factor is exactly 1, so the shared
            # parameters are the same values without one copy of the chain per row
            return params
        dT = (cond.temperature - REFERENCE_TEMPERATURE).to(params.origin_xyz.dtype)
        grow = self.value * carried(dT[..., None, None], self.value)  # see geometry.tangents
        factor = carried(1.0, grow) + grow  # (*B, 1, 1)
        n = params.origin_xyz.shape[-2]
        batch = dT.shape
        return KinematicParams(
            carried(params.origin_xyz, factor) * factor,
            params.origin_rot.expand(*batch, n, 3, 3),
            params.axis.expand(*batch, *params.axis.shape[-2:]),
        )

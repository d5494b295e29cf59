"""Joint-space effects: commanded joint value -> true joint value.

Conventions (contract section 4), per joint ``i``:

- ``joint_offset``:       theta_true = theta + delta                               [rad]
- ``gear_ratio``:         theta_true = theta * (1 + s)                             [1]
- ``joint_eccentricity``: theta_true = theta + a sin(theta) + b cos(theta)         [rad]
- ``cyclic_error_<n>``:   theta_true = theta + a sin(n theta) + b cos(n theta)     [rad]
- ``backlash``:           theta_true = theta + (b / 2) * approach direction        [rad]
- ``joint_compliance``:   theta_true = theta + c * tau_gravity(theta_true, payload) [rad/Nm]

``tau_gravity`` is the torque gravity exerts on the joint, i.e. minus the holding
torque ``Robot.gravity_torques`` returns (pinocchio's ``g(q)``): with ``c > 0`` the
arm sags under its weight, as a real spring-loaded gearbox does.
"""

from __future__ import annotations

import functools
from typing import ClassVar

import torch
from torch import Tensor

from hybrid_pk.effects.base import Effect, register, register_family
from hybrid_pk.effects.conditions import Conditions
from hybrid_pk.errors import HybridPKError

__all__ = [
    "CYCLIC_PREFIX",
    "MAX_CYCLIC_ORDER",
    "Backlash",
    "CyclicError",
    "GearRatio",
    "JointCompliance",
    "JointEccentricity",
    "JointOffset",
    "cyclic_error_kind",
]


def _add_to_joint(q: Tensor, index: int, delta: Tensor) -> Tensor:
    onehot = torch.zeros(q.shape[-1], dtype=q.dtype, device=q.device)
    onehot[index] = 1
    return q + delta[..., None] * onehot


@register
class JointOffset(Effect):
    kind, unit, stage, scale = "joint_offset", "rad", "joint", 1e-3

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        return _add_to_joint(q, self.joint_index, self.value.to(q.dtype).expand(q.shape[:-1]))


@register
class GearRatio(Effect):
    kind, unit, stage, scale = "gear_ratio", "1", "joint", 1e-4

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        return _add_to_joint(q, self.joint_index, q[..., self.joint_index] * self.value)


@register
class JointEccentricity(Effect):
    """Value ``(a, b)`` [rad]; the contract's scalar value is the amplitude sqrt(a² + b²)."""

    kind, unit, stage, scale, shape = "joint_eccentricity", "rad", "joint", 1e-3, (2,)
    order: ClassVar[int] = 1  # cycles per revolution of the joint

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        th = self.order * q[..., self.joint_index]
        a, b = self.value.to(q.dtype).unbind(-1)
        return _add_to_joint(q, self.joint_index, a * torch.sin(th) + b * torch.cos(th))


class CyclicError(JointEccentricity):
    """``cyclic_error_<n>``: theta_true = theta + a sin(n theta) + b cos(n theta) [rad].

    A periodic angle error with ``n`` cycles per revolution of the joint (2 <= n <=
    :data:`MAX_CYCLIC_ORDER`): a gear's or bearing's out-of-roundness (n = 2), the
    cyclic error of a multi-pole output encoder or of a gear stage turning ``n`` times
    per revolution. ``joint_eccentricity`` is the same law at n = 1. Value ``(a, b)``.
    """

    scale = 1e-4


MAX_CYCLIC_ORDER = 36  # a period of 10 degrees; the diagnosis tests every order up to it
CYCLIC_PREFIX = "cyclic_error_"


@functools.cache
def _cyclic_class(order: int) -> type[CyclicError]:
    return type(
        f"CyclicError{order}", (CyclicError,), {"kind": f"{CYCLIC_PREFIX}{order}", "order": order}
    )


def cyclic_error_kind(kind: str) -> type[CyclicError] | None:
    """The class of ``cyclic_error_<n>`` (``n`` from 2 to :data:`MAX_CYCLIC_ORDER`), or None."""
    digits = kind.removeprefix(CYCLIC_PREFIX)
    if not digits.isdigit() or digits != str(int(digits)):
        return None
    order = int(digits)
    return _cyclic_class(order) if 2 <= order <= MAX_CYCLIC_ORDER else None


register_family(CYCLIC_PREFIX, cyclic_error_kind, f"{CYCLIC_PREFIX}<n> (n = 2..{MAX_CYCLIC_ORDER})")


@register
class Backlash(Effect):
    """Value ``b`` = full play [rad]; needs the approach direction of every sample.

    Measured rows get it from their acquisition order (``conditions_from_data``). An IK
    target has none: ``solve_ik`` / ``solve_ik_two_stage`` (and ``hybrid-pk ik
    --approach``) solve for a stated direction per joint (+1: the joint arrives moving
    in its positive direction, -1: negative) or, by default, for the mid-play model
    (direction 0, half-way between both approaches) and say so
    (:mod:`hybrid_pk.ik.conditions`).
    """

    kind, unit, stage, scale, needs = "backlash", "rad", "joint", 1e-3, "direction"

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        if cond.direction is None:
            raise HybridPKError(
                f"backlash on {self.joint} needs the approach direction of each row: pass "
                "cond=conditions_from_data(data) for measured rows in acquisition order, or "
                "Conditions(direction=...) with +1 / -1 / 0 (mid-play) per joint; the IK "
                "functions take approach= instead"
            )
        d = cond.direction[..., self.joint_index].to(q.dtype)
        return _add_to_joint(q, self.joint_index, 0.5 * self.value * d)


@register
class JointCompliance(Effect):
    """Value ``c`` [rad/Nm]. Solved jointly with the other compliant joints by the model
    as a fixed point (torques depend on the deflected configuration)."""

    kind, unit, stage, scale = "joint_compliance", "rad/Nm", "compliance", 1e-6

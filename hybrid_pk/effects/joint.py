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
import math
from typing import ClassVar

import torch
from torch import Tensor

from hybrid_pk.effects.base import Effect, register, register_family
from hybrid_pk.effects.conditions import Conditions
from hybrid_pk.effects.limits import (
    DRAWN_COMPLIANCE,
    MAX_BACKLASH_DEG,
    MAX_COMPLIANCE,
    MAX_GEAR_RATIO,
    MAX_ROTATION_DEG,
)
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry.tangents import carried

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
    # One column replaced (not q + delta * one-hot): forward mode under vmap takes torch's
    # native rules for these ops, a third of the time of the broadcast multiply-add.
    column = (q[..., index] + delta)[..., None]
    return torch.cat([q[..., :index], column, q[..., index + 1 :]], -1)


@register
class JointOffset(Effect):
    kind, unit, stage, scale = "joint_offset", "rad", "joint", 1e-3
    limit = math.radians(MAX_ROTATION_DEG)
    simulate_random = first_joint_is_frame = True  # a first-joint offset is a base yaw
    law = "θ_true - θ = δ: a flat line"
    equation = description = "θ_true = θ + δ"

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        return _add_to_joint(q, self.joint_index, self.value.to(q.dtype).expand(q.shape[:-1]))

    def joint_derivatives(self, q: Tensor, cond: Conditions, step: float):
        """Closed-form forward-mode derivatives (see :mod:`.base`), the same numbers."""
        ones = q.new_ones(q.shape[:-1])
        return ones, (ones * step)[None]


@register
class GearRatio(Effect):
    kind, unit, stage, scale = "gear_ratio", "1", "joint", 1e-4
    joints, limit, simulate_random = "revolute", MAX_GEAR_RATIO, True
    law = "θ_true - θ = s · θ: a line through the origin, slope s"
    equation, description = "θ_true = θ · (1 + s)", "θ_true = θ(1 + s)"

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        return _add_to_joint(q, self.joint_index, q[..., self.joint_index] * self.value)

    def joint_derivatives(self, q: Tensor, cond: Conditions, step: float):
        qj = q[..., self.joint_index]
        return 1 + self.value.detach().to(q.dtype).expand_as(qj), (qj * step)[None]


@register
class JointEccentricity(Effect):
    """Value ``(a, b)`` [rad]; the contract's scalar value is the amplitude sqrt(a² + b²)."""

    kind, unit, stage, scale, shape = "joint_eccentricity", "rad", "joint", 1e-3, (2,)
    order: ClassVar[int] = 1  # cycles per revolution of the joint
    joints, limit, simulate_random = "revolute", math.radians(MAX_ROTATION_DEG), True
    equation = "θ_true = θ + a sin θ + b cos θ; value: amplitude √(a² + b²)"
    description = "θ_true = θ + a sin θ + b cos θ (value √(a²+b²); `components` [a, b])"

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        qj = q[..., self.joint_index]
        th = qj if self.order == 1 else carried(float(self.order), qj) * qj
        a, b = self.value.to(q.dtype).unbind(-1)
        return _add_to_joint(q, self.joint_index, a * torch.sin(th) + b * torch.cos(th))

    def joint_derivatives(self, q: Tensor, cond: Conditions, step: float):
        qj = q[..., self.joint_index]
        n = float(self.order)
        th = qj if self.order == 1 else n * qj
        a, b = self.value.detach().to(q.dtype).unbind(-1)
        s, c = torch.sin(th), torch.cos(th)
        ds, dc = (c, -s) if self.order == 1 else (c * n, -(s * n))
        return 1 + (a * ds + b * dc), torch.stack([step * s, step * c])


MAX_CYCLIC_ORDER = 36  # a period of 10 degrees; the diagnosis tests every order up to it


class CyclicError(JointEccentricity):
    """``cyclic_error_<n>``: theta_true = theta + a sin(n theta) + b cos(n theta) [rad].

    A periodic angle error with ``n`` cycles per revolution of the joint (2 <= n <=
    :data:`MAX_CYCLIC_ORDER`): a gear's or bearing's out-of-roundness (n = 2), the
    cyclic error of a multi-pole output encoder or of a gear stage turning ``n`` times
    per revolution. ``joint_eccentricity`` is the same law at n = 1. Value ``(a, b)``.
    """

    scale = 1e-4
    simulate_random = False
    equation = (
        f"θ_true = θ + a sin nθ + b cos nθ, n = 2 … {MAX_CYCLIC_ORDER} (one kind per "
        "order); value: amplitude √(a² + b²)"
    )
    description = (
        f"θ_true = θ + a sin nθ + b cos nθ, n = 2 … {MAX_CYCLIC_ORDER} cycles per turn of "
        "the joint: a multi-pole output encoder's or a gear stage's periodic error, an "
        "out-of-round bearing (n = 2); value √(a²+b²), `components` [a, b]. At every step "
        "the diagnosis fits each order's sinusoid to the angle error the current model "
        "leaves, block by block of the blocked hold-out, and tests the orders that predict "
        "the held-out blocks better by the practical margin (every order counts in the "
        "Bonferroni level); an order that another order predicts the blocked hold-out as "
        "well as (within the margin) or better is listed under `ambiguous` and never named; "
        "so is one "
        "that does not predict both ends of its joint's measured range (the lowest and "
        "highest quarter of the rows, each held out in turn) by the margin; a named one "
        "gives `fitted_range_rad` and `own_range_gain_mm`, and a warning when its joint "
        "moves beyond that range"
    )


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


register_family(
    CYCLIC_PREFIX, cyclic_error_kind, f"{CYCLIC_PREFIX}<n> (n = 2..{MAX_CYCLIC_ORDER})", CyclicError
)


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
    joints, positive, limit = "revolute", True, math.radians(MAX_BACKLASH_DEG)
    evidence, simulate_random = "row_order", True
    law = "θ_true - θ = ± b/2 by approach direction: two levels, b apart"
    equation = "θ_true = θ + (b / 2) · sign(approach direction); b the full play"
    description = (
        "θ_true = θ + (b/2)·sign(approach direction), direction from row order; an IK "
        'target has no row order: `solve_ik*(…, approach=+1 / -1 / {"joint_3": -1})` and '
        "`hybrid-pk ik --approach + / - / joint_3=-` solve for the side the robot will come "
        "from, and without it the mid-play model (direction 0, at most b/2 from either "
        "side) is solved and a note says so"
    )

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        if cond.direction is None:
            raise HybridPKError(
                f"backlash on {self.joint} needs the approach direction of each row: pass "
                "cond=conditions_from_data(data) for measured rows in acquisition order, or "
                "Conditions(direction=...) with +1 / -1 / 0 (mid-play) per joint; the IK "
                "functions take approach= instead"
            )
        if cond.direction.shape[-1:] != q.shape[-1:]:
            raise HybridPKError(
                f"Conditions.direction must be (*B, {q.shape[-1]}): one +1 / -1 / 0 per "
                f"joint, found {tuple(cond.direction.shape)}"
            )
        d = cond.direction[..., self.joint_index].to(q.dtype)
        half = carried(0.5, self.value) * self.value  # see geometry.tangents
        return _add_to_joint(q, self.joint_index, half * carried(d, half))

    def joint_derivatives(self, q: Tensor, cond: Conditions, step: float):
        d = cond.direction[..., self.joint_index].to(q.dtype)
        return q.new_ones(q.shape[:-1]), ((0.5 * step) * d)[None]


@register
class JointCompliance(Effect):
    """Value ``c`` [rad/Nm]. Solved jointly with the other compliant joints by the model
    as a fixed point (torques depend on the deflected configuration)."""

    kind, unit, stage, scale = "joint_compliance", "rad/Nm", "compliance", 1e-6
    joints, positive, limit, evidence = "revolute", True, MAX_COMPLIANCE, "torque"
    drawn = DRAWN_COMPLIANCE
    simulate_random = needs_torque = True
    law = "θ_true - θ = c · τ_gravity: a line through the origin, slope c"
    equation = "θ_true = θ + c · τ_gravity(θ_true, payload)"
    description = (
        "θ_true = θ + c·τ_gravity(θ_true, payload) — τ_gravity is the torque gravity exerts "
        "(minus the holding torque `Robot.gravity_torques`), so c > 0 sags"
    )

"""What a small, physical correction of a URDF can be: the largest credible size of
each effect (the diagnosis flags larger fitted values, simulated campaigns draw within).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hybrid_pk.effects.base import Effect
    from hybrid_pk.robot import Robot

__all__ = [
    "MAX_BACKLASH_DEG",
    "MAX_COMPLIANCE",
    "MAX_GEAR_RATIO",
    "MAX_ROTATION_DEG",
    "MAX_TRANSLATION_M",
    "effect_limit",
    "size_limit",
]

MAX_ROTATION_DEG = 5.0
MAX_BACKLASH_DEG = 1.0
MAX_TRANSLATION_M = 0.05
MAX_GEAR_RATIO = 0.01
MAX_COMPLIANCE = 1e-4  # [rad/Nm]; industrial joints are 1e-7 .. 1e-5


def size_limit(kind: str, unit: str, prismatic: bool = False) -> float | None:
    """Largest credible norm of an effect's value [its unit], or None where the limit
    depends on the loads (deflections per metre of extension) or on the data
    (thermal expansion).

    Args:
        prismatic: the effect shifts a prismatic joint (its value is then a length).
    """
    if unit == "rad/Nm":  # joint and tilt compliance
        return MAX_COMPLIANCE
    if kind == "gear_ratio":
        return MAX_GEAR_RATIO
    if unit == "m" or prismatic:
        return MAX_TRANSLATION_M
    if unit == "rad":
        return math.radians(MAX_BACKLASH_DEG if kind == "backlash" else MAX_ROTATION_DEG)
    return None


def effect_limit(effect: Effect, robot: Robot) -> float | None:
    """:func:`size_limit` of a made effect of ``robot`` (a joint-space effect of a
    prismatic joint is a length)."""
    prismatic = (
        effect.stage == "joint"
        and effect.joint is not None
        and robot.joint_types[effect.joint_index] == "prismatic"
    )
    return size_limit(effect.kind, effect.unit, prismatic)

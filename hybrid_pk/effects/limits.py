"""What a small, physical correction of a URDF can be: the largest credible sizes the
effect classes state as their ``limit`` (the diagnosis flags larger fitted values,
simulated campaigns draw within).
"""

from __future__ import annotations

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
]

MAX_ROTATION_DEG = 5.0
MAX_BACKLASH_DEG = 1.0
MAX_TRANSLATION_M = 0.05
MAX_GEAR_RATIO = 0.01
MAX_COMPLIANCE = 1e-4  # [rad/Nm]; industrial joints are 1e-7 .. 1e-5


def effect_limit(effect: Effect, robot: Robot) -> float | None:
    """Largest credible norm of a made effect's value [its unit], or None where the
    limit depends on the loads (deflections per metre of extension) or on the data
    (thermal expansion): the ``limit`` its class states, except that a joint-space
    angle of a prismatic joint of ``robot`` is a length."""
    prismatic = (
        effect.stage == "joint"
        and effect.joint is not None
        and robot.joint_types[effect.joint_index] == "prismatic"
    )
    return MAX_TRANSLATION_M if prismatic and effect.unit == "rad" else effect.limit

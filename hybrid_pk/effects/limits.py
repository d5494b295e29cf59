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
    "DRAWN_COMPLIANCE",
    "MAX_BACKLASH_DEG",
    "MAX_COMPLIANCE",
    "MAX_GEAR_RATIO",
    "MAX_ROTATION_DEG",
    "MAX_TRANSLATION_M",
    "WARNED_TRANSLATION_M",
    "drawn_limit",
    "effect_limit",
]

MAX_ROTATION_DEG = 5.0  # [deg] a joint zero or origin off by more is a wrong URDF, not a tolerance
MAX_BACKLASH_DEG = 1.0  # [deg] worn gearboxes play arcminutes; a degree is a loose coupling
MAX_TRANSLATION_M = 0.05  # [m] machining and assembly errors are sub-mm; 5 cm is a wrong link
# [m] a named translation above this is warned about: ten times a sub-mm tolerance, a
# tenth of the structural limit (the expansion coefficient's convention)
WARNED_TRANSLATION_M = MAX_TRANSLATION_M / 10
MAX_GEAR_RATIO = 0.01  # 1 % is an encoder scaling mistake, far beyond a gear's tolerance
# [rad/Nm]: industrial joints are 1e-7 .. 1e-5, torque-sensed cobot joints and small
# strain-wave gears at low torque reach 1e-4; ten times that is no metal gear train (a
# compliance that bends its joint beyond MAX_ROTATION_DEG under the data's gravity is
# flagged as well, whatever its size)
MAX_COMPLIANCE = 1e-3
# [rad/Nm]: simulated joints are drawn within the soft end of real ones (a cobot's), not
# up to what the diagnosis still credits
DRAWN_COMPLIANCE = 1e-4


def effect_limit(effect: Effect, robot: Robot) -> float | None:
    """Largest credible norm of a made effect's value [its unit], or None where the
    limit depends on the loads (deflections per metre of extension): the ``limit`` its
    class states, except that a joint-space angle of a prismatic joint of ``robot`` is
    a length."""
    prismatic = (
        effect.stage == "joint"
        and effect.joint is not None
        and robot.joint_types[effect.joint_index] == "prismatic"
    )
    return MAX_TRANSLATION_M if prismatic and effect.unit == "rad" else effect.limit


def drawn_limit(effect: Effect, robot: Robot) -> float | None:
    """Largest norm simulation draws ``effect`` at: its class's ``drawn`` where stated
    (compliances: real joints, below what the diagnosis credits), else
    :func:`effect_limit`."""
    drawn = getattr(type(effect), "drawn", None)
    return drawn if drawn is not None else effect_limit(effect, robot)

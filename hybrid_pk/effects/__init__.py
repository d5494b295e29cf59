"""Physical error effects and the extended model that applies them."""

from hybrid_pk.effects import deflection as _deflection  # noqa: F401  (registers effects)
from hybrid_pk.effects import geometric as _geometric  # noqa: F401  (registers effects)
from hybrid_pk.effects import joint as _joint  # noqa: F401  (registers effects)
from hybrid_pk.effects.base import EFFECTS as EFFECTS
from hybrid_pk.effects.base import Effect as Effect
from hybrid_pk.effects.base import effect_joint_names as effect_joint_names
from hybrid_pk.effects.base import entry_label as entry_label
from hybrid_pk.effects.base import make_effect as make_effect
from hybrid_pk.effects.conditions import Conditions as Conditions
from hybrid_pk.effects.conditions import approach_direction as approach_direction
from hybrid_pk.effects.conditions import conditions_from_data as conditions_from_data
from hybrid_pk.effects.extended import ExtendedModel as ExtendedModel
from hybrid_pk.effects.extended import RigidFrame as RigidFrame
from hybrid_pk.effects.gravity import Gravity as Gravity
from hybrid_pk.effects.gravity import parse_gravity as parse_gravity
from hybrid_pk.effects.gravity import unloaded_reason as unloaded_reason

__all__ = [
    "EFFECTS",
    "Conditions",
    "Effect",
    "ExtendedModel",
    "Gravity",
    "RigidFrame",
    "approach_direction",
    "conditions_from_data",
    "effect_joint_names",
    "entry_label",
    "make_effect",
    "parse_gravity",
    "unloaded_reason",
]

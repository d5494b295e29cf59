"""Virtual measurement campaigns: trajectories, injected error effects, noisy tracker data."""

from hybrid_pk.simulate.campaign import random_frames as random_frames
from hybrid_pk.simulate.campaign import simulate_campaign as simulate_campaign
from hybrid_pk.simulate.effect_specs import effect_entry as effect_entry
from hybrid_pk.simulate.effect_specs import is_hidden_spec as is_hidden_spec
from hybrid_pk.simulate.effect_specs import paper_effects as paper_effects
from hybrid_pk.simulate.effect_specs import parse_effects as parse_effects
from hybrid_pk.simulate.effect_specs import random_effects as random_effects
from hybrid_pk.simulate.trajectories import TRAJECTORIES as TRAJECTORIES
from hybrid_pk.simulate.trajectories import IsoCube as IsoCube
from hybrid_pk.simulate.trajectories import Trajectory as Trajectory
from hybrid_pk.simulate.trajectories import iso_cube as iso_cube
from hybrid_pk.simulate.trajectories import make_trajectory as make_trajectory

__all__ = [
    "TRAJECTORIES",
    "IsoCube",
    "Trajectory",
    "effect_entry",
    "is_hidden_spec",
    "iso_cube",
    "make_trajectory",
    "paper_effects",
    "parse_effects",
    "random_effects",
    "random_frames",
    "simulate_campaign",
]

"""Virtual measurement campaigns: trajectories, injected error effects, noisy tracker data."""

from hybrid_pk.simulate.campaign import random_frames as random_frames
from hybrid_pk.simulate.campaign import simulate_campaign as simulate_campaign
from hybrid_pk.simulate.effect_specs import effect_entry as effect_entry
from hybrid_pk.simulate.effect_specs import is_hidden_spec as is_hidden_spec
from hybrid_pk.simulate.effect_specs import paper_effects as paper_effects
from hybrid_pk.simulate.effect_specs import parse_effects as parse_effects
from hybrid_pk.simulate.effect_specs import random_effects as random_effects
from hybrid_pk.simulate.gross_errors import displace_rows as displace_rows
from hybrid_pk.simulate.mounting import MOUNTS as MOUNTS
from hybrid_pk.simulate.mounting import Mount as Mount
from hybrid_pk.simulate.mounting import mount_from_gravity as mount_from_gravity
from hybrid_pk.simulate.mounting import parse_mount as parse_mount
from hybrid_pk.simulate.trajectories import TRAJECTORIES as TRAJECTORIES
from hybrid_pk.simulate.trajectories import IsoCube as IsoCube
from hybrid_pk.simulate.trajectories import Trajectory as Trajectory
from hybrid_pk.simulate.trajectories import iso_cube as iso_cube
from hybrid_pk.simulate.trajectories import make_trajectory as make_trajectory

__all__ = [
    "MOUNTS",
    "TRAJECTORIES",
    "IsoCube",
    "Mount",
    "Trajectory",
    "displace_rows",
    "effect_entry",
    "is_hidden_spec",
    "iso_cube",
    "make_trajectory",
    "mount_from_gravity",
    "paper_effects",
    "parse_effects",
    "parse_mount",
    "random_effects",
    "random_frames",
    "simulate_campaign",
]

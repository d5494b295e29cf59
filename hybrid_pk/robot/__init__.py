"""Robot model: URDF -> serial chain -> batched differentiable FK and statics."""

from hybrid_pk.robot.chain import KinematicParams as KinematicParams
from hybrid_pk.robot.robot import Robot as Robot
from hybrid_pk.robot.spec import ChainSpec as ChainSpec
from hybrid_pk.robot.spec import load_chain_spec as load_chain_spec
from hybrid_pk.robot.spec import resolve_urdf as resolve_urdf
from hybrid_pk.robot.spec import shipped_robots as shipped_robots

__all__ = [
    "ChainSpec",
    "KinematicParams",
    "Robot",
    "load_chain_spec",
    "resolve_urdf",
    "shipped_robots",
]

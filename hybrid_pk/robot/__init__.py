"""Robot model: URDF -> serial chain (mimic joints coupled) -> batched FK and statics."""

from hybrid_pk.robot.chain import ChainTerms as ChainTerms
from hybrid_pk.robot.chain import KinematicParams as KinematicParams
from hybrid_pk.robot.chain_spec import BranchBody as BranchBody
from hybrid_pk.robot.chain_spec import ChainSpec as ChainSpec
from hybrid_pk.robot.chain_spec import load_chain_spec as load_chain_spec
from hybrid_pk.robot.chain_spec import resolve_urdf as resolve_urdf
from hybrid_pk.robot.chain_spec import shipped_robots as shipped_robots
from hybrid_pk.robot.kernel import ChainKernel as ChainKernel
from hybrid_pk.robot.robot import STANDARD_GRAVITY as STANDARD_GRAVITY
from hybrid_pk.robot.robot import Robot as Robot

__all__ = [
    "STANDARD_GRAVITY",
    "BranchBody",
    "ChainKernel",
    "ChainSpec",
    "ChainTerms",
    "KinematicParams",
    "Robot",
    "load_chain_spec",
    "resolve_urdf",
    "shipped_robots",
]

"""Robot model: URDF (or a DH table, :mod:`~hybrid_pk.robot.dh`) -> serial chain (mimic
joints coupled) -> batched FK and statics."""

from hybrid_pk.robot.chain import ChainTerms as ChainTerms
from hybrid_pk.robot.chain import KinematicParams as KinematicParams
from hybrid_pk.robot.chain_spec import BranchBody as BranchBody
from hybrid_pk.robot.chain_spec import ChainSpec as ChainSpec
from hybrid_pk.robot.chain_spec import load_chain_spec as load_chain_spec
from hybrid_pk.robot.chain_spec import resolve_urdf as resolve_urdf
from hybrid_pk.robot.chain_spec import shipped_robots as shipped_robots
from hybrid_pk.robot.dh import dh_urdf as dh_urdf
from hybrid_pk.robot.dh_table import DHTable as DHTable
from hybrid_pk.robot.dh_table import read_dh_table as read_dh_table
from hybrid_pk.robot.kernel import ChainKernel as ChainKernel
from hybrid_pk.robot.robot import STANDARD_GRAVITY as STANDARD_GRAVITY
from hybrid_pk.robot.robot import Robot as Robot

__all__ = [
    "STANDARD_GRAVITY",
    "BranchBody",
    "ChainKernel",
    "ChainSpec",
    "ChainTerms",
    "DHTable",
    "KinematicParams",
    "Robot",
    "dh_urdf",
    "load_chain_spec",
    "read_dh_table",
    "resolve_urdf",
    "shipped_robots",
]

"""hybrid_pk: differentiable, physics-aware kinematics for accurate serial robot arms.

Data flow: robot model -> measured data -> error effects -> diagnosis/calibration
-> residual networks -> IK -> reports.
"""

from hybrid_pk.errors import DataError as DataError
from hybrid_pk.errors import HybridPKError as HybridPKError
from hybrid_pk.errors import InvalidFrame as InvalidFrame
from hybrid_pk.errors import ModelFileError as ModelFileError
from hybrid_pk.errors import RobotModelError as RobotModelError
from hybrid_pk.errors import ShapeError as ShapeError
from hybrid_pk.robot import KinematicParams as KinematicParams
from hybrid_pk.robot import Robot as Robot
from hybrid_pk.robot import shipped_robots as shipped_robots

__version__ = "0.1.0"

__all__ = [
    "DataError",
    "HybridPKError",
    "InvalidFrame",
    "KinematicParams",
    "ModelFileError",
    "Robot",
    "RobotModelError",
    "ShapeError",
    "__version__",
    "shipped_robots",
]

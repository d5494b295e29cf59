"""hybrid_pk: differentiable, physics-aware kinematics for accurate serial robot arms.

Data flow: robot model -> measured data -> error effects -> diagnosis/calibration
-> residual networks -> IK -> reports.
"""

# isort: off
# First: Ctrl-C while the command starts is one line (hybrid_pk.startup), and waiting
# OpenMP threads sleep (set before torch loads OpenMP; hybrid_pk.threads).
import hybrid_pk.startup
import hybrid_pk.threads  # noqa: F401
# isort: on

import importlib
import importlib.util
from typing import TYPE_CHECKING

# The public names, each from the module that defines it, imported on first use (PEP
# 562): `import hybrid_pk` and `hybrid-pk --help` do not load torch, scipy and the
# whole package (seconds on a loaded machine); `hybrid_pk.Robot` loads what it needs.
_HOME = {
    "Diagnosis": "hybrid_pk.calibration.diagnosis",
    "diagnose": "hybrid_pk.calibration.diagnosis",
    "FitResult": "hybrid_pk.calibration.fit",
    "fit": "hybrid_pk.calibration.fit",
    "DiagnosisSettings": "hybrid_pk.calibration.settings",
    "FitSettings": "hybrid_pk.calibration.settings",
    "MeasuredData": "hybrid_pk.data",
    "read_table": "hybrid_pk.data",
    "read_table_for": "hybrid_pk.data",
    "write_table": "hybrid_pk.data",
    "Conditions": "hybrid_pk.effects",
    "ExtendedModel": "hybrid_pk.effects",
    "Gravity": "hybrid_pk.effects",
    "make_effect": "hybrid_pk.effects",
    "DataError": "hybrid_pk.errors",
    "HybridPKError": "hybrid_pk.errors",
    "InvalidFrame": "hybrid_pk.errors",
    "ModelFileError": "hybrid_pk.errors",
    "RobotModelError": "hybrid_pk.errors",
    "ShapeError": "hybrid_pk.errors",
    "error_stats": "hybrid_pk.evaluation.metrics",
    "pose_error": "hybrid_pk.evaluation.metrics",
    "HybridFK": "hybrid_pk.hybrid",
    "IKOptions": "hybrid_pk.ik",
    "IKResult": "hybrid_pk.ik",
    "solve_ik": "hybrid_pk.ik",
    "solve_ik_two_stage": "hybrid_pk.ik",
    "wang_baseline": "hybrid_pk.ik",
    "load_hybrid": "hybrid_pk.io.hybrid_file",
    "save_hybrid": "hybrid_pk.io.hybrid_file",
    "load_model": "hybrid_pk.io.model_file",
    "save_model": "hybrid_pk.io.model_file",
    "export_urdf": "hybrid_pk.io.urdf_export",
    "KinematicParams": "hybrid_pk.robot",
    "Robot": "hybrid_pk.robot",
    "shipped_robots": "hybrid_pk.robot",
    "simulate_campaign": "hybrid_pk.simulate",
}

__version__ = "0.1.0"

__all__ = ["__version__", *sorted(_HOME)]  # every public name is in _HOME


def __getattr__(name: str):
    if name in _HOME:
        value = getattr(importlib.import_module(_HOME[name]), name)
    elif importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")  # `hybrid_pk.ik.IKOptions`
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # once: later lookups do not come here
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what the names are, for type checkers and editors (= _HOME; a test)
    from hybrid_pk.calibration.diagnosis import Diagnosis as Diagnosis
    from hybrid_pk.calibration.diagnosis import diagnose as diagnose
    from hybrid_pk.calibration.fit import FitResult as FitResult
    from hybrid_pk.calibration.fit import fit as fit
    from hybrid_pk.calibration.settings import DiagnosisSettings as DiagnosisSettings
    from hybrid_pk.calibration.settings import FitSettings as FitSettings
    from hybrid_pk.data import MeasuredData as MeasuredData
    from hybrid_pk.data import read_table as read_table
    from hybrid_pk.data import read_table_for as read_table_for
    from hybrid_pk.data import write_table as write_table
    from hybrid_pk.effects import Conditions as Conditions
    from hybrid_pk.effects import ExtendedModel as ExtendedModel
    from hybrid_pk.effects import Gravity as Gravity
    from hybrid_pk.effects import make_effect as make_effect
    from hybrid_pk.errors import DataError as DataError
    from hybrid_pk.errors import HybridPKError as HybridPKError
    from hybrid_pk.errors import InvalidFrame as InvalidFrame
    from hybrid_pk.errors import ModelFileError as ModelFileError
    from hybrid_pk.errors import RobotModelError as RobotModelError
    from hybrid_pk.errors import ShapeError as ShapeError
    from hybrid_pk.evaluation.metrics import error_stats as error_stats
    from hybrid_pk.evaluation.metrics import pose_error as pose_error
    from hybrid_pk.hybrid import HybridFK as HybridFK
    from hybrid_pk.ik import IKOptions as IKOptions
    from hybrid_pk.ik import IKResult as IKResult
    from hybrid_pk.ik import solve_ik as solve_ik
    from hybrid_pk.ik import solve_ik_two_stage as solve_ik_two_stage
    from hybrid_pk.ik import wang_baseline as wang_baseline
    from hybrid_pk.io.hybrid_file import load_hybrid as load_hybrid
    from hybrid_pk.io.hybrid_file import save_hybrid as save_hybrid
    from hybrid_pk.io.model_file import load_model as load_model
    from hybrid_pk.io.model_file import save_model as save_model
    from hybrid_pk.io.urdf_export import export_urdf as export_urdf
    from hybrid_pk.robot import KinematicParams as KinematicParams
    from hybrid_pk.robot import Robot as Robot
    from hybrid_pk.robot import shipped_robots as shipped_robots
    from hybrid_pk.simulate import simulate_campaign as simulate_campaign

"""Calibration: fit a model's frames and effect values, and diagnose which effects.

- :mod:`.problem`: the weighted least-squares problem (residuals, structured Jacobian);
- :mod:`.least_squares`: Levenberg–Marquardt in torch;
- :mod:`.fit`: :func:`fit` with noise re-estimation, :class:`FitResult`, frame
  initialisation by registration;
- :mod:`.diagnosis`: :func:`diagnose`, the search for the physical causes.
"""

from hybrid_pk.calibration.diagnosis import Cause as Cause
from hybrid_pk.calibration.diagnosis import Diagnosis as Diagnosis
from hybrid_pk.calibration.diagnosis import diagnose as diagnose
from hybrid_pk.calibration.fit import FitResult as FitResult
from hybrid_pk.calibration.fit import fit as fit
from hybrid_pk.calibration.fit import initialise_frames as initialise_frames
from hybrid_pk.calibration.fit import model_errors as model_errors
from hybrid_pk.calibration.least_squares import LMResult as LMResult
from hybrid_pk.calibration.least_squares import levenberg_marquardt as levenberg_marquardt
from hybrid_pk.calibration.problem import ParamBlock as ParamBlock
from hybrid_pk.calibration.problem import Problem as Problem
from hybrid_pk.calibration.problem import param_blocks as param_blocks

__all__ = [
    "Cause",
    "Diagnosis",
    "FitResult",
    "LMResult",
    "ParamBlock",
    "Problem",
    "diagnose",
    "fit",
    "initialise_frames",
    "levenberg_marquardt",
    "model_errors",
    "param_blocks",
]

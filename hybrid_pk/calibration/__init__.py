"""Calibration: identify frames and effect values of an extended model from measured poses.

- :mod:`~hybrid_pk.calibration.fit`: ``fit.fit`` (Levenberg–Marquardt with noise
  re-weighting and covariance) of an :class:`~hybrid_pk.effects.ExtendedModel`, and
  :func:`initialise_frames` (closed-form base and tool frames); the function is
  :func:`hybrid_pk.fit` at the top level (here ``fit`` stays the module);
- :mod:`~hybrid_pk.calibration.least_squares`: the dense Levenberg–Marquardt solver
  and forward-mode Jacobian it uses;
- :mod:`~hybrid_pk.calibration.diagnosis`: :func:`diagnose`, which effects the data
  shows.
"""

from hybrid_pk.calibration import fit as fit  # the module (see above)
from hybrid_pk.calibration.diagnosis import Diagnosis as Diagnosis
from hybrid_pk.calibration.diagnosis import diagnose as diagnose
from hybrid_pk.calibration.fit import FitResult as FitResult
from hybrid_pk.calibration.fit import initialise_frames as initialise_frames
from hybrid_pk.calibration.fit import model_errors as model_errors
from hybrid_pk.calibration.least_squares import LMResult as LMResult
from hybrid_pk.calibration.least_squares import levenberg_marquardt as levenberg_marquardt

__all__ = [
    "Diagnosis",
    "FitResult",
    "LMResult",
    "diagnose",
    "fit",
    "initialise_frames",
    "levenberg_marquardt",
    "model_errors",
]

"""Calibration: identify frames and effect values of an extended model from measured poses.

- :mod:`~hybrid_pk.calibration.problem`: the weighted least-squares problem (residuals,
  their Jacobian by structure, row by chunk: normal equations and the R factor);
- :mod:`~hybrid_pk.calibration.structured_jacobian`, :mod:`~hybrid_pk.calibration.twists`:
  how that Jacobian is built (closed-form twists of frames, origins and joints);
- :mod:`~hybrid_pk.calibration.fit`: ``fit.fit`` (Levenberg–Marquardt with noise
  re-weighting and covariance) of an :class:`~hybrid_pk.effects.ExtendedModel`, and
  :func:`initialise_frames` (closed-form base and tool frames); the function is
  :func:`hybrid_pk.fit` at the top level (here ``fit`` stays the module);
- :mod:`~hybrid_pk.calibration.frames`, :mod:`~hybrid_pk.calibration.known_frames`:
  frames known from outside the data (``--tool``, ``--base``) and the prior that holds
  what the data do not determine; :mod:`~hybrid_pk.calibration.identifiability`: which
  frame components are not determined, in words; :mod:`~hybrid_pk.calibration.robust`:
  robust losses and outlier rows;
- :mod:`~hybrid_pk.calibration.least_squares`: the Levenberg–Marquardt solver and the
  forward-mode Jacobian it uses by default;
- :mod:`~hybrid_pk.calibration.diagnosis`: :func:`diagnose`, which effects the data
  shows;
- :mod:`~hybrid_pk.calibration.settings`: :class:`FitSettings` and
  :class:`DiagnosisSettings` (the fit and diagnosis flags, typed, with their
  defaults), :mod:`~hybrid_pk.calibration.tuning`: :class:`DiagnosisTuning`.
"""

from hybrid_pk.calibration import fit as fit  # the module (see above)
from hybrid_pk.calibration.diagnosis import Cause as Cause
from hybrid_pk.calibration.diagnosis import Diagnosis as Diagnosis
from hybrid_pk.calibration.diagnosis import diagnose as diagnose
from hybrid_pk.calibration.fit import FitResult as FitResult
from hybrid_pk.calibration.fit import initialise_frames as initialise_frames
from hybrid_pk.calibration.fit import model_errors as model_errors
from hybrid_pk.calibration.frames import FramePriors as FramePriors
from hybrid_pk.calibration.frames import FrameSpec as FrameSpec
from hybrid_pk.calibration.least_squares import LMResult as LMResult
from hybrid_pk.calibration.least_squares import levenberg_marquardt as levenberg_marquardt
from hybrid_pk.calibration.problem import ParamBlock as ParamBlock
from hybrid_pk.calibration.problem import Problem as Problem
from hybrid_pk.calibration.problem import param_blocks as param_blocks
from hybrid_pk.calibration.settings import DiagnosisSettings as DiagnosisSettings
from hybrid_pk.calibration.settings import FitSettings as FitSettings
from hybrid_pk.calibration.tuning import DiagnosisTuning as DiagnosisTuning

__all__ = [
    "Cause",
    "Diagnosis",
    "DiagnosisSettings",
    "DiagnosisTuning",
    "FitResult",
    "FitSettings",
    "FramePriors",
    "FrameSpec",
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

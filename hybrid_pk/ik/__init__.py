"""Inverse kinematics: every distinct solution of a pose, on nominal and hybrid models.

- :func:`solve_ik`: batched projected Levenberg–Marquardt over targets × quasi-random
  seeds, verified, polished onto the exact branch (:mod:`~hybrid_pk.ik.polish`) and
  deduplicated (contract section 6) into an :class:`IKResult`.
- :func:`solve_ik_two_stage` / :func:`refine_ik`: the paper's IK for expensive
  (hybrid) models: branches on the cheap model, refinement in a box on the accurate one.
- :func:`batched_levenberg_marquardt`: the solver core, many tiny box-constrained pose
  problems in one batch-last batch (the calibration's ``levenberg_marquardt`` solves one
  dense problem instead).
- :func:`wang_baseline`: the comparison method of the paper's Tables IV and V.
- :func:`compensate`: a robot program's joint targets corrected for a calibrated or
  hybrid model (the controller keeps its nominal model).
- :func:`resolve_conditions`: the backlash approach direction (and temperature,
  payload) an IK target is solved under, stated when not given.
"""

from hybrid_pk.ik.batched_lm import LMOutput as LMOutput
from hybrid_pk.ik.batched_lm import LMSettings as LMSettings
from hybrid_pk.ik.batched_lm import batched_levenberg_marquardt as batched_levenberg_marquardt
from hybrid_pk.ik.compensation import Compensation as Compensation
from hybrid_pk.ik.compensation import compensate as compensate
from hybrid_pk.ik.conditions import IKAssumption as IKAssumption
from hybrid_pk.ik.conditions import parse_approach as parse_approach
from hybrid_pk.ik.conditions import resolve_conditions as resolve_conditions
from hybrid_pk.ik.dedup import distinct_mask as distinct_mask
from hybrid_pk.ik.dedup import same_solution as same_solution
from hybrid_pk.ik.forward_model import IKModel as IKModel
from hybrid_pk.ik.forward_model import as_ik_model as as_ik_model
from hybrid_pk.ik.result import IKResult as IKResult
from hybrid_pk.ik.seeds import quasi_random_seeds as quasi_random_seeds
from hybrid_pk.ik.solver import IKOptions as IKOptions
from hybrid_pk.ik.solver import solve_ik as solve_ik
from hybrid_pk.ik.two_stage import refine_ik as refine_ik
from hybrid_pk.ik.two_stage import solve_ik_two_stage as solve_ik_two_stage
from hybrid_pk.ik.two_stage import wang_baseline as wang_baseline

__all__ = [
    "Compensation",
    "IKAssumption",
    "IKModel",
    "IKOptions",
    "IKResult",
    "LMOutput",
    "LMSettings",
    "as_ik_model",
    "batched_levenberg_marquardt",
    "compensate",
    "distinct_mask",
    "parse_approach",
    "quasi_random_seeds",
    "refine_ik",
    "resolve_conditions",
    "same_solution",
    "solve_ik",
    "solve_ik_two_stage",
    "wang_baseline",
]

"""Evaluation: pose errors and their summaries, hold-out splits, ISO 9283.

- :mod:`~hybrid_pk.evaluation.metrics`: the paper's position and orientation errors
  (mm, deg), summaries, the ``evaluation.json`` payload; its names are exported here;
- :mod:`~hybrid_pk.evaluation.splits`: random, region and joint-box hold-out splits;
- :mod:`~hybrid_pk.evaluation.iso9283`: pose accuracy and repeatability where poses
  repeat;
- :mod:`~hybrid_pk.evaluation.plots`: figure primitives and error histograms.

The last three import scipy or matplotlib, so they load on first use
(``hybrid_pk.evaluation.splits`` works without an import of its own).
"""

import importlib
from types import ModuleType

from hybrid_pk.evaluation import metrics
from hybrid_pk.evaluation.metrics import ErrorStats as ErrorStats
from hybrid_pk.evaluation.metrics import PoseError as PoseError
from hybrid_pk.evaluation.metrics import error_stats as error_stats
from hybrid_pk.evaluation.metrics import evaluate_json as evaluate_json
from hybrid_pk.evaluation.metrics import ik_cost as ik_cost
from hybrid_pk.evaluation.metrics import pose_error as pose_error
from hybrid_pk.evaluation.metrics import pose_residual as pose_residual
from hybrid_pk.evaluation.metrics import position_error_mm as position_error_mm
from hybrid_pk.evaluation.metrics import row_errors as row_errors

_LAZY = ("iso9283", "plots", "splits")

__all__ = [*metrics.__all__, "metrics", *_LAZY]


def __getattr__(name: str) -> ModuleType:
    if name in _LAZY:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

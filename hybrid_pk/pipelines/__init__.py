"""Pipelines: whole jobs built from the layers below, returning typed results: the
calibration workflow (:mod:`~hybrid_pk.pipelines.calibration`), the re-fit of a saved
model's frames (``refit``), hybrid training (``training``), evaluation (``evaluation``),
simulation (``simulation``), planning (``planning``), compensation (``compensation``)
and the demo. The CLI parses, calls these and prints; the experiments and the demo call
the same functions.
"""

from hybrid_pk.pipelines.calibration import CalibrationResult as CalibrationResult
from hybrid_pk.pipelines.calibration import calibrate as calibrate
from hybrid_pk.pipelines.calibration import diagnose_and_calibrate as diagnose_and_calibrate
from hybrid_pk.pipelines.calibration import refit_frames as refit_frames

__all__ = [
    "CalibrationResult",
    "DemoResult",
    "calibrate",
    "diagnose_and_calibrate",
    "refit_frames",
    "run_demo",
]


def __getattr__(name: str):
    """The demo (simulation, training, IK, reports) is imported when first asked for."""
    if name in ("DemoResult", "run_demo"):
        from hybrid_pk.pipelines import demo

        return getattr(demo, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Diagnosis: which physical effects the data shows, with their size and evidence.

:func:`diagnose` runs forward selection over candidate effects (score test, F-test,
BIC, hold-out error), reports what cannot be told apart (ambiguous) and tests what is
left for structure; the result is a :class:`Diagnosis` of :class:`Cause` entries.
"""

from hybrid_pk.calibration.diagnosis.search import Cause as Cause
from hybrid_pk.calibration.diagnosis.search import Diagnosis as Diagnosis
from hybrid_pk.calibration.diagnosis.search import candidate_labels as candidate_labels
from hybrid_pk.calibration.diagnosis.search import diagnose as diagnose

__all__ = ["Cause", "Diagnosis", "candidate_labels", "diagnose"]

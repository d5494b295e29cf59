"""Diagnosis: name the physical causes of a nominal model's errors, with evidence.

The search (:func:`diagnose`, in :mod:`.search`) is built of named steps:

- :mod:`.split`: fit and hold-out rows;
- :mod:`.selection`: score every candidate from one Jacobian, refit the best one;
- :mod:`.elimination`: drop earlier causes that later ones made redundant;
- :mod:`.ambiguity`: what the data cannot tell apart;
- :mod:`.gains`: each cause's hold-out gain and evidence;
- :mod:`.plausibility`: values that are significant but not physical;
- :mod:`.result`: :class:`Cause`, :class:`Diagnosis` and their JSON;
- :mod:`.statistics`, :mod:`.variants`: F-tests and the model variants compared;
- :mod:`.blocked`, :mod:`.carryover`: the blocked hold-out and its practical margin;
- :mod:`.regions`: the regions of joint space (and files) it leaves out in turn;
- :mod:`.noise`: the measurement noise behind the margin, from close pairs of poses;
- :mod:`.power`: what the data cannot show (detection limits, too little data);
- :mod:`.rivals`: causes another candidate stands in for, and where the two part;
- :mod:`.leftovers`: outliers and the error no cause explains (what it varies along);
- :mod:`.stability`: the same rows diagnosed with other seeds (``--stability N``);
- :mod:`.unseen`: the parts of an effect the frames absorb (marked in tables).
"""

from hybrid_pk.calibration.diagnosis.plausibility import (
    plausibility_warnings as plausibility_warnings,
)
from hybrid_pk.calibration.diagnosis.result import Cause as Cause
from hybrid_pk.calibration.diagnosis.result import Diagnosis as Diagnosis
from hybrid_pk.calibration.diagnosis.result import report_value as report_value
from hybrid_pk.calibration.diagnosis.search import diagnose as diagnose
from hybrid_pk.calibration.diagnosis.selection import candidate_labels as candidate_labels

__all__ = [
    "Cause",
    "Diagnosis",
    "candidate_labels",
    "diagnose",
    "plausibility_warnings",
    "report_value",
]

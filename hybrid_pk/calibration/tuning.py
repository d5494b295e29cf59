"""The diagnosis' tuning constants, each a field with the reason for its value.

They are reached from the settings (``DiagnosisSettings.tuning``, or
``diagnose(..., tuning=DiagnosisTuning(...))``); while a diagnosis runs, its modules
read them through :func:`diagnosis_tuning` (the tuning of the diagnosis under way, the
defaults outside one: :class:`hybrid_pk.settings.Active`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from hybrid_pk.settings import Active

__all__ = ["ACTIVE", "DiagnosisTuning", "diagnosis_tuning", "tuned"]


@dataclass(frozen=True)
class DiagnosisTuning:
    """The diagnosis' tuning constants, each with its reason (change them only to
    study the method: a diagnosis is compared across data with the defaults)."""

    # The blocked hold-out (diagnosis.blocked), what carries over:
    # regions held out in turn: each a fifth of the workspace, far enough from the others
    # that a cause must extrapolate, and still holding a fifth of the rows
    region_blocks: int = 5
    # rows a region needs (4 x a six-parameter frame pair): fewer rows, fewer regions
    min_block_rows: int = 24
    # joints whose median lever (point motion per radian) is at least this share of the
    # largest one's move the point comparably: regions are cut along them
    lever_share: float = 0.5
    # the default practical margin is the standard error sigma / sqrt(2 n) of an RMS
    # error measured on a check of n poses (the rows a re-stationed set-up re-fits its
    # frames on): a smaller gain is one no check of the model could confirm
    check_rows: int = 50
    # the error a cause must carry over in: "pose", every measured component (rotation
    # at the noise ratio sigma_pos / sigma_rot, the weighting of every fit): each is
    # evidence of a physical cause. "position": the measured point's position alone,
    # the quantity an absolute accuracy is stated in (on the shared UR10 proxies the
    # two tie: set-up transfers and region split favour position, the pan split pose)
    carry_over_channel: Literal["position", "pose"] = "pose"
    # Lloyd iterations of the regions' k-means: they need to be contiguous, not optimal
    kmeans_iterations: int = 25

    # The search (diagnosis.search, elimination, ambiguity, selection):
    # a candidate whose refit fails is set aside; after this many in a row the model,
    # not the candidate, is the problem: the search stops
    max_rejected_in_a_row: int = 2
    # a cause stays without a refit when its linearised removal F exceeds the critical F
    # by this factor: the refit's F differs from it by the model's nonlinearity over the
    # removal (well under 1 % for effects of this size), never by a factor of 3
    linearised_margin: float = 3.0
    # signatures more alike than this |cosine| of their projected columns are ambiguous
    ambiguity_cosine: float = 0.98
    # estimates correlated beyond this are reported as an ambiguous group
    ambiguity_correlation: float = 0.95
    # temperature must vary by this much [K] for thermal expansion to be tested: below
    # it a 1e-5 1/K expansion of a 1 m arm moves the point by less than 5 um
    min_temperature_spread: float = 0.5

    # What the data cannot show (diagnosis.power):
    # the probability of detection the limits are stated at (the usual design power)
    power: float = 0.8

    # The optional stages (diagnosis.budget):
    # together at most a quarter of the main search's work, so at most a fifth of the
    # whole diagnosis (issue 30's bound on the structural search)
    optional_share: float = 0.25

    # A structurally wrong URDF (diagnosis.structural):
    # more than this share of the displacement a cause makes is what a change of the
    # frames makes too: its value measures a trade-off with them, not a physical error
    max_frame_share: float = 0.98
    # a nominal hold-out mean error beyond this [mm] is not what small corrections make
    gross_error_mm: float = 20.0
    # a structural correction that leaves less than this fraction of the nominal
    # hold-out error explains it
    structural_fraction: float = 0.2


# The tuning of the diagnosis under way: ``diagnose(..., tuning=...)`` sets it.
ACTIVE: Active[DiagnosisTuning] = Active("diagnosis_tuning", DiagnosisTuning())
diagnosis_tuning = ACTIVE.get
tuned = ACTIVE.tuned

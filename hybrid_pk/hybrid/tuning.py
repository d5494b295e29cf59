"""The hybrid's tuning constants, each a field with the reason for its value.

They are reached from the settings (``TrainSettings.tuning``, the ``tuning`` mapping of
a ``train --config`` YAML); while a training runs, the modules it calls read them
through :func:`hybrid_tuning` (the tuning of the training under way, the defaults
outside one: :class:`hybrid_pk.settings.Active`).
"""

from __future__ import annotations

from dataclasses import dataclass

from hybrid_pk.settings import Active

__all__ = ["ACTIVE", "HybridTuning", "hybrid_tuning"]


@dataclass(frozen=True)
class HybridTuning:
    """The hybrid's tuning constants, each with its reason (change them only to study
    the method)."""

    # Freeing a stage on blocked hold-out (hybrid.blocked_trust, training.blocked):
    # a gain counts when it is at least this many standard errors of the mean paired
    # difference: chance shows that in about 1 of 40 sets of blocks
    freeing_z: float = 2.0
    # an end quarter of a joint is a region the other rows do not surround
    # (extrapolation, as to another workspace), small enough that the probe still
    # trains on most rows
    block_quarter: float = 0.25
    # a block with fewer rows says nothing about a region
    min_block_rows: int = 10

    # Coverage and spread (hybrid.coverage, hybrid.spread):
    # k of the mean k-nearest-neighbour distance: a few neighbours average out one
    # row's noise and still see a gap between clusters of rows
    coverage_neighbours: int = 5
    # reference rows kept (a seeded random sample of the training rows): distances to
    # 4,096 rows resolve a 1 % quantile, and the search stays within memory
    coverage_reference: int = 4096

    # The posture features (hybrid.posture):
    # rows whose levers are averaged (a seeded sample): a mean, not a fit
    lever_rows: int = 4096
    # a lever below 1 mm per rad is a joint whose axis passes through the flange point
    # up to the URDF's own rounding (a flange offset of an arm is at least centimetres)
    on_axis_m: float = 1e-3


# The tuning of the training under way: the training pipeline sets it.
ACTIVE: Active[HybridTuning] = Active("hybrid_tuning", HybridTuning())
hybrid_tuning = ACTIVE.get

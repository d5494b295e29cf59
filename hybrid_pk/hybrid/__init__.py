"""Residual networks on top of a geometric/physical model (Ojer et al. 2024).

- :mod:`~hybrid_pk.hybrid.nets`: the paper's architectures (D1, D4, D4w, D4W, Rw, Rd),
  the baselines B1-B4, our small MLP, and :class:`ResidualHead` (a network with its
  output unit);
- :mod:`~hybrid_pk.hybrid.inputs`: the paper's inputs (all joints) and their joint box;
- :mod:`~hybrid_pk.hybrid.features`: inputs chosen by the physics (the frame of link k,
  the joints after it, gravity direction and static wrench there);
- :mod:`~hybrid_pk.hybrid.coverage`: where the networks apply (distance to the
  training data in their input space), the physics as fall-back;
- :mod:`~hybrid_pk.hybrid.spread`: how much of a posture stage's correction to keep
  where the networks refining it (which read every joint) are off;
- :mod:`~hybrid_pk.hybrid.hybrid_fk`: :class:`HybridFK`, base model + two networks;
- :mod:`~hybrid_pk.hybrid.networks_state`: their model-file entry;
- :mod:`~hybrid_pk.hybrid.losses`: training targets and the paper's losses.

Training (Lightning) lives in :mod:`hybrid_pk.training`; nothing here imports it.
"""

from __future__ import annotations

from hybrid_pk.hybrid.coverage import Coverage as Coverage
from hybrid_pk.hybrid.features import FeatureSpec as FeatureSpec
from hybrid_pk.hybrid.features import PhysicsFeatures as PhysicsFeatures
from hybrid_pk.hybrid.features import static_wrenches as static_wrenches
from hybrid_pk.hybrid.hybrid_fk import HybridFK as HybridFK
from hybrid_pk.hybrid.inputs import InputBox as InputBox
from hybrid_pk.hybrid.losses import ResidualTargets as ResidualTargets
from hybrid_pk.hybrid.losses import residual_targets as residual_targets
from hybrid_pk.hybrid.nets import ARCHITECTURES as ARCHITECTURES
from hybrid_pk.hybrid.nets import ResidualHead as ResidualHead
from hybrid_pk.hybrid.nets import build_net as build_net
from hybrid_pk.hybrid.nets import count_parameters as count_parameters

__all__ = [
    "ARCHITECTURES",
    "Coverage",
    "FeatureSpec",
    "HybridFK",
    "InputBox",
    "PhysicsFeatures",
    "ResidualHead",
    "ResidualTargets",
    "build_net",
    "count_parameters",
    "residual_targets",
    "static_wrenches",
]

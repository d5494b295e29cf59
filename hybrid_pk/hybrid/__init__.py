"""Residual networks on top of a geometric/physical model (Ojer et al. 2024).

- :mod:`~hybrid_pk.hybrid.nets`: the paper's architectures (D1, D4, D4w, D4W, Rw, Rd),
  the baselines B1-B4 and our small MLP;
- :mod:`~hybrid_pk.hybrid.hybrid_fk`: :class:`HybridFK`, base model + two networks;
- :mod:`~hybrid_pk.hybrid.losses`: training targets and the paper's losses.

Training (Lightning) lives in :mod:`hybrid_pk.training`; nothing here imports it.
"""

from __future__ import annotations

from hybrid_pk.hybrid.hybrid_fk import HybridFK as HybridFK
from hybrid_pk.hybrid.hybrid_fk import InputBox as InputBox
from hybrid_pk.hybrid.hybrid_fk import ResidualHead as ResidualHead
from hybrid_pk.hybrid.losses import ResidualTargets as ResidualTargets
from hybrid_pk.hybrid.losses import residual_targets as residual_targets
from hybrid_pk.hybrid.nets import ARCHITECTURES as ARCHITECTURES
from hybrid_pk.hybrid.nets import build_net as build_net
from hybrid_pk.hybrid.nets import count_parameters as count_parameters

__all__ = [
    "ARCHITECTURES",
    "HybridFK",
    "InputBox",
    "ResidualHead",
    "ResidualTargets",
    "build_net",
    "count_parameters",
    "residual_targets",
]

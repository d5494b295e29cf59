"""Residual networks on top of a geometric/physical model (Ojer et al. 2024).

- :mod:`~hybrid_pk.hybrid.nets`: the paper's architectures (D1, D4, D4w, D4W, Rw, Rd),
  the baselines B1-B4 and our small MLP;
- :mod:`~hybrid_pk.hybrid.hybrid_fk`: :class:`HybridFK`, base model + two networks;
- :mod:`~hybrid_pk.hybrid.losses`: training targets and the paper's losses.

Training (Lightning) lives in :mod:`hybrid_pk.training`; nothing here imports it.
"""

from __future__ import annotations

import os

from hybrid_pk.hybrid.hybrid_fk import HybridFK as HybridFK
from hybrid_pk.hybrid.hybrid_fk import InputBox as InputBox
from hybrid_pk.hybrid.hybrid_fk import ResidualHead as ResidualHead
from hybrid_pk.hybrid.losses import ResidualTargets as ResidualTargets
from hybrid_pk.hybrid.losses import residual_targets as residual_targets
from hybrid_pk.hybrid.nets import ARCHITECTURES as ARCHITECTURES
from hybrid_pk.hybrid.nets import build_net as build_net
from hybrid_pk.hybrid.nets import count_parameters as count_parameters
from hybrid_pk.io.model_file import LoadedModel, save_model

__all__ = [
    "ARCHITECTURES",
    "HybridFK",
    "InputBox",
    "ResidualHead",
    "ResidualTargets",
    "build_net",
    "count_parameters",
    "load_hybrid",
    "residual_targets",
    "save_hybrid",
]


def load_hybrid(loaded: LoadedModel) -> HybridFK:
    """The :class:`HybridFK` of a loaded model file that carries residual networks
    (in eval mode; callable as ``model(q, cond) -> (N, 4, 4)``).

    Raises:
        ModelFileError: the file's networks are malformed or made for other joints.
    """
    return HybridFK.from_state(loaded.model, loaded.networks, source=loaded.source)


def save_hybrid(
    path: str | os.PathLike,
    hybrid: HybridFK,
    *,
    metadata: dict | None = None,
    training: dict | None = None,
    frames_fitted: bool = True,
) -> os.PathLike:
    """Write ``hybrid`` (base model + networks) to one model file.

    Args:
        path: output file.
        hybrid: the trained model.
        metadata: free-form file metadata.
        training: plain values stored with the networks (``networks["training"]``).
        frames_fitted: whether the base model's frames were fitted (False: identity).
    """
    return save_model(
        path,
        hybrid.base,
        networks=hybrid.state(training),
        metadata=metadata,
        frames_fitted=frames_fitted,
    )

"""Hybrid models in model files: save, load, and predict with whatever a file holds.

A model file with residual networks is an :class:`~hybrid_pk.effects.ExtendedModel`
plus the networks' state (``networks`` of :mod:`hybrid_pk.io.model_file`); this module
turns it back into a :class:`~hybrid_pk.hybrid.HybridFK`.
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import ModelFileError
from hybrid_pk.hybrid import HybridFK
from hybrid_pk.io.model_file import LoadedModel, load_model, save_model

__all__ = ["forward_model", "load_hybrid", "networks_used", "predict_poses", "save_hybrid"]


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


def load_hybrid(source: str | os.PathLike | LoadedModel) -> HybridFK:
    """The :class:`HybridFK` of a model file with residual networks, in eval mode
    (callable as ``model(q, cond) -> (N, 4, 4)``); mirrors :func:`save_hybrid`. It is
    returned even where a re-fit marked the networks unused (:func:`forward_model`
    respects that verdict).

    Args:
        source: a model file path, or a model file already read by ``load_model``.

    Raises:
        ModelFileError: the file has no networks, or they are malformed or made for
            other joints.
    """
    loaded = source if isinstance(source, LoadedModel) else load_model(source)
    if not loaded.has_networks:
        raise ModelFileError(
            f"{loaded.source} has no residual networks: load it with load_model, or train "
            "networks on it with hybrid-pk train"
        )
    return HybridFK.from_state(loaded.model, loaded.networks, source=loaded.source)


def networks_used(loaded: LoadedModel) -> bool:
    """Whether a file's networks are used: it has some, and no re-fit on a new set-up
    found them worse than the physics there (their ``transfer`` verdict,
    :mod:`hybrid_pk.pipelines.network_rule`)."""
    if not loaded.has_networks:
        return False
    return bool((loaded.networks.get("transfer") or {}).get("used", True))


def forward_model(loaded: LoadedModel) -> ExtendedModel | HybridFK:
    """The most accurate model a file holds: its :class:`HybridFK` when it carries
    networks that are used (:func:`networks_used`), else its :class:`ExtendedModel`.
    Both map ``(q, cond) -> (N, 4, 4)``."""
    return load_hybrid(loaded) if networks_used(loaded) else loaded.model


def predict_poses(loaded: LoadedModel, data: MeasuredData, cond: Conditions) -> Tensor:
    """``(N, 4, 4)`` predicted pose of the measured point/frame in the measurement frame.

    Args:
        loaded: from :func:`~hybrid_pk.io.model_file.load_model`.
        data: rows to predict (``data.q`` [rad or m]).
        cond: their operating conditions (``conditions_from_data``).
    """
    with torch.no_grad():
        return forward_model(loaded)(data.q, cond)

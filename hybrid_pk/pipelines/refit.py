"""Re-fit the frames of a saved model (a re-mounted tool, a moved tracker): its effects
and residual networks are kept, only the base and/or tool frame is fitted again. The
networks are used afterwards only if they beat the physics on the re-fit rows, held out
(:mod:`~hybrid_pk.pipelines.network_rule`); the verdict is the networks' ``transfer``.

    result = refit(load_model("model.pt"), data, "tool")
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.errors import HybridPKError, ModelFileError
from hybrid_pk.evaluation.metrics import row_errors
from hybrid_pk.io.hybrid_file import predict_poses
from hybrid_pk.io.model_file import LoadedModel
from hybrid_pk.pipelines.calibration import refit_frames
from hybrid_pk.pipelines.network_rule import NetworkVerdict, network_rule

__all__ = ["RefitResult", "model_errors", "refit", "with_frame_sets"]


@dataclass(frozen=True)
class RefitResult:
    """What :func:`refit` returns.

    Attributes:
        model: the model with its re-fitted frame(s) (effects and modules of MODEL).
        fit: the frames' fit.
        before, after: :func:`model_errors` of MODEL and of the re-fitted model on the
            data (``before`` None where MODEL has another number of frame sets).
        networks: MODEL's networks entry with the verdict as its ``transfer`` (None
            without networks); the file to write holds it.
        verdict: whether the networks are used on the new set-up (None without networks).
    """

    model: ExtendedModel
    fit: FitResult
    before: tuple[Tensor, Tensor | None, str] | None
    after: tuple[Tensor, Tensor | None, str]
    networks: dict | None = None
    verdict: NetworkVerdict | None = None


def with_frame_sets(model: ExtendedModel, sets: int, keep: str | None = None) -> ExtendedModel:
    """``model`` with ``sets`` base/tool frame sets (same robot and effect modules).

    Args:
        model: source model (returned unchanged if it already has ``sets`` sets).
        sets: frame sets wanted (1, or one per DATA file).
        keep: ``"base"`` or ``"tool"``: that frame keeps its values (a single set is
            repeated); the other starts at identity. None: both start at identity.

    Raises:
        HybridPKError: if a kept frame has several sets that cannot map to ``sets``.
    """
    if model.base.sets == sets:
        return model
    kept = {}
    if keep is not None:
        frame = getattr(model, keep)
        if frame.sets != 1:
            raise HybridPKError(
                f"the model has {frame.sets} {keep} frames (one per file of its "
                f"calibration) but this re-fit has {sets} frame set(s); give as many DATA "
                f"files with --frames-per-file, or --refit frames"
            )
        kept[keep] = frame.matrix().detach()
    return ExtendedModel(
        model.robot, list(model.effects), frame_sets=sets, gravity=model.gravity, **kept
    )


def refit(
    loaded: LoadedModel,
    data: MeasuredData,
    which: str,
    *,
    frames_per_file: bool = False,
    priors: FramePriors | None = None,
    robust: str | None = None,
) -> RefitResult:
    """Re-fit the ``which`` frame(s) (``"base"``, ``"tool"``, ``"frames"``) of a loaded
    model on ``data``; the other frame keeps its values, effects and networks are kept.
    With networks, :func:`~hybrid_pk.pipelines.network_rule.network_rule` decides on
    ``data`` whether they are used; if so, the frames are the hybrid's own fit."""
    sets = len(data.sources) if frames_per_file else 1
    cond = conditions_from_data(data, sets > 1)
    before = model_errors(loaded, data, cond) if loaded.model.base.sets == sets else None
    keep = {"base": "tool", "tool": "base", "frames": None}[which]
    model = with_frame_sets(loaded.model, sets, keep=keep)
    res = refit_frames(model, data, cond, which, priors=priors, robust=robust)
    networks = verdict = None
    if loaded.has_networks:
        verdict, frames, kept = network_rule(loaded.networks, model, data, cond, which, res)
        if frames is not None:
            for g in range(model.base.sets):
                model.base.reset_to(frames[0][g], g)
                model.tool.reset_to(frames[1][g], g)
        networks = {**kept, "transfer": verdict.to_json()}
    moved = dataclasses.replace(loaded, model=model, frames_fitted=True, networks=networks)
    after = model_errors(moved, data, cond)
    return RefitResult(model, res, before, after, networks, verdict)


def model_errors(loaded: LoadedModel, data: MeasuredData, cond: Conditions):
    """Position [mm] and orientation [deg] errors per row, and a note if the residual
    networks could not be evaluated by this installation (extended model alone)."""
    try:
        T, note = predict_poses(loaded, data, cond), ""
    except ModelFileError as exc:
        with torch.no_grad():
            T = loaded.model(data.q, cond)
        note = f"note: errors of the extended model only: {exc}"
    return (*row_errors(T, data), note)

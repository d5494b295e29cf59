"""Re-fit the frames of a saved model (a re-mounted tool, a moved tracker): its effects
and residual networks are kept, only the base and/or tool frame is fitted again.

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

__all__ = ["RefitResult", "model_errors", "refit", "with_frame_sets"]


@dataclass(frozen=True)
class RefitResult:
    """What :func:`refit` returns.

    Attributes:
        model: the model with its re-fitted frame(s) (effects and modules of MODEL).
        fit: the frames' fit.
        before, after: :func:`model_errors` of MODEL and of the re-fitted model on the
            data (``before`` None where MODEL has another number of frame sets).
    """

    model: ExtendedModel
    fit: FitResult
    before: tuple[Tensor, Tensor | None, str] | None
    after: tuple[Tensor, Tensor | None, str]


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
    model on ``data``; the other frame keeps its values, effects and networks are kept."""
    sets = len(data.sources) if frames_per_file else 1
    cond = conditions_from_data(data, sets > 1)
    before = model_errors(loaded, data, cond) if loaded.model.base.sets == sets else None
    keep = {"base": "tool", "tool": "base", "frames": None}[which]
    model = with_frame_sets(loaded.model, sets, keep=keep)
    res = refit_frames(model, data, cond, which, priors=priors, robust=robust)
    after = model_errors(dataclasses.replace(loaded, model=model, frames_fitted=True), data, cond)
    return RefitResult(model, res, before, after)


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

"""Model variants the search compares: the current model plus or minus one effect."""

from __future__ import annotations

import torch

from hybrid_pk.calibration.fit import FitResult, fit
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, Effect, ExtendedModel, make_effect

__all__ = ["refit_without", "with_effects", "without_effect"]


def with_effects(model: ExtendedModel, extra: list[Effect] = ()) -> ExtendedModel:
    """A copy of ``model`` (same robot, frames and effect values) plus ``extra`` effects."""
    robot = model.robot
    effects = [make_effect(robot, e.label, e.value.detach().clone()) for e in model.effects]
    out = ExtendedModel(
        robot, effects + list(extra), frame_sets=model.base.sets, gravity=model.gravity
    )
    out.base.reset_to(model.base.matrix().detach())
    out.tool.reset_to(model.tool.matrix().detach())
    return out


def without_effect(model: ExtendedModel, label: str) -> ExtendedModel:
    """A copy of ``model`` without effect ``label``."""
    out = with_effects(model)
    out.effects = torch.nn.ModuleList([e for e in out.effects if e.label != label])
    return out


def refit_without(
    model: ExtendedModel, label: str, data: MeasuredData, cond: Conditions, res: FitResult
) -> ExtendedModel:
    """``model`` without effect ``label``, refitted under ``res``'s noise weights."""
    reduced = without_effect(model, label)
    fit(
        reduced,
        data,
        cond=cond,
        sigma_pos_mm=res.sigma_pos_mm,
        sigma_rot_rad=res.sigma_rot_rad,
        covariance=False,
        max_iter=15,  # warm start from the full model: a few steps re-balance the rest
    )
    return reduced

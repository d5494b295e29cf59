"""Model variants the search compares: the current model plus or minus one effect.

Refits start where a linearised (Gauss–Newton) update from the current fit puts them,
so that the refit only corrects the nonlinearity (a step or two of LM) and ends where
a refit from the current values would.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from hybrid_pk.calibration.chord import Linearisation
from hybrid_pk.calibration.diagnosis.statistics import weighted_residual
from hybrid_pk.calibration.fit import FitResult, fit
from hybrid_pk.calibration.problem import param_blocks
from hybrid_pk.calibration.robust import reestimated_noise
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, Effect, ExtendedModel, make_effect

__all__ = [
    "linearised_removal",
    "refit_removed",
    "refit_without",
    "shift_parameters",
    "with_effects",
    "without_effect",
]


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


@torch.no_grad()
def shift_parameters(model: ExtendedModel, steps: dict[str, Tensor], position_only: bool) -> None:
    """Add ``steps`` (scaled offsets by block label) to the model's parameters."""
    params = dict(model.named_parameters())
    for b in param_blocks(model, None, position_only):
        if b.label in steps:
            p = params[b.name]
            p.add_((steps[b.label] * b.scale).reshape(p.shape).to(p.dtype))


def linearised_removal(res: FitResult, label: str) -> tuple[float, dict[str, Tensor]]:
    """Removing effect ``label`` from the fit ``res``, linearised at its solution.

    Setting the effect's scaled value ``t`` to zero and re-balancing the others raises
    the weighted sum of squares by ``t^T S t`` (``S`` the Schur complement of the
    normal matrix on the effect, the Wald statistic); the others move by
    ``-G_rr^+ G_re (-t)``. Returns that increase and the moves, by block label.
    """
    G = res.normal_matrix
    sl = res.block_slice(label)
    keep = torch.ones(G.shape[0], dtype=torch.bool)
    keep[sl] = False
    scale = torch.cat([torch.full((b.size,), b.scale, dtype=G.dtype) for b in res.blocks])
    delta = -res.x[sl] / scale[sl]
    G_rr_inv = torch.linalg.pinv(G[keep][:, keep], hermitian=True)
    G_re = G[keep][:, sl]
    move = -G_rr_inv @ (G_re @ delta)
    schur = G[sl, sl] - G_re.T @ G_rr_inv @ G_re
    increase = float(delta @ schur @ delta)
    steps, start = {}, 0
    for b in res.blocks:
        if b.label != label:
            steps[b.label] = move[start : start + b.size]
            start += b.size
    return increase, steps


def refit_without(
    model: ExtendedModel,
    label: str,
    data: MeasuredData,
    cond: Conditions,
    res: FitResult,
    progress: Callable[[str], None] | None = None,
    max_iter: int = 15,
) -> ExtendedModel:
    """``model`` without effect ``label``, refitted under ``res``'s noise weights.

    Starts from the linearised removal (:func:`linearised_removal`) when ``res`` has
    its normal matrix, otherwise from the full model's values; ``max_iter`` LM steps
    from there (a few re-balance the rest; after the linearised start one is enough
    for a value, ~1e-9 of the cost left to gain; 0: the linearised start itself).
    """
    reduced = without_effect(model, label)
    if res.normal_matrix is not None:
        _, steps = linearised_removal(res, label)
        shift_parameters(reduced, steps, data.quat is None)
    if max_iter == 0:
        return reduced
    fit(
        reduced,
        data,
        cond=cond,
        sigma_pos_mm=res.sigma_pos_mm,
        sigma_rot_rad=res.sigma_rot_rad,
        covariance=False,
        max_iter=max_iter,
        progress=progress,
        **res.settings(),
    )
    return reduced


def refit_removed(
    reduced: ExtendedModel,
    label: str,
    data: MeasuredData,
    cond: Conditions,
    res: FitResult,
    near: Linearisation | None,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Refit ``reduced``, the model of ``res`` less effect ``label`` (same values),
    under ``res``'s frame prior and robust loss: from its linearised removal, the noise
    levels re-estimated there (the removal raises them; a pass at the old ones would
    be one more), the first step with ``near``, a Jacobian of ``res``'s model on these
    rows (:mod:`hybrid_pk.calibration.chord`; None: exact Jacobians from the start)."""
    position_only = data.quat is None
    _, steps = linearised_removal(res, label)
    shift_parameters(reduced, steps, position_only)
    n_params = sum(b.size for b in param_blocks(reduced, None, position_only))
    sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
    r = weighted_residual(reduced, data, cond, res)
    noise = reestimated_noise(r, data.n, n_params, sigmas, position_only=position_only)
    start = (noise[0], None if position_only else noise[1])
    return fit(
        reduced, data, cond=cond, initial_sigma=start, progress=progress, near=near,
        report_frames=False, **res.settings(),
    )  # fmt: skip

"""Each chosen cause's hold-out gain (left out and refitted) and its evidence line."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from hybrid_pk.calibration.diagnosis.result import Cause, report_value
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.variants import refit_without
from hybrid_pk.calibration.fit import FitResult, model_errors
from hybrid_pk.effects import Effect, ExtendedModel

__all__ = ["GAIN_REFIT_STEPS", "measure_causes"]

# LM steps of the refit without a cause, after its linearised removal: the first step
# leaves ~1e-9 of the cost to gain (the linearised start is within ~1e-7 of it).
GAIN_REFIT_STEPS = 1


def measure_causes(
    model: ExtendedModel,
    res: FitResult,
    split: Split,
    steps: list[dict],
    alpha: float,
    errors: tuple[Tensor, Tensor | None],
    progress: Callable[[str], None] | None = None,
) -> list[Cause]:
    """The causes of ``model``, largest hold-out position gain first.

    A cause's gain is the hold-out mean error of the model refitted without it (its
    linearised removal and :data:`GAIN_REFIT_STEPS` LM steps) minus the full model's
    (``errors``: its per-row hold-out position [mm] and orientation [deg] errors); its
    evidence quotes the step that accepted it.
    """
    pos1, ori1 = errors
    causes = []
    for e in model.effects:
        say = None
        if progress is not None:
            say = lambda text, lbl=e.label: progress(f"gain of {lbl}: {text}")  # noqa: E731
        reduced = refit_without(
            model, e.label, split.train, split.cond_fit, res, say, max_iter=GAIN_REFIT_STEPS
        )
        pos_r, ori_r = model_errors(reduced, split.test, split.cond_hold)
        step = next(s for s in steps if s["candidate"] == e.label and s.get("accepted"))
        causes.append(_cause(e, res, step, alpha, (pos1, ori1), (pos_r, ori_r)))
    causes.sort(key=lambda c: c.position_gain_mm, reverse=True)
    return causes


def _cause(
    e: Effect,
    res: FitResult,
    step: dict,
    alpha: float,
    with_it: tuple[Tensor, Tensor | None],
    without: tuple[Tensor, Tensor | None],
) -> Cause:
    (pos1, ori1), (pos_r, ori_r) = with_it, without
    value, std, components = report_value(e, res.std[res.block_slice(e.label)])
    gain_p = float(pos_r.mean() - pos1.mean())
    gain_o = None if ori1 is None else float(ori_r.mean() - ori1.mean())
    evidence = (
        f"F-test of the refit F = {step['fit_F']:.3g} on {e.value.numel()} dof, "
        f"p = {step['fit_p']:.2g} < {step['threshold']:.1g} (Bonferroni over "
        f"{round(alpha / step['threshold'])} candidates); BIC change "
        f"{step['delta_bic']:.1f}; hold-out mean position error without it "
        f"{float(pos_r.mean()):.4f} mm, with it {float(pos1.mean()):.4f} mm"
    )
    return Cause(
        effect=e.kind,
        joint=e.joint,
        value=value,
        unit=e.unit,
        std=std,
        position_gain_mm=gain_p,
        orientation_gain_deg=gain_o,
        evidence=evidence,
        components=components,
    )

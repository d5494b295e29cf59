"""Rival stories: a named cause the data cannot tell from another candidate, and how far
the two models part where no row was measured.

A cause has a rival when swapping it for another candidate of the vocabulary predicts
the blocked hold-out as well, within the practical margin (linearised swaps on the cell
Grams of one Jacobian of the final model and every candidate, :mod:`.blocked`). The
rows then cannot choose between the two stories: both explain the measured workspace
and carry over between its blocks. What differs is the rest of the workspace, so the
rival model is refitted and both predict the measured point on the fit rows and on
joint configurations drawn inside the joint limits; the diagnosis states how far they
part there. Measuring where they part most tells the two apart.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from hybrid_pk.calibration.diagnosis.carryover import Carry, linearise
from hybrid_pk.calibration.diagnosis.cyclic_screen import screen_cyclic
from hybrid_pk.calibration.diagnosis.plausibility import effect_std, implausibility
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.variants import with_effects, without_effect
from hybrid_pk.calibration.fit import FitResult, fit
from hybrid_pk.effects import ExtendedModel, make_effect

__all__ = ["RIVAL_SAMPLES", "rival_lines", "rival_stories"]

# RIVAL_SAMPLES: joint configurations drawn inside the joint limits to compare two
# stories (the p95 of their differences is then known to about 1 %: its tail holds 100
# draws); RIVAL_TRIES: candidates refitted per cause, best blocked gain first, until one
# is plausible (a rival the refit throws out of the physical range is no story).
RIVAL_SAMPLES, RIVAL_TRIES = 2000, 2


def rival_stories(
    model: ExtendedModel, res: FitResult, pool: list[str], split: Split, carry: Carry,
    say: Callable[[str], None], budget,
) -> list[dict]:  # fmt: skip
    """Per named cause with a rival, ``{"cause", "rival", "rival_value", "unit",
    "blocked_rms_mm": {"named", "rival"}, "differ_mm": {"fit_rows", "joint_limits"}}``:
    the blocked hold-out RMS error [mm] of the named model and of the rival story (each
    re-fitted per block at its own values), and the p95 and max distance [mm] of the
    points the two predict. Causes are taken smallest blocked gain first (a strong
    cause has no rival within the margin) while the optional stages' ``budget`` lasts."""
    causes = [e.label for e in model.effects]
    if carry.folds is None or not causes:
        return []
    margin = carry.margin(res)
    say("rival stories: can another candidate stand in for a cause?")
    others, _ = screen_cyclic(
        model, split, [c for c in pool if c not in causes], res.weights, carry.folds, margin
    )
    robot = model.robot
    trial = with_effects(model, [make_effect(robot, c) for c in others])
    blocked = linearise(trial, res, split, carry.folds, say, factor=False)[3]
    full = blocked.of(causes)
    gains = {}
    for c in causes:
        without = blocked.of([x for x in causes if x != c], removed=[c])
        gains[c] = (without, blocked.gain_mm(without, full))
    out, order = [], sorted(causes, key=lambda x: gains[x][1])  # the weakest first
    for k, c in enumerate(order):
        if k and budget.spent():
            budget.cut("rival stories", [f"rivals of {x}" for x in order[k:]])
            break
        without, own = gains[c]
        rest = [x for x in causes if x != c]
        each = blocked.each(rest, others, removed=[c])
        swaps = {o: blocked.gain_mm(without, s) for o, s in zip(others, each, strict=True)}
        close = sorted((o for o in swaps if swaps[o] >= own - margin), key=lambda o: -swaps[o])
        for rival in close[:RIVAL_TRIES]:
            entry = _parted(model, res, split, (c, rival), (carry, blocked.rms_mm(full)), say)
            if entry is not None:
                out.append(entry)
                break
    return out


def _parted(model, res, split, pair: tuple[str, str], judge, say) -> dict | None:
    """The rival story refitted, judged on the blocked hold-out at its own values and
    compared with ``model`` (``judge``: the blocks and ``model``'s blocked RMS error
    [mm]); None if its value is not a small physical correction or the refit predicts
    the blocks worse by the margin (the linearised swap promised more than it holds)."""
    (cause, rival), (carry, named) = pair, judge
    say(f"rival stories: {rival} for {cause}")
    swapped = with_effects(without_effect(model, cause), [make_effect(model.robot, rival)])
    # with its covariance: the sign rule reads the rival's standard deviation
    fitted = fit(
        swapped, split.train, cond=split.cond_fit, report_frames=False,
        initial_sigma=(res.sigma_pos_mm, res.sigma_rot_rad), **res.settings(),
    )  # fmt: skip
    effect = swapped.effect(rival)
    if implausibility(effect, model.robot, split.train, effect_std(fitted, rival)) is not None:
        return None
    blocked = linearise(swapped, res, split, carry.folds, say, factor=False)[3]
    own = blocked.rms_mm(blocked.of([e.label for e in swapped.effects]))
    if own > named + carry.margin(res):
        return None
    g = torch.Generator().manual_seed(0)
    q = model.robot.sample_q(RIVAL_SAMPLES, g).to(split.train.q.dtype)
    first = torch.zeros(RIVAL_SAMPLES, dtype=torch.long)  # the first fit row's conditions
    value = effect.value.detach()
    return {
        "cause": cause,
        "rival": rival,
        "rival_value": float(value) if value.numel() == 1 else value.tolist(),
        "unit": effect.unit,
        "blocked_rms_mm": {"named": named, "rival": own},
        "differ_mm": {
            "fit_rows": _distance(model, swapped, split.train.q, split.cond_fit),
            "joint_limits": _distance(model, swapped, q, split.cond_fit.subset(first)),
        },
    }


def _distance(a: ExtendedModel, b: ExtendedModel, q, cond) -> dict:
    """p95 and max [mm] of the distance between the points ``a`` and ``b`` predict."""
    with torch.no_grad():
        d = 1000.0 * (a(q, cond)[..., :3, 3] - b(q, cond)[..., :3, 3]).norm(dim=-1)
    return {"p95": float(d.quantile(0.95)), "max": float(d.max())}


def rival_lines(
    stories: list[dict], margin: float | None, ambiguous: list[dict] | None = None
) -> list[str]:
    """One line per rival story (``rival_stories`` of the diagnosis JSON): both causes,
    their blocked RMS errors and how far the two models part. ``ambiguous``: the
    diagnosis' entries, whose unresolved cyclic orders (``order_not_resolved``) say why
    a rival that predicts the blocks better is not named."""
    unresolved = {
        label: a["order_not_resolved"]
        for a in ambiguous or []
        if "order_not_resolved" in a
        for label in a["effects"]
    }
    out = []
    for s in stories:
        named, rival = s["blocked_rms_mm"]["named"], s["blocked_rms_mm"]["rival"]
        fit_rows, box = s["differ_mm"]["fit_rows"], s["differ_mm"]["joint_limits"]
        value = s["rival_value"]
        shown = f"{value:.3g}" if isinstance(value, float) else ", ".join(f"{v:.3g}" for v in value)
        line = (
            f"{s['cause']} or {s['rival']} ({shown} {s['unit']}): blocked hold-out "
            f"{named:.4g} / {rival:.4g} mm; the two models part by {fit_rows['p95']:.2g} mm "
            f"(p95) on the fit rows, {box['p95']:.2g} mm (p95; max {box['max']:.2g}) inside "
            "the joint limits"
        )
        if margin is not None and rival < named - margin:
            line += "; the rival predicts the blocks better by more than the margin ("
            joint = unresolved.get(s["rival"])
            line += (
                "the search's order chose the named cause)"
                if joint is None
                else f"its order is not resolved by these rows, so it is not named: the "
                f"named cause may stand in for a periodic error of {joint})"
            )
        out.append(line)
    return out

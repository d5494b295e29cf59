"""Parsimony after the greedy search: one cause where the search needed two.

Forward selection picks by score, one cause at a time. A cause chosen early can need a
second one to finish what a near-duplicate does alone: on the RX160 a joint_2 offset
plus a joint_3 origin moved perpendicular to the upper arm is, to first order, exactly
a joint_3 offset. Each chosen cause with a near-duplicate (``near_duplicates``) is
therefore swapped for it, refitted and followed by backward elimination; the swap stays
when the data then need fewer causes, or the alternative has fewer parameters (a
joint_4 offset against a joint_5 axis tilt whose third component is that offset), and
fit no worse (BIC, both models' residuals under the same noise weights, and the blocked
hold-out: the current model may not predict it better by the practical margin).

When both of a near-duplicate pair end up chosen (the second added once the first had
taken part of its signature), they split one effect between them: their values trade
off along a direction the data barely see. The one of the two whose removal the
blocked hold-out (:mod:`.blocked`) misses least is then dropped, if it gains less than
the practical margin there. The in-sample F-test is not asked here: on thousands of
rows at a noise of hundredths of a millimetre, a direction that nearly repeats another
is significant on almost any leftover error that no cause of the vocabulary describes
(an unmodelled spring, say), and it buys that small gain at the price of the other
cause's value.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

from hybrid_pk.calibration.chord import Linearisation
from hybrid_pk.calibration.diagnosis.carryover import Carry, linearise, weakest
from hybrid_pk.calibration.diagnosis.elimination import eliminate
from hybrid_pk.calibration.diagnosis.plausibility import implausible_effect, oversized
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import holdout_score, weighted_ssr
from hybrid_pk.calibration.diagnosis.variants import refit_without, with_effects, without_effect
from hybrid_pk.calibration.fit import FitResult, fit
from hybrid_pk.calibration.least_squares import StoppedFit
from hybrid_pk.distributions import f_sf
from hybrid_pk.effects import ExtendedModel, make_effect

__all__ = [
    "Swap",
    "best_swap",
    "blocked_score",
    "judged",
    "prefer_fewer_causes",
    "rationed",
    "record_swap",
]


class Swap(NamedTuple):
    """A swap the rule keeps: ``alternative`` in place of ``chosen``, the BIC change,
    the model and fit after backward elimination, the causes it removed and its
    removal steps."""

    chosen: str
    alternative: str
    d_bic: float
    model: ExtendedModel
    res: FitResult
    removed: set[str]
    removals: list[dict]


def prefer_fewer_causes(
    model: ExtendedModel,
    res: FitResult,
    pairs: list[tuple[str, str]],
    split: Split,
    tests: tuple[float, Carry],
    steps: list[dict],
    say: Callable[[str], None],
    budget=None,
) -> tuple[ExtendedModel, FitResult]:
    """Swap chosen causes for near-duplicates where that leaves fewer causes.

    Args:
        pairs: ``(chosen, alternative)`` labels, as ``near_duplicates`` found them.
        tests: ``(alpha, carry)``: the F-tests' level, the blocked hold-out's blocks
            and margin.
        steps: the search's step records; an accepted swap appends its own and the
            removals that followed it.
        budget: the optional stages' :class:`~.budget.Budget`: the first swap (one
            alternative in place of one cause, refitted, backward elimination) is
            tried whatever the budget, each later one only while it lasts.

    Returns the (possibly) simpler model and its fit.
    """
    model, res = _drop_split_duplicates(model, res, pairs, split, tests[1], steps, say)
    chosen_causes = list(dict.fromkeys(c for c, _ in pairs))
    for k, chosen in enumerate(chosen_causes):
        if budget is not None and budget.stopped("swaps"):
            break
        labels = [e.label for e in model.effects]
        if chosen not in labels or len(labels) < 2:
            continue
        alternatives = [a for c, a in pairs if c == chosen and a not in labels]
        later = [f"swaps of {c}" for c in chosen_causes[k + 1 :]]
        ration = None if budget is None else rationed(budget, "swaps", later)
        trials = [(chosen, a) for a in alternatives]
        best = best_swap(model, res, trials, split, tests, say, ration)
        if best is None:
            continue
        alternative, removed = best.alternative, best.removed
        simpler = "fewer causes" if removed else "fewer parameters"
        why = (
            f"{alternative} alone does what {chosen} needed {', '.join(sorted(removed))} for"
            if removed
            else f"{alternative} does what {chosen} does with fewer parameters"
        ) + f": {simpler}, the same fit"
        model, res = record_swap(steps, best, split, why)
    return model, res


def best_swap(
    model: ExtendedModel,
    res: FitResult,
    swaps: list[tuple[str, str]],
    split: Split,
    tests,
    say,
    ration: Callable[[list[tuple[str, str]]], bool] | None = None,
) -> Swap | None:
    """The best (lowest BIC) of the ``(chosen, alternative)`` swaps of ``model`` that the
    swap rule keeps (:func:`_swapped`), or None when it keeps none. ``tests``:
    ``(alpha, carry)``: the F-tests' level, the blocked hold-out's blocks and margin;
    ``say``: the progress callback; ``ration``: asked before each swap is tried, with
    the swaps left (that one first): where it says no, the best of those tried
    (:func:`rationed`)."""
    if swaps and ration is not None and not ration(swaps):
        return None
    alternatives = list(dict.fromkeys(a for _, a in swaps))
    # what every swap must match, and the Jacobian its refit steps with
    blocked, near = _blocked_near(model, res, split, tests[1], alternatives, say)
    current = (weighted_ssr(model, split.train, split.cond_fit, res), blocked)
    best = None
    for k, swap in enumerate(swaps):
        if k and ration is not None and not ration(swaps[k:]):
            break
        trial = _swapped(model, res, current, swap, split, tests, say, near)
        if trial is not None and (best is None or trial.d_bic < best.d_bic):
            best = trial
    return best


def rationed(budget, stage: str, later: list[str]) -> Callable[[list[tuple[str, str]]], bool]:
    """The ``ration`` of :func:`best_swap` in optional stage ``stage``: each swap tried
    is one unit of ``budget``'s (:meth:`.budget.Budget.allows`); a cut leaves the swaps
    not tried (``"alternative in place of chosen"``) and ``later``, what the stage
    would have done after them."""

    def allows(left: list[tuple[str, str]]) -> bool:
        return budget.allows(stage, [f"{a} in place of {c}" for c, a in left] + later)

    return allows


def record_swap(
    steps: list[dict], swap: Swap, split: Split, why: str, simpler: str | None = None
) -> tuple[ExtendedModel, FitResult]:
    """Record ``swap`` in ``steps`` (its step, ``why`` it was kept, and the removals that
    followed it; the step that chose the replaced cause marked as replaced, ``simpler``:
    by default fewer causes when the swap removed any, else fewer parameters), and
    return its model and fit."""
    chosen, alternative = swap.chosen, swap.alternative
    chosen_step = next(s for s in steps if s["candidate"] == chosen and s.get("accepted"))
    step = {"candidate": alternative, "replaces": chosen, "accepted": True}
    step.update(_evidence(swap.model, swap.res, alternative, split, chosen_step["threshold"]))
    step["why"] = why
    simpler = simpler or ("fewer causes" if swap.removed else "fewer parameters")
    chosen_step["accepted"] = False
    chosen_step["why"] = f"replaced by {alternative} ({simpler}, the same fit)"
    steps.append(step)
    steps.extend(swap.removals)
    return swap.model, swap.res


def blocked_score(model, res, split, carry, say):
    """``(blocked score, Blocked)`` of ``model`` (its own parameters re-fitted per
    block) under ``res``'s noise weights; None without blocks."""
    if carry.folds is None:
        return None
    blocked = linearise(model, res, split, carry.folds, say, factor=False)[3]
    return blocked.of([e.label for e in model.effects]), blocked


def _blocked_near(model, res, split, carry, extra, say):
    """:func:`_blocked` of ``model``, and the ``[J r]`` chunks of its linearisation,
    made with the ``extra`` effects' columns (at zero: the score is the model's), that
    a swap's refit steps with (:mod:`hybrid_pk.calibration.chord`); None, None without
    blocks."""
    if carry.folds is None:
        return None, None
    trial = with_effects(model, [make_effect(model.robot, a) for a in extra])
    problem, blocks, _, blocked = linearise(
        trial, res, split, carry.folds, say, factor=False, keep=True
    )
    near = Linearisation.kept_by(problem, blocks)
    return (blocked.of([e.label for e in model.effects]), blocked), near


def _drop_split_duplicates(model, res, pairs, split, carry, steps, say):
    """Drop one cause of each near-duplicate pair of which both were chosen: the one
    whose removal the blocked hold-out misses least, when that gains less than the
    practical margin."""
    for pair in pairs:
        labels = [e.label for e in model.effects]
        if not set(pair) <= set(labels) or len(labels) < 3 or carry.folds is None:
            continue
        say(f"testing whether one of {' and '.join(pair)} only splits the other's signature")
        blocked = linearise(model, res, split, carry.folds, say, factor=False)[3]
        margin = carry.margin(res)
        worst = weakest(blocked, labels, margin, keep=None, only=pair)
        if worst is None:
            continue
        drop, gain = worst
        keep = pair[1] if drop == pair[0] else pair[0]
        steps.append(
            {
                "candidate": drop,
                "removed": True,
                "blocked_gain_mm": gain,
                "min_gain_mm": margin,
                "accepted": False,
                "why": f"near-duplicate of {keep}: the two split one signature, and "
                f"{drop} gains {gain:.3g} mm on the blocked hold-out, less than the "
                f"practical margin {margin:.3g} mm",
            }
        )
        for s in steps[:-1]:
            if s["candidate"] == drop and s.get("accepted"):
                s["accepted"] = False
                s["why"] = f"dropped later: it split {keep}'s signature (see below)"
        model = without_effect(model, drop)
        sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
        res = fit(
            model, split.train, cond=split.cond_fit, initial_sigma=sigmas, progress=say,
            **res.settings(),
        )  # fmt: skip
    return model, res


def _swapped(model, res, current, swap, split, tests, say, near=None):
    """The :class:`Swap` of ``model`` with ``alternative`` in place of ``chosen``
    (``swap``) after backward elimination, or None when that is implausible, leaves
    neither fewer causes nor fewer parameters, or fits worse than ``current``
    (``model``'s weighted SSR and blocked score): a higher BIC, or a blocked hold-out
    the current model predicts better by the practical margin. ``near``: a Jacobian of
    ``model`` with ``alternative``'s columns, that the refit steps with."""
    (chosen, alternative), (alpha, carry) = swap, tests
    say(f"trying {alternative} in place of {chosen}")
    trial = with_effects(without_effect(model, chosen), [make_effect(model.robot, alternative)])
    sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
    try:  # a refit that carries an effect beyond a small correction is refused: stop there
        trial_res = fit(
            trial, split.train, cond=split.cond_fit, initial_sigma=sigmas, progress=say,
            near=near, stop=oversized, **res.settings(),
        )  # fmt: skip
    except StoppedFit:
        say(f"{alternative} in place of {chosen}: its refit left a small correction, refused")
        return None
    if implausible_effect(trial, split.train, first=alternative, res=trial_res) is not None:
        return None
    removals: list[dict] = []
    trial, trial_res, removed = eliminate(
        trial, trial_res, split, alpha, alternative, removals, say
    )
    return judged(
        model, res, current, (trial, trial_res), swap, removed, removals, split, carry, say
    )


def judged(model, res, current, trial, swap, removed, removals, split, carry, say) -> Swap | None:
    """The :class:`Swap` ``swap`` (``(chosen, alternative)``) that led from ``model``
    (its fit ``res``, ``current``: its weighted SSR and blocked score) to ``trial``
    (``(model, fit)``, after backward elimination removed ``removed``, logged in
    ``removals``), or None when the swap rule does not keep it: neither fewer causes
    nor (as many) with fewer parameters, a higher BIC, or a blocked hold-out the current
    model predicts better by the practical margin."""
    trial, trial_res = trial
    fewer = len(trial.effects) < len(model.effects)
    if not fewer and (
        len(trial.effects) > len(model.effects) or trial_res.n_params >= res.n_params
    ):
        return None  # neither fewer causes nor fewer parameters
    ssr_cur, blocked_cur = current
    ssr_new = weighted_ssr(trial, split.train, split.cond_fit, res)
    m = res.n_obs  # BIC of the trial minus the current model's
    d_bic = m * math.log(max(ssr_new, 1e-300) / max(ssr_cur, 1e-300))
    d_bic += (trial_res.n_params - res.n_params) * math.log(m)
    if d_bic > 0:
        return None
    if blocked_cur is not None:
        score_new = blocked_score(trial, res, split, carry, say)[0]
        score_cur, blocked = blocked_cur
        if blocked.gain_mm(score_new, score_cur) >= carry.margin(res):
            return None  # the current causes carry over better by the margin
    return Swap(*swap, d_bic, trial, trial_res, removed, removals)


def _evidence(
    model: ExtendedModel, res: FitResult, label: str, split: Split, threshold: float
) -> dict:
    """The F-test, BIC change and hold-out scores of ``label`` in ``model`` against
    ``model`` refitted without it (the fields a search step records)."""
    train, cond = split.train, split.cond_fit
    reduced = refit_without(model, label, train, cond, res)
    ssr_full = weighted_ssr(model, train, cond, res)
    ssr_red = weighted_ssr(reduced, train, cond, res)
    k, m = model.effect(label).value.numel(), res.n_obs
    dof = max(m - res.n_params, 1)
    F = ((ssr_red - ssr_full) / k) / max(ssr_full / dof, 1e-300)
    return {
        "fit_F": F,
        "fit_p": f_sf(F, k, dof) if F > 0 else 1.0,
        "threshold": threshold,
        "delta_bic": m * math.log(max(ssr_full, 1e-300) / max(ssr_red, 1e-300)) + k * math.log(m),
        "holdout_score_before": holdout_score(reduced, split.test, split.cond_hold, res),
        "holdout_score_after": holdout_score(model, split.test, split.cond_hold, res),
    }

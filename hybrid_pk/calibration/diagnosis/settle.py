"""After the search: every cause keeps its place only if it carries over.

On the final model (one Jacobian of its parameters and of every other order of each
chosen cyclic error), each cause's blocked hold-out gain is measured by leaving it out
(the rest re-fitted per block). A cyclic error another order predicts the held-out
blocks nearly as well as (within the practical margin) is not resolved by the data:
it is listed as ambiguous and taken out (so is one another order predicts better).
Then a periodic cause that does not carry over along its own joint's range
(:mod:`.own_range`) is listed and taken out. Then a
cause that gains less than the margin is taken out. One at a time, the weakest first,
the model refitted after each, until every cause carries over.

Before all that, an effect that a refit after its acceptance carried beyond a small
physical correction (:func:`.plausibility.implausible_effect`; e.g. two link lengths
along parallel axes walking to metres while they cancel) is taken out first and
handed to the structural check as a finding: the model measured and reported holds
only the causes it names.
"""

from __future__ import annotations

from collections.abc import Callable

from hybrid_pk.calibration.chord import Linearisation
from hybrid_pk.calibration.diagnosis.blocked import Blocked
from hybrid_pk.calibration.diagnosis.carryover import Carry, linearise, removal_gains
from hybrid_pk.calibration.diagnosis.own_range import off_range, own_range_gains
from hybrid_pk.calibration.diagnosis.plausibility import implausible_effect, refusal_why
from hybrid_pk.calibration.diagnosis.selection import Scores, cyclic_candidates
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.variants import refit_removed, with_effects, without_effect
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.effects import ExtendedModel, make_effect
from hybrid_pk.effects.joint import CYCLIC_PREFIX, cyclic_error_kind

__all__ = ["entry_rivals", "order_groups", "order_rivals", "settle", "unresolved_entry"]


def _is_cyclic(label: str) -> bool:
    return label.startswith(CYCLIC_PREFIX)


def _joint(label: str) -> str:
    return label.partition(":")[2]


def rival_advantages(blocked: Blocked, effects: list[str], label: str, alternatives):
    """``{alternative: advantage [mm]}``: how much better ``label`` (one of ``effects``,
    at the linearisation point or zero) predicts the held-out blocks than each
    ``alternative`` order in its place."""
    removed = [label] if label in effects else []
    rest = [e for e in effects if e != label]
    with_it = blocked.of([*rest, label])
    alternatives = list(alternatives)
    each = blocked.each(rest, alternatives, removed)
    return {alt: blocked.gain_mm(s, with_it) for alt, s in zip(alternatives, each, strict=True)}


def entry_rivals(scores: Scores, effects: list[str], label: str) -> dict[str, float]:
    """The other scored orders of ``label``'s joint that predict the held-out blocks
    within the margin of ``label`` (empty: resolved, or not a cyclic error)."""
    if scores.blocked is None or not _is_cyclic(label):
        return {}
    alts = [
        s.label
        for s in scores.scored
        if _is_cyclic(s.label) and s.label != label and _joint(s.label) == _joint(label)
    ]
    adv = rival_advantages(scores.blocked, effects, label, alts)
    return {a: v for a, v in adv.items() if v < scores.margin}


def order_rivals(
    model: ExtendedModel, res: FitResult, split: Split, carry: Carry, label: str, say, cache
) -> dict[str, float]:
    """:func:`entry_rivals` of ``label`` (a candidate of ``model``, not yet in it) among
    *every* order of its joint that :func:`settle` compares it with, not only those the
    cyclic screen let into this step's scoring: the rule that takes an unresolved order
    out after the search keeps it from entering (empty: resolved, not a cyclic error,
    or no blocks). ``cache``: a dict kept for one model and fit (one linearisation per
    joint serves all its orders)."""
    if carry.folds is None or not _is_cyclic(label):
        return {}
    current, joint = [e.label for e in model.effects], _joint(label)
    orders = [
        c
        for c in cyclic_candidates(model.robot, split.train)
        if _joint(c) == joint and c not in current
    ]
    if joint not in cache:
        say(f"are the orders of {joint} resolved? ({len(orders)} orders)")
        trial = with_effects(model, [make_effect(model.robot, a) for a in orders])
        cache[joint] = linearise(trial, res, split, carry.folds, say, factor=False)[3]
    adv = rival_advantages(cache[joint], current, label, [a for a in orders if a != label])
    return {a: v for a, v in adv.items() if v < carry.margin(res)}


def unresolved_entry(label: str, rivals: dict[str, float], margin: float) -> list[dict]:
    """Ambiguity entries of a cyclic order that ``rivals`` predict nearly as well."""

    def how(alt: str, adv: float) -> str:  # adv: how much better label predicts than alt
        if adv < 0:
            return f"{alt} predicts the blocked hold-out better than {label} (by {-adv:.3g} mm)"
        return (
            f"{alt} predicts the blocked hold-out within {adv:.3g} mm of {label} (less than "
            f"the {margin:.3g} mm margin)"
        )

    return [
        {
            "effects": [label, alt],
            "why": f"{how(alt, adv)}: the order is not resolved by these rows, so neither is named",
            "order_not_resolved": _joint(label),
        }
        for alt, adv in sorted(rivals.items(), key=lambda kv: kv[1])
    ]


def order_groups(ambiguous: list[dict]) -> tuple[dict[str, list[int]], list[dict]]:
    """The cyclic orders ``ambiguous`` lists as not resolved, per joint (``{joint:
    orders per turn, ascending}``; the data show a periodic error there, not its
    order), and the other entries."""
    groups: dict[str, set[int]] = {}
    others = []
    for entry in ambiguous:
        joint = entry.get("order_not_resolved")
        if not joint:
            others.append(entry)
            continue
        for label in entry["effects"]:
            groups.setdefault(joint, set()).add(cyclic_error_kind(label.partition(":")[0]).order)
    return {j: sorted(v) for j, v in groups.items()}, others


def settle(
    model: ExtendedModel,
    res: FitResult,
    split: Split,
    carry: Carry,
    steps: list[dict],
    say: Callable[[str], None],
    flagged: list[dict] | None = None,
) -> tuple[ExtendedModel, FitResult, dict[str, dict], list[dict]]:
    """Take out implausible effects, unresolved cyclic errors and causes below the
    margin (see the module).

    Returns the model, its fit, each remaining cause's blocked gains (by label:
    ``gain_mm``, ``position_mm``, ``orientation_deg``; a periodic one also
    ``own_range``, :func:`.own_range.own_range_gains`) and the ambiguity entries. An
    implausible effect's :func:`.plausibility.implausibility` entry goes into
    ``flagged``."""
    ambiguous: list[dict] = []
    while True:
        # every refit (the search's, this loop's) may carry an effect off: first that
        implausible = implausible_effect(model, split.train, res=res)
        if implausible is not None:
            drop = implausible["cause"]
            why = refusal_why(implausible)
            say(f"taking out {drop}: {why}")
            _record(steps, drop, why, None, carry.margin(res))
            if flagged is not None:
                flagged.append(implausible)
            model = without_effect(model, drop)
            res = refit_removed(model, drop, split.train, split.cond_fit, res, None, say)
            continue
        if not model.effects or carry.folds is None:
            break
        labels = [e.label for e in model.effects]
        alts = {
            lbl: [c for c in cyclic_candidates(model.robot, split.train)
                  if _joint(c) == _joint(lbl) and c not in labels]
            for lbl in labels if _is_cyclic(lbl)
        }  # fmt: skip
        extra = sorted({a for v in alts.values() for a in v})
        trial = with_effects(model, [make_effect(model.robot, a) for a in extra])
        say("blocked hold-out gain of each cause")
        problem, blocks, _, blocked = linearise(
            trial, res, split, carry.folds, say, factor=False, keep=True
        )
        near = Linearisation.kept_by(problem, blocks)
        del problem  # its rows live on in near
        gains = removal_gains(blocked, labels)
        margin = carry.margin(res)
        drop, why = _unresolved(blocked, labels, alts, margin, ambiguous)
        own: dict[str, dict] = {}
        if drop is None:
            say("own-range gain of each periodic cause")
            own = own_range_gains(model, res, split, say)
            drop, why = off_range(own, margin, ambiguous)
        if drop is None:
            drop, why = _below_margin(gains, margin)
        if drop is None:
            for label, record in own.items():
                gains[label]["own_range"] = record
            return model, res, gains, ambiguous
        say(f"taking out {drop}: {why}")
        _record(steps, drop, why, gains[drop]["gain_mm"], margin)
        model = without_effect(model, drop)
        res = refit_removed(model, drop, split.train, split.cond_fit, res, near, say)
    return model, res, {}, ambiguous


def _unresolved(blocked, labels, alts, margin, ambiguous):
    """The cyclic error whose order another order predicts as well (or better), and why
    (None: every order resolved); its ambiguity entries go into ``ambiguous``."""
    worst = None  # (advantage, label, rivals)
    for label, others in alts.items():
        adv = rival_advantages(blocked, labels, label, others)
        rivals = {a: v for a, v in adv.items() if v < margin}
        if rivals and (worst is None or min(rivals.values()) < worst[0]):
            worst = (min(rivals.values()), label, rivals)
    if worst is not None:
        _, label, rivals = worst
        ambiguous += unresolved_entry(label, rivals, margin)
        return label, f"order not resolved: {', '.join(sorted(rivals))} predict as well"
    return None, ""


def _below_margin(gains, margin):
    """The cause with the smallest blocked gain below ``margin``, and why (None: every
    one carries over)."""
    label = min(gains, key=lambda k: gains[k]["gain_mm"])
    if gains[label]["gain_mm"] >= margin:
        return None, ""
    return label, (
        f"gains {gains[label]['gain_mm']:.3g} mm on the blocked hold-out, less than the "
        f"practical margin {margin:.3g} mm"
    )


def _record(steps: list[dict], label: str, why: str, gain: float | None, margin: float) -> None:
    """Log the removal and mark the step that accepted ``label`` as undone (``gain``:
    its blocked gain, None when it was not measured)."""
    for s in steps:
        if s["candidate"] == label and s.get("accepted"):
            s["accepted"] = False
            s["why"] = f"taken out after the search: {why}"
    record = {"candidate": label, "removed": True, "blocked_gain_mm": gain, "min_gain_mm": margin}
    if gain is None:
        del record["blocked_gain_mm"]
    steps.append({**record, "accepted": False, "why": f"does not carry over: {why}"})

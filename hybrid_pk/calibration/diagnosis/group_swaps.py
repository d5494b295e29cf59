"""The final model: settled causes, group stand-ins, and one cause for a named group.

After the search, :func:`.settle.settle` takes out the causes that do not carry over;
the detection limits of the candidates not named come from one factor of the final
model's columns and theirs, which also shows the candidates that two or more named
causes together stand in for (:mod:`.stand_ins`). The same factor shows the named
causes whose exchange (:mod:`.exchanges`: the cause out, two forward steps, backward
elimination) may give a simpler model; those are exchanged first, where the swap rule
keeps it, and the model is settled and scored again. A stand-in candidate may be the simpler
story: a Panda's hidden joint-4 offset is named by the search as the joint-5 axis
misalignment (2 parameters) together with the joint-5 link length, and the offset (1
parameter) with that link length does the same. For each member of the group, the
model with that member replaced by the candidate is refitted and followed by backward
elimination, and the best such swap is kept under the rule of the one-for-one swaps
(:func:`.swaps.best_swap`: plausible, fewer causes or fewer parameters, BIC no worse,
and a blocked hold-out the current model does not predict better by the practical
margin). After a swap the model is settled again and the candidates not named are
scored anew; the old group is then listed as what still stands in for the cause now
named, where it does.

The swaps are an optional stage (``group swaps`` under the work budget,
:mod:`.budget`), one swap (a member replaced, refitted, backward elimination) a unit:
the first stand-in's first swap is tried whatever the budget, each later one only
while it lasts. One swap may still overrun the budget by itself: on the UR10 pan split
capped at 20 causes the first cost 1.3 times the main search's work, most of it the
backward elimination of a swapped model that fits worse (its refits run to LM's
iteration limit).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from hybrid_pk.calibration.diagnosis.budget import Budget
from hybrid_pk.calibration.diagnosis.carryover import Carry
from hybrid_pk.calibration.diagnosis.exchanges import exchange_causes, promising
from hybrid_pk.calibration.diagnosis.power import detection_limits
from hybrid_pk.calibration.diagnosis.settle import settle
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.stand_ins import group_stand_ins, swapped_stand_ins
from hybrid_pk.calibration.diagnosis.swaps import best_swap, rationed, record_swap
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.effects import ExtendedModel

__all__ = ["Final", "final_model"]


@dataclass
class Final:
    """The final model of a diagnosis and its fit, before its causes are measured."""

    model: ExtendedModel
    res: FitResult
    gains: dict[str, dict] = field(default_factory=dict)  # blocked gains (:func:`.settle.settle`)
    unresolved: list[dict] = field(default_factory=list)  # ambiguity entries of the settling
    detectable: list[dict] = field(default_factory=list)  # limits of the candidates not named
    stand_ins: list[dict] = field(default_factory=list)  # group stand-ins (:mod:`.stand_ins`)
    flagged: list[dict] = field(default_factory=list)  # effects taken out as implausible


def final_model(
    model: ExtendedModel,
    res: FitResult,
    pool: list[str],
    split: Split,
    tests: tuple[float, Carry, Budget],
    steps: list[dict],
    say: Callable[[str], None],
) -> Final:
    """Settle the searched ``model``, list what is not named, and swap a named group
    for the candidate it stands in for where that is simpler (see the module).

    ``tests``: ``(alpha, carry, budget)``; ``steps``: the search's step records (a kept
    swap appends its own, and the settling its removals)."""
    alpha, carry, budget = tests
    out = Final(model, res)
    _settle(out, split, carry, steps, say)
    scores = _not_named(out, pool, split, (alpha, carry), say)
    causes = [] if scores is None else promising(scores, out.model, alpha)
    if causes:
        with budget.stage("exchanges"):
            named = [e.label for e in out.model.effects]
            fitted = (out.model, out.res)
            out.model, out.res = exchange_causes(fitted, causes, pool, split, tests, steps, say)
            if [e.label for e in out.model.effects] != named:
                _settle(out, split, carry, steps, say)
                _not_named(out, pool, split, (alpha, carry), say)  # limits, stand-ins anew
    if not out.stand_ins:
        return out
    with budget.stage("group swaps"):
        swaps = _prefer_single_causes(out, split, tests, steps, say)
        if swaps:
            _settle(out, split, carry, steps, say)
            scores = _not_named(out, pool, split, (alpha, carry), say)
            named = [e.label for e in out.model.effects]
            out.stand_ins += [] if scores is None else swapped_stand_ins(scores, named, swaps)
    return out


def _prefer_single_causes(out: Final, split: Split, tests, steps, say) -> list[dict]:
    """Name each candidate of ``out``'s stand-ins (:func:`.stand_ins.group_stand_ins`
    entries) in place of one member of its group, where the swap rule keeps it;
    ``out``'s model and fit become the swapped ones.

    ``tests``: ``(alpha, carry, budget)``; the first swap (the first entry's candidate
    in place of one member) is tried whatever the budget, each later one only while it
    lasts, and where the budget cuts an entry's swaps short the best of those tried
    may still be kept. Returns the swaps kept
    (``{"candidate", "group", "replaced", "simpler"}``)."""
    (alpha, carry, budget), stand_ins = tests, out.stand_ins
    swaps: list[dict] = []
    for k, entry in enumerate(stand_ins):
        if budget.stopped("group swaps"):
            break
        candidate, group = entry["effects"][0], entry["stood_in_by"]
        labels = [e.label for e in out.model.effects]
        if candidate in labels or not set(group) <= set(labels):
            continue  # an earlier swap changed the causes this entry speaks of
        trials = [(member, candidate) for member in group]
        later = [f"swaps for {e['effects'][0]}" for e in stand_ins[k + 1 :]]
        ration = rationed(budget, "group swaps", later)
        best = best_swap(out.model, out.res, trials, split, (alpha, carry), say, ration)
        if best is None:
            continue
        simpler = "fewer causes" if best.removed else "fewer parameters"
        why = (
            f"{candidate} in place of {best.chosen} does what {' + '.join(group)} did "
            f"together: {simpler}, the same fit"
        )
        out.model, out.res = record_swap(steps, best, split, why)
        swaps.append(
            {"candidate": candidate, "group": group, "replaced": best.chosen, "simpler": simpler}
        )
    return swaps


def _settle(out: Final, split: Split, carry: Carry, steps: list[dict], say) -> None:
    """:func:`.settle.settle` ``out``'s model, in place."""
    out.model, out.res, out.gains, unresolved = settle(
        out.model, out.res, split, carry, steps, say, out.flagged
    )
    out.unresolved += unresolved


def _not_named(out: Final, pool: list[str], split: Split, tests, say):
    """Fill in ``out``'s detection limits of the candidates not named and, from the
    same factor of the final model's and their columns, the candidates that named
    causes together stand in for (:mod:`.stand_ins`); returns that scoring (None
    without candidates). ``tests``: ``(alpha, carry)``."""
    say("detection limits of the candidates not named")
    out.detectable, scores = detection_limits(
        out.model, out.res, pool, split, tests[0], say, tests[1]
    )
    named = [e.label for e in out.model.effects]
    out.stand_ins = [] if scores is None else group_stand_ins(scores, named)
    return scores

"""Which candidate a search step tests, and what a step that tests none records.

The best eligible candidate (:meth:`.selection.Scores.eligible`) enters unless it is a
cyclic order that another order predicts the blocked hold-out nearly as well as
(:func:`first_resolved`); a search that stops records why (:func:`why_stop`), and one
stopped at its limit records the candidate it would have tested next
(:func:`note_cap`).
"""

from __future__ import annotations

from hybrid_pk.calibration.diagnosis.selection import carry_record, score_candidates
from hybrid_pk.calibration.diagnosis.settle import entry_rivals, order_rivals, unresolved_entry

__all__ = ["first_resolved", "note_cap", "untested", "why_stop"]


def first_resolved(scores, model, ambiguous, every_order=None):
    """The best eligible candidate (:meth:`Scores.eligible`) that is not a cyclic order
    another order predicts the blocked hold-out nearly as well as (or better); and the
    candidates set aside as unresolved (their ambiguity entries go into ``ambiguous``).
    ``every_order``: ``(model, res, split, carry, say)``, to compare a cyclic candidate
    with every order of its joint (:func:`.settle.order_rivals`), not only the scored
    ones."""
    current = [e.label for e in model.effects]
    aside: set[str] = set()
    per_joint: dict = {}  # every order of a joint: one linearisation
    for sc in scores.ranked:
        if not scores.eligible(sc):
            break
        if sc.label in aside:
            continue
        rivals = entry_rivals(scores, current, sc.label)
        if not rivals and every_order is not None:
            m, r, split, carry, say = every_order
            rivals = order_rivals(m, r, split, carry, sc.label, say, per_joint)
        if not rivals:
            return sc, aside
        ambiguous += unresolved_entry(sc.label, rivals, scores.margin)
        aside |= {sc.label, *rivals}
    return None, aside


def why_stop(scores, aside: set[str]) -> str:
    """Why the search stopped with candidates left (``aside``: unresolved orders)."""
    best = scores.ranked[0]
    if aside:
        return (
            "every significant candidate that gains the practical margin on the blocked "
            "hold-out is a cyclic order that other orders predict as well (see ambiguous)"
        )
    if best.p >= scores.threshold:
        return "best remaining candidate is not significant"
    sig = [s.label for s in scores.scored if s.p < scores.threshold]
    top = max(sig, key=lambda s: scores.carry.get(s, 0.0))
    gain, se = scores.carry.get(top, 0.0), scores.carry_se.get(top, 0.0)
    return (
        "no significant candidate gains the practical margin and its own standard "
        f"error over the blocks on the blocked hold-out (best {gain:.3g} mm, standard "
        f"error {se:.3g} mm, margin {scores.margin:.3g} mm)"
    )


def note_cap(model, res, pool, split, tests, limits, steps, say) -> None:
    """Record (``"capped"`` step) the candidate the search would have tested next when it
    stopped at ``max_causes`` (:func:`first_resolved`: significant, gaining the margin,
    a resolved order): the data carry more than was named. ``tests``: ``(alpha, carry)``;
    ``limits``: ``(max_causes, screened)``."""
    (alpha, carry), (max_causes, screened) = tests, limits
    say(f"{max_causes} causes named (the limit): does the next candidate still carry over?")
    scores = score_candidates(
        model, res, pool, split, alpha, False, progress=say, screened=screened, carry=carry
    )
    if not scores.scored:
        return
    # the candidate the search would have tested next: eligible and, if a cyclic
    # order, resolved (its unresolved orders were never candidates for a cause)
    best, _ = first_resolved(scores, model, [], (model, res, split, carry, say))
    if best is None:
        return
    why = f"not tested: the search stopped at max_causes = {max_causes}"
    steps.append({**untested(best, scores, why), "capped": max_causes})


def untested(best, scores, why: str) -> dict:
    """The step record of a scored candidate that was not refitted."""
    out = {
        "candidate": best.label,
        "score_F": best.F,
        "score_p": best.p,
        "threshold": scores.threshold,
        "accepted": False,
        "why": why,
    }
    if scores.blocked is not None:
        out.update(carry_record(scores, best.label))
    return out

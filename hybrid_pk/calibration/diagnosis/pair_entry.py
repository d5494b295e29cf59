"""Two causes that carry over only together: a pair enters where no single one does.

A cause enters on a blocked hold-out gain the blocks agree on (:meth:`.selection.Scores.
carries`: the practical margin and its own standard error over the blocks). Two hidden
effects can mask each other so that neither alone carries over: fitted without the
other, each takes part of the other's signature in a way that holds in some regions of
joint space and fails in the others. On an RX160 with a joint-3 offset and a soft
joint-2 under a payload (sweep seed 242424, pinocchio-generated rows), each alone
gains 0.11-0.18 mm pooled over the blocks with a standard error of 0.25 mm (the
regions' own drops -0.7 .. +0.6 mm), so the search named nothing; together they gain
1.12 mm at a standard error of 0.28 mm, and leave the noise (0.034 mm in every block).

So when no significant candidate carries over alone, the pairs of the significant
candidates are scored on the same linearisation (every candidate's columns are in it):
the best pair whose gain reaches the margin and its own standard error enters, its
member with the larger score first; at the next step the partner is judged on its own,
with the first in the model, and the first stays only while it gains the margin
(:func:`.carryover.weakest`), as every cause.
"""

from __future__ import annotations

__all__ = ["PAIR_CANDIDATES", "carrying_pair"]

# The significant candidates (best score first) whose pairs are scored: 12 give 66
# pairs, each a batched blocked score; a masking pair is among the largest scores, as
# each member explains much of the error in sample (seed 242424: ranks 1 and 4).
PAIR_CANDIDATES = 12


def carrying_pair(scores, current: list[str], base) -> dict | None:
    """``{"lead", "partner", "gain_mm", "se_mm"}`` of the best pair of significant
    candidates of ``scores`` (a scoring at the model whose effects are ``current``, with
    blocked score ``base``) whose blocked gain reaches the practical margin and its own
    standard error, when no single candidate does; else None. ``lead``: the member with
    the larger score."""
    blocked = scores.blocked
    if blocked is None or any(scores.eligible(sc) for sc in scores.scored):
        return None
    significant = sorted(
        (sc for sc in scores.scored if sc.p < scores.threshold), key=lambda sc: -sc.F
    )[:PAIR_CANDIDATES]
    if len(significant) < 2:
        return None
    best = None
    for i, lead in enumerate(significant[:-1]):
        partners = [sc.label for sc in significant[i + 1 :]]
        for partner, with_both in zip(
            partners, blocked.each([*current, lead.label], partners), strict=True
        ):
            gain = blocked.gain_mm(base, with_both)
            se = blocked.gain_se_mm(base, with_both)
            if gain >= max(scores.margin, se) and (best is None or gain > best["gain_mm"]):
                best = {"lead": lead.label, "partner": partner, "gain_mm": gain, "se_mm": se}
    return best

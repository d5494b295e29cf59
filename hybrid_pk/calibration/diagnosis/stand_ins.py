"""Group stand-ins: a candidate not named that two or more named causes together mimic.

The pairwise checks of :mod:`.ambiguity` compare one candidate with one cause; after
the first step a candidate inside the current model's columns is dropped silently
(:data:`.selection.EQUIVALENCE_FRACTION`). A joint offset of a Panda's joint 4, for
one, moves the point as the next joint's axis misalignment and link length do
together (exactly; neither alone makes all of it), so the search may name the pair and
no entry says that the offset would explain the same.

At the final model, on the factor of the Jacobian that the detection limits build
(:func:`.power.detection_limits`: the model's columns, frames included, and every
candidate not named), each candidate's signature and each named cause's columns are
projected off the frames. A candidate whose every identifiable direction lies inside
the span of the named causes (|cosine| of the worst direction above the tuning's
``ambiguity_cosine``, as the pairwise check) is listed with the causes it needs there:
causes are dropped one at a time while the rest hold it nearly as closely
(:func:`_smallest_group`); a candidate that one cause holds without the others' help
is left to the pairwise checks. Nothing is refitted here; :mod:`.group_swaps` tries the
candidate in place of each member of its group, and where it names the candidate,
:func:`swapped_stand_ins` lists the old group as what still stands in for it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.ambiguity import projector_residual
from hybrid_pk.calibration.diagnosis.selection import Scores, rank_basis
from hybrid_pk.calibration.tuning import diagnosis_tuning

__all__ = ["group_stand_ins", "kept_stand_ins", "swapped_stand_ins"]


def group_stand_ins(scores: Scores, named: list[str]) -> list[dict]:
    """Ambiguity entries ``{"effects": [candidate, *group], "stood_in_by": group,
    "why"}`` of the candidates of ``scores`` (a scoring at the final model) that the
    named causes ``named`` together could stand in for (each member needed:
    :func:`_smallest_group`)."""
    if scores.R is None or len(named) < 2:
        return []
    cols, norms = _off_frames(scores, named)
    causes = {c: v for c, v in cols.items() if c in named}
    everything = rank_basis(torch.cat(list(causes.values()), 1))
    least = diagnosis_tuning().ambiguity_cosine
    out = []
    for label in (c for c in cols if c not in named):
        U = rank_basis(cols[label], norms[label])
        if U.shape[1] == 0 or float(torch.linalg.svdvals(everything.T @ U).min()) <= least:
            continue  # inside the frames (the frame check's) or outside the causes' span
        group = _smallest_group(U, causes)
        if group is not None:
            alone = {c: _held(U, causes, [c]) for c in group}
            out.append(_entry(label, group, _held(U, causes, group), alone))
    return out


def swapped_stand_ins(scores: Scores, named: list[str], swaps: list[dict]) -> list[dict]:
    """Ambiguity entries ``{"effects": [candidate, *group], "group": group,
    "named_in_place_of": member, "why"}`` of the group swaps ``swaps`` (``{"candidate",
    "group", "replaced", "simpler"}``: the candidate a named group stood in for, named
    in place of one member) whose old group still stands in for the candidate in
    ``scores`` (a scoring at the model after the swaps, whose causes are ``named``: the
    candidate among them, the member not): every direction of the candidate, beside
    the frames, within the group's span at |cosine| above the tuning's
    ``ambiguity_cosine``."""
    if scores.R is None or not swaps:
        return []
    cols, norms = _off_frames(scores, named)
    out = []
    for swap in swaps:
        label, group = swap["candidate"], swap["group"]
        if label not in named or not set(group) <= set(cols):
            continue  # no longer named, or a member not scored here: nothing to compare
        U = rank_basis(cols[label], norms[label])
        cos = _held(U, cols, group)
        if U.shape[1] and cos > diagnosis_tuning().ambiguity_cosine:
            out.append(_swapped_entry(label, group, swap["replaced"], cos, swap["simpler"]))
    return out


def _off_frames(scores: Scores, named) -> tuple[dict[str, Tensor], dict[str, float]]:
    """Columns of ``scores``' factor, by label, of the ``named`` causes and of the
    candidates, projected off the frames' (the current model's other columns), and
    their norms before that."""
    J = scores.R[:, :-1]
    frames, cols, start = [], {}, 0
    for b in scores.blocks:
        block, start = J[:, start : start + b.size], start + b.size
        if start > scores.n_current or b.label in named:
            cols[b.label] = block
        else:
            frames.append(block)
    Qf = rank_basis(torch.cat(frames, 1)) if frames else J[:, :0]
    return (
        {c: projector_residual(v, Qf) for c, v in cols.items()},
        {c: float(v.norm()) for c, v in cols.items()},
    )


def kept_stand_ins(entries: list[dict], causes: list) -> list[dict]:
    """The entries whose stand-in group (or, after a group swap, the candidate and the
    group's members kept) are still among the reported ``causes``
    (:class:`.result.Cause`: the structural check may turn a cause into a finding)."""
    named = {c.effect if c.joint is None else f"{c.effect}:{c.joint}" for c in causes}
    return [e for e in entries if set(_needs_named(e)) <= named]


def _needs_named(entry: dict) -> list[str]:
    """The effects of a stand-in entry that must be named for it to hold."""
    if "stood_in_by" in entry:
        return entry["stood_in_by"]
    return [e for e in entry["effects"] if e != entry["named_in_place_of"]]


def _held(U: Tensor, spans: dict[str, Tensor], group: list[str]) -> float:
    """|cosine| of ``U``'s worst direction with the span of ``group``'s columns."""
    Q = rank_basis(torch.cat([spans[c] for c in group], 1))
    return float(torch.linalg.svdvals(Q.T @ U).min()) if Q.shape[1] else 0.0


def _smallest_group(U: Tensor, spans: dict[str, Tensor]) -> list[str] | None:
    """The causes whose span holds ``U`` (cosine above the tuning's
    ``ambiguity_cosine``) and that it needs; None unless two or more. From all of them,
    the cause whose loss leaves the least of ``U`` outside is dropped while the rest
    leave at most twice what the group does or half the share a lookalike may leave
    (``1 - ambiguity_cosine ** 2``): a needed cause explains at least half of what the
    others leave, and enough to move the pairwise checks' verdict."""
    least = diagnosis_tuning().ambiguity_cosine
    allowed = 1.0 - least**2
    group = list(spans)
    outside = 1.0 - _held(U, spans, group) ** 2
    if outside >= allowed:
        return None
    while len(group) > 1:
        left, drop = min((1.0 - _held(U, spans, [x for x in group if x != c]) ** 2, c)
                         for c in group)  # fmt: skip
        if left > max(2 * outside, allowed / 2):
            break
        group.remove(drop)
        outside = left
    return group if len(group) > 1 else None


def _entry(label: str, group: list[str], cos: float, alone: dict[str, float]) -> dict:
    """The ambiguity entry of ``label``, which ``group`` together stands in for
    (``alone``: each member's own |cosine| with it)."""
    together = " + ".join(group)
    each = ", ".join(f"{c} {v:.4f}" for c, v in alone.items())
    return {
        "effects": [label, *group],
        "stood_in_by": group,
        "why": f"{label} (not named) moves the measured pose as {together} do together "
        f"(|cos| = {cos:.4f} beside the frames; alone: {each}): the data cannot "
        f"tell it from their combination, it may be the physical cause they stand in for",
    }


def _swapped_entry(label: str, group: list[str], member: str, cos: float, simpler: str) -> dict:
    """The ambiguity entry of ``label``, named in place of ``member`` of ``group``, which
    still together stands in for it."""
    together = " + ".join(group)
    return {
        "effects": [label, *group],
        "group": group,
        "named_in_place_of": member,
        "why": f"{label} moves the measured pose as {together} do together (|cos| = "
        f"{cos:.4f} beside the frames): the data cannot tell them apart; {label} is named "
        f"in place of {member} ({simpler}, the same fit)",
    }

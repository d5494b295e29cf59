"""Exchanges: a cause chosen first may hold the place of two others.

Forward selection scores every candidate against all that the nominal model gets wrong.
With two hidden effects, a cause that makes part of each can win the first step, and a
second cause then finishes both; no near-duplicate of either cause does what it does
alone, so the one-for-one swaps (:mod:`.swaps`) find nothing. On the RX160 the joint_1
tilt compliance sees the joint_2 holding torque plus the constant moment of the arm's
weight about the shoulder offset: it turns the arm as a joint_2 compliance does,
together with a constant rotation about the joint_2 axis. Where a hidden joint_3
offset is about that rotation, the tilt with a joint_3 link length makes both hidden
effects (a joint_2 compliance and the joint_3 offset) to a tenth of a millimetre, and
either one-for-one swap breaks the pair: the compliance in place of the tilt leaves the
link length without the rotation it completes, the offset in place of the link length
leaves the tilt's rotation over.

An exchange takes one named cause out and lets the search choose twice at the others:
the best eligible candidate in its place (the same scoring and entry rule as a search
step; the cause itself not), then one forward step more; then, as after the search,
backward elimination and the near-duplicate swaps of what it chose.
The exchange stays under the swap rule (:func:`.swaps.judged`: fewer causes or as
many with fewer parameters, BIC no worse, and a blocked hold-out the current model
does not predict better by the practical margin).

It runs on the settled model (:mod:`.group_swaps`), and only for the causes that pass
the same rule linearised (:func:`promising`) on the scoring the detection limits
already made there (one factor of the model's and every candidate's columns): a cause
whose exchange could not give a simpler model with a BIC no worse even on the
linearisation is not refitted, so a diagnosis that the exchanges leave alone does the
work it did before them. The refits are an optional stage (``exchanges`` under the
work budget, :mod:`.budget`): the first such cause's exchange is tried whatever the
budget, the others only while it lasts.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.ambiguity import near_duplicates, projector_residual
from hybrid_pk.calibration.diagnosis.budget import Budget
from hybrid_pk.calibration.diagnosis.carryover import Carry
from hybrid_pk.calibration.diagnosis.cyclic_screen import screen_cyclic
from hybrid_pk.calibration.diagnosis.elimination import eliminate
from hybrid_pk.calibration.diagnosis.plausibility import implausible_effect
from hybrid_pk.calibration.diagnosis.selection import (
    Scores,
    rank_basis,
    score_candidates,
    try_candidate,
)
from hybrid_pk.calibration.diagnosis.settle import entry_rivals
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import weighted_ssr
from hybrid_pk.calibration.diagnosis.swaps import (
    Swap,
    blocked_score,
    judged,
    prefer_fewer_causes,
    record_swap,
)
from hybrid_pk.calibration.diagnosis.variants import without_effect
from hybrid_pk.calibration.fit import FitResult, fit
from hybrid_pk.distributions import f_sf
from hybrid_pk.effects import ExtendedModel

__all__ = ["exchange_causes", "promising"]


def promising(scores: Scores, model: ExtendedModel, alpha: float) -> list[str]:
    """The named causes of ``model`` whose exchange the swap rule may keep, judged on
    the linearisation of ``scores`` (a scoring of every candidate at ``model``: its
    factor of ``[J r]``; nothing is refitted, :func:`exchange_causes` refits those that
    pass). With the cause set to zero, the candidate the search would choose in its
    place and the one after it (by BIC gain, each significant at the search's level:
    ``alpha`` over the candidates), then the other causes whose removal is not
    significant (``alpha`` over the causes) dropped one at a time, the least missed
    first: some model on the way has fewer causes, or as many with fewer parameters,
    and a linearised BIC no higher than ``model``'s."""
    if scores.R is None or not scores.scored:
        return []
    J, r = scores.R[:, :-1], scores.R[:, -1]
    cols, start = {}, 0
    for b in scores.blocks:
        cols.setdefault(b.label, []).append((start, b.size, b.scale))
        start += b.size
    index = {k: torch.cat([torch.arange(a, a + n) for a, n, _ in v]) for k, v in cols.items()}
    named = [e.label for e in model.effects]
    zero = {}  # each cause's part of the residual: what setting it to zero takes away
    for c in named:
        scale = torch.cat([torch.full((n,), sc) for _, n, sc in cols[c]]).to(J.dtype)
        zero[c] = J[:, index[c]] @ (model.effect(c).value.detach().reshape(-1).to(J.dtype) / scale)
    lin = _Linear(
        J, r, index, {k: len(v) for k, v in index.items()}, scores.m, zero,
        frames=[k for k in index if k not in named and int(index[k][0]) < scores.n_current],
        others=[sc.label for sc in scores.scored if sc.label in index and sc.label not in named],
        alpha=alpha,
    )  # fmt: skip
    return [cause for cause in named if _simpler(lin, cause)]


class _Linear(NamedTuple):
    """The linearisation :func:`promising` reads: the factor's columns ``J`` and
    residual ``r``, their indices and parameter counts by block label, the residual
    count ``m``, each named cause's part of the residual (``zero``), the frames'
    labels, the candidates' and the F-tests' level."""

    J: Tensor
    r: Tensor
    index: dict[str, Tensor]
    size: dict[str, int]
    m: int
    zero: dict[str, Tensor]
    frames: list[str]
    others: list[str]
    alpha: float

    def left(self, labels: list[str]) -> Tensor:
        """The linearised residual of the model of ``labels`` (the named causes not
        among them set to zero; the frames' and their columns free)."""
        r = self.r - sum(
            (z for c, z in self.zero.items() if c not in labels), torch.zeros_like(self.r)
        )
        base = rank_basis(self.J[:, torch.cat([self.index[k] for k in self.frames + labels])])
        return projector_residual(r, base)

    def p_value(self, drop: float, k: int, ssr: float, n: int) -> float:
        """The F-test of ``k`` parameters that explain ``drop`` of the SSR ``ssr`` of a
        model of ``n`` parameters (theirs included)."""
        dof = max(self.m - n, 1)
        F = (drop / k) / max(ssr / dof, 1e-300)
        return f_sf(F, k, dof) if F > 0 else 1.0


def _simpler(lin: _Linear, cause: str) -> bool:
    """Whether ``cause`` set to zero, two forward steps and backward elimination give a
    simpler model with a BIC no higher (linearised, see :func:`promising`)."""
    named = list(lin.zero)
    frame_params = sum(lin.size[k] for k in lin.frames)
    n_now, log_m = sum(lin.size[c] for c in named), math.log(lin.m)
    ssr_now = float(lin.left(named).pow(2).sum())
    kept = [c for c in named if c != cause]
    for _ in range(2):  # in its place, then one more
        left = lin.left(kept)
        base = rank_basis(lin.J[:, torch.cat([lin.index[k] for k in lin.frames + kept])])
        drops = {c: _drop(lin.J[:, lin.index[c]], base, left) for c in lin.others if c not in kept}
        if not drops:
            break
        best = max(drops, key=lambda c: drops[c] - lin.size[c] * log_m)
        n = frame_params + sum(lin.size[k] for k in kept) + lin.size[best]
        ssr = float(left @ left) - drops[best]
        if lin.p_value(drops[best], lin.size[best], ssr, n) >= lin.alpha / len(lin.others):
            break  # not significant: the search would not choose it
        kept.append(best)
    while True:
        ssr, n_par = float(lin.left(kept).pow(2).sum()), sum(lin.size[c] for c in kept)
        fewer = len(kept) < len(named) or (len(kept) == len(named) and n_par < n_now)
        bic = lin.m * math.log(max(ssr, 1e-300) / max(ssr_now, 1e-300))
        if fewer and bic + (n_par - n_now) * log_m <= 0:
            return True
        droppable = [c for c in kept if c in named]
        if not droppable:
            return False
        without = {c: float(lin.left([k for k in kept if k != c]).pow(2).sum()) for c in droppable}
        least = min(without, key=without.get)
        p = lin.p_value(without[least] - ssr, lin.size[least], ssr, frame_params + n_par)
        if p < lin.alpha / len(kept):
            return False  # every other cause still significant: elimination keeps them
        kept.remove(least)


def _drop(cols: Tensor, base: Tensor, left: Tensor) -> float:
    """How much of ``left`` (orthogonal to ``base``) the columns ``cols`` explain beside
    ``base``: the score test's drop (:func:`.selection.score_candidates`, the same rank
    rule)."""
    U = rank_basis(projector_residual(cols, base), float(cols.norm()))
    return float((U.T @ left).pow(2).sum())


def exchange_causes(
    fitted: tuple[ExtendedModel, FitResult],
    causes: list[str],
    pool: list[str],
    split: Split,
    tests: tuple[float, Carry, Budget],
    steps: list[dict],
    say: Callable[[str], None],
) -> tuple[ExtendedModel, FitResult]:
    """Exchange named causes where the swap rule keeps it (see the module).

    Args:
        causes: the named causes to exchange, in order (:func:`promising`).
        pool: every candidate of the diagnosis.
        fitted: the model and its fit.
        tests: ``(alpha, carry, budget)``: the F-tests' level, the blocked hold-out's
            blocks and margin, and the optional stages' :class:`~.budget.Budget`.
        steps: the search's step records; a kept exchange appends its own, the step of
            the second choice and the removals that followed.

    Returns the (possibly) simpler model and its fit.
    """
    (model, res), (alpha, carry, budget) = fitted, tests
    for k, cause in enumerate(causes):
        if carry.folds is None:
            break  # the swap rule's blocked hold-out needs blocks
        named = [e.label for e in model.effects]
        if cause not in named or len(named) < 2:
            continue  # an earlier exchange took it out
        if k and budget.spent():
            left = [f"exchange of {c}" for c in causes[k:] if c in named]
            budget.cut("exchanges", left)
            break
        n_causes = len(model.effects)
        swap = _exchange(model, res, cause, pool, split, (alpha, carry), say)
        if swap is None:
            continue
        added = [s["candidate"] for s in swap.removals if s.get("accepted")]
        together = " + ".join([swap.alternative, *added])
        gone = " + ".join([cause, *sorted(swap.removed)])
        simpler = "fewer causes" if len(swap.model.effects) < n_causes else "fewer parameters"
        why = f"{together} in place of {gone} (an exchange): {simpler}, the same fit"
        model, res = record_swap(steps, swap, split, why, simpler)
    return model, res


def _exchange(model, res, cause, pool, split, tests, say) -> Swap | None:
    """The exchange of ``cause`` (``model`` without it, two forward steps, backward
    elimination) that the swap rule keeps, or None."""
    alpha, carry = tests
    labels = [e.label for e in model.effects]
    current = (
        weighted_ssr(model, split.train, split.cond_fit, res),
        blocked_score(model, res, split, carry, say),
    )
    say(f"exchanging {cause}: what does the search choose in its place?")
    trial = without_effect(model, cause)
    sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
    trial_res = fit(
        trial, split.train, cond=split.cond_fit, initial_sigma=sigmas, progress=say,
        report_frames=False, **res.settings(),
    )  # fmt: skip
    added: list[dict] = []
    pairs: list[tuple[str, str]] = []  # (chosen, near-duplicate), as the search keeps them
    for exclude in ({cause}, set()):  # in its place, then one step more
        named = [e.label for e in trial.effects]
        open_ = [c for c in pool if c not in named and c not in exclude]
        step = _forward(trial, trial_res, open_, split, tests, say)
        if step is None:
            break
        trial, trial_res, record, duplicates = step
        added.append(record)
        pairs += duplicates
    if not added:
        return None
    alternative, log = added[0]["candidate"], list(added)
    # as after the search: backward elimination, then the near-duplicate swaps
    trial, trial_res, _ = eliminate(
        trial, trial_res, split, alpha, added[-1]["candidate"], log, say
    )
    trial, trial_res = prefer_fewer_causes(trial, trial_res, pairs, split, tests, log, say)
    kept = {e.label for e in trial.effects}
    if alternative not in kept:
        return None
    removed = set(labels) - kept - {cause}
    removals = [s for s in log if s is not added[0]]  # added[0] is the swap's own step
    fitted = (trial, trial_res)
    return judged(
        model, res, current, fitted, (cause, alternative), removed, removals, split, carry, say
    )


def _forward(model, res, pool, split, tests, say):
    """One step of the search at ``model``: ``(model, fit, step record, pairs)`` with
    the best eligible candidate of ``pool`` (a resolved order if cyclic, plausible,
    accepted by the refit) and its ``(label, near-duplicate)`` pairs
    (:func:`.ambiguity.near_duplicates`), or None."""
    alpha, carry = tests
    open_, screened = screen_cyclic(model, split, pool, res.weights, carry.folds, carry.margin(res))
    scores = score_candidates(
        model, res, open_, split, alpha, False, progress=say, screened=screened, carry=carry
    )
    current = [e.label for e in model.effects]
    best = next(
        (
            sc
            for sc in scores.ranked
            if scores.eligible(sc) and not entry_rivals(scores, current, sc.label)
        ),
        None,
    )
    if best is None:
        return None
    new, new_res, step = try_candidate(model, res, best, scores, split, progress=say)
    if not step["accepted"] or implausible_effect(new, split.train, best.label, new_res):
        return None
    duplicates = near_duplicates(best.label, best.fitted, scores.signatures)
    return new, new_res, step, [(best.label, d["effects"][1]) for d in duplicates]

"""Forward selection: score every candidate from one Jacobian, refit the best one.

At the current model, one Jacobian of *every* candidate effect gives each candidate's
score: the drop of the (noise-normalised) sum of squares it would bring once projected
off what the model already explains (a Lagrange multiplier / score test, linear in the
candidates). The best candidate is added and the model refitted; it stays only if the
refit passes an F-test at ``alpha / n_candidates`` (Bonferroni over the candidates
tried), lowers BIC and lowers the hold-out error.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from hybrid_pk.calibration.chord import Linearisation
from hybrid_pk.calibration.diagnosis.ambiguity import (
    equivalent_to_frame,
    frame_of_equivalence,
    projector_residual,
)
from hybrid_pk.calibration.diagnosis.blocked import Blocked
from hybrid_pk.calibration.diagnosis.carryover import Carry, linearise
from hybrid_pk.calibration.diagnosis.pair_entry import carrying_pair
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import (
    holdout_score,
    weighted_residual,
    weighted_ssr,
)
from hybrid_pk.calibration.diagnosis.variants import shift_parameters, with_effects
from hybrid_pk.calibration.fit import FitResult, fit
from hybrid_pk.calibration.robust import reestimated_noise
from hybrid_pk.calibration.shared_jacobian import release_shared
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.distributions import f_sf
from hybrid_pk.effects import EFFECTS, ExtendedModel, effect_joint_names, make_effect
from hybrid_pk.effects.base import Effect, effect_joint_types
from hybrid_pk.effects.joint import CYCLIC_PREFIX, MAX_CYCLIC_ORDER
from hybrid_pk.robot import Robot

__all__ = [
    "CandidateScore",
    "Scores",
    "candidate_labels",
    "gauss_newton_start",
    "rank_basis",
    "score_candidates",
    "try_candidate",
]

# A candidate whose signature keeps less than this fraction of its squared norm once
# projected off the current model's columns is taken as equivalent to them
# (unidentifiable): 1e-4 of the norm, 0.1 um left of a 1 mm displacement, a hundred
# times under a laser tracker's noise (~10 um).
EQUIVALENCE_FRACTION = 1e-8
# Singular values of a candidate's projected signature below this fraction of its own
# norm are directions the current model already explains: the same 1e-4 of the norm as
# EQUIVALENCE_FRACTION, a motion no tracker resolves.
RANK_TOLERANCE = 1e-4


def rank_basis(cols: Tensor, norm: float | None = None) -> Tensor:
    """Orthonormal basis of the directions of ``cols`` above :data:`RANK_TOLERANCE` of
    ``norm`` (default their own norm), each column scaled to unit norm first (blocks
    carry different units)."""
    if norm is None:
        cols = cols / cols.norm(dim=0).clamp_min(1e-300)
        norm = float(cols.norm())
    U, S, _ = torch.linalg.svd(cols, full_matrices=False)
    return U[:, S > RANK_TOLERANCE * max(norm, 1e-300)]


def candidate_labels(robot: Robot, data: MeasuredData) -> list[str]:
    """Every effect of the vocabulary that this data could reveal."""
    labels = []
    for kind, cls in EFFECTS.items():
        if not cls.per_joint or not _observable(cls, data):
            continue
        types = effect_joint_types(robot, cls)
        for i, joint in enumerate(effect_joint_names(robot, cls)):
            if cls.stage == "geometry" and i == 0:
                continue  # origin 0 is the base frame's business
            if cls.allowed_on(types[i]):  # e.g. a column's bending grows with its extension
                labels.append(f"{kind}:{joint}")
    labels += [k for k, cls in EFFECTS.items() if not cls.per_joint and _observable(cls, data)]
    return labels + cyclic_candidates(robot, data)


def _observable(cls: type[Effect], data: MeasuredData) -> bool:
    """Whether the data vary the condition an effect of ``cls`` needs (a temperature)."""
    if cls.needs != "temperature":
        return True
    if data.temperature is None:
        return False
    spread = float(data.temperature.max() - data.temperature.min())
    return spread >= diagnosis_tuning().min_temperature_spread


def cyclic_candidates(robot: Robot, data: MeasuredData) -> list[str]:
    """``cyclic_error_<n>:JOINT`` for every revolute joint and every order whose
    period the data's range of that joint covers at least once (n = 2 ..
    :data:`MAX_CYCLIC_ORDER`). Each order is a candidate of its own, so the search's
    Bonferroni level counts every order it tried."""
    labels = []
    span = (data.q.max(0).values - data.q.min(0).values).tolist() if data.n else []
    for i, joint in enumerate(robot.joint_names):
        if robot.joint_types[i] == "prismatic" or not span:
            continue
        lowest = max(2, math.ceil(2 * math.pi / max(span[i], 1e-9)))
        labels += [f"{CYCLIC_PREFIX}{n}:{joint}" for n in range(lowest, MAX_CYCLIC_ORDER + 1)]
    return labels


@dataclass(frozen=True)
class CandidateScore:
    """Score test of one candidate at the current model.

    Attributes:
        label: effect label.
        k: identifiable directions of its signature (rank after projection).
        F, p: score-test statistic and p-value.
        bic_gain: ``-(drop - k log m)``, the ranking key (lower is better).
        signature: ``(m, size)`` its Jacobian columns projected off the model's.
        fitted: ``(m,)`` the correction it would make to the residuals.
    """

    label: str
    k: int
    F: float
    p: float
    bic_gain: float
    signature: Tensor
    fitted: Tensor


@dataclass
class Scores:
    """All candidates' score tests at one step.

    Attributes:
        scored: the candidates with an identifiable signature, in pool order.
        ranked: the same, best first (significant ones first, then by BIC gain).
        m, n_current: residual count and the current model's parameter count.
        threshold: Bonferroni level ``alpha / (len(scored) + screened)``.
        unobservable: candidates without any signature in this data.
        equivalent: ambiguity entries of candidates that a frame or effect absorbs.
        R: ``(n + 1, n + 1)`` factor of ``[J r]`` (``R^T R = [J r]^T [J r]``) of the
            current model and every candidate (``blocks``): the current model's
            columns by QR, the candidates' completed from the Gram
            (:func:`.blocked.cell_factors`), for the Gauss–Newton start of a refit.
        blocked, margin, carry: the cell Grams of the blocked hold-out, the practical
            margin [mm] and each candidate's blocked gain [mm] (empty without blocks).
        carry_se: each candidate's jackknife standard error of that gain over the
            blocks [mm] (:meth:`.blocked.Blocked.gain_se_mm`).
        near: the Jacobian's rows, where the chosen candidate's refit steps from
            (:mod:`hybrid_pk.calibration.chord`; released by :func:`try_candidate`).
        pair: where no candidate carries over alone, the pair that does
            (:func:`.pair_entry.carrying_pair`): its lead carries over with it.
    """

    scored: list[CandidateScore]
    m: int
    n_current: int
    threshold: float = math.nan
    unobservable: list[str] = field(default_factory=list)
    equivalent: list[dict] = field(default_factory=list)
    R: Tensor | None = None
    blocks: tuple = ()
    blocked: Blocked | None = None
    margin: float = 0.0
    carry: dict[str, float] = field(default_factory=dict)
    carry_se: dict[str, float] = field(default_factory=dict)
    near: Linearisation | None = None
    pair: dict | None = None

    @property
    def ranked(self) -> list[CandidateScore]:
        """Significant candidates that carry over first (by BIC gain), then the rest."""
        return sorted(self.scored, key=lambda sc: (not self.eligible(sc), sc.bic_gain))

    def eligible(self, sc: CandidateScore) -> bool:
        """Significant and, with blocks, gaining what :meth:`carries` asks."""
        return sc.p < self.threshold and self.carries(sc.label)

    def carries(self, label: str) -> bool:
        """Whether a candidate's blocked gain reaches the practical margin and its own
        standard error over the blocks (one-standard-error rule of cross-validation:
        a cause enters on a gain the blocks agree on; it stays while it gains the
        margin, :func:`.carryover.weakest`). True without blocks."""
        gain = self.carry.get(label)
        if self.pair is not None and label == self.pair["lead"]:
            return True  # it carries over with its partner (:mod:`.pair_entry`)
        return gain is None or gain >= max(self.margin, self.carry_se.get(label, 0.0))

    @property
    def signatures(self) -> dict[str, Tensor]:
        """Projected signature of every scored candidate, in pool order."""
        return {s.label: s.signature for s in self.scored}


def score_candidates(
    model: ExtendedModel,
    res: FitResult,
    pool: list[str],
    split: Split,
    alpha: float,
    name_equivalents: bool,
    progress: Callable[[str], None] | None = None,
    screened: int = 0,
    carry: Carry | None = None,
) -> Scores:
    """Score every candidate of ``pool`` against ``model`` from one Jacobian.

    ``screened``: candidates set aside before scoring (:func:`.screen_cyclic`); they
    count in the Bonferroni level. ``carry``: the blocks and margin of the blocked
    hold-out; each scored candidate's blocked gain goes into ``Scores.carry``.

    Candidates with no signature are ``unobservable``; those inside the current
    columns are dropped (and, with ``name_equivalents``, reported as equivalent to
    the frame or effect that explains them).
    """
    robot = model.robot
    trial = with_effects(model, [make_effect(robot, c) for c in pool])
    folds = None if carry is None else carry.folds
    problem, blocks, R, blocked = linearise(
        trial, res, split, folds, progress, candidates=len(pool)
    )
    # R^T R = [J r]^T [J r]: R's columns stand for J's and r's (same norms, inner
    # products and projections) with n + 1 rows instead of m.
    J, r = R[:, :-1], R[:, -1]
    current_blocks = blocks[: len(blocks) - len(pool)]
    n_cur = sum(b.size for b in current_blocks)
    J_cur, J_pool = J[:, :n_cur], J[:, n_cur:]
    Q, _ = torch.linalg.qr(J_cur)
    ssr = float(r @ r)
    m = problem.n_residuals
    out = Scores(scored=[], m=m, n_current=n_cur, R=R, blocks=blocks)
    out.near = Linearisation.kept_by(problem, blocks)
    start = 0
    for b, label in zip(blocks[len(blocks) - len(pool) :], pool, strict=True):
        Jc = J_pool[:, start : start + b.size]
        start += b.size
        Jp = projector_residual(Jc, Q)
        norm_c = float(Jc.norm() ** 2)
        frac = float(Jp.norm() ** 2) / max(norm_c, 1e-300)
        if norm_c < 1e-20:
            out.unobservable.append(label)  # no signature at all in this data
            continue
        if frac < EQUIVALENCE_FRACTION:
            if name_equivalents:
                other = frame_of_equivalence(Jc, J_cur, current_blocks)
                out.equivalent.append(equivalent_to_frame(label, other, frac))
            continue
        score = _score_test(label, Jc, Jp, r, ssr, m, n_cur)
        if score is not None:
            out.scored.append(score)
    if out.scored:
        out.threshold = alpha / (len(out.scored) + screened)
    if blocked is not None:
        out.blocked, out.margin = blocked, carry.margin(res)
        current = [e.label for e in model.effects]
        base = blocked.of(current)
        withs = blocked.each(current, [sc.label for sc in out.scored])
        for sc, with_it in zip(out.scored, withs, strict=True):
            out.carry[sc.label] = blocked.gain_mm(base, with_it)
            out.carry_se[sc.label] = blocked.gain_se_mm(base, with_it)
        out.pair = carrying_pair(out, current, base)
    return out


def _score_test(
    label: str, Jc: Tensor, Jp: Tensor, r: Tensor, ssr: float, m: int, n_cur: int
) -> CandidateScore | None:
    """F-test of adding the projected signature ``Jp``; None when it has no rank."""
    # Rank-revealing projection: directions of the candidate that the model already
    # explains (e.g. a misalignment about a neighbouring parallel axis after that
    # joint's offset was chosen) carry no information.
    U, S, _ = torch.linalg.svd(Jp, full_matrices=False)
    keep = S > RANK_TOLERANCE * float(Jc.norm())
    k = int(keep.sum())
    if k == 0:
        return None
    Ur = U[:, keep]
    fitted = Ur @ (Ur.T @ r)  # the correction this candidate would make
    drop = min(float(fitted @ fitted), ssr)
    F = (drop / k) / max((ssr - drop) / max(m - n_cur - k, 1), 1e-300)
    p = f_sf(F, k, max(m - n_cur - k, 1))
    # Rank significant candidates by BIC gain: among equally certain ones (p-values
    # underflow to 0) the one with fewer parameters wins ties.
    return CandidateScore(label, k, F, p, -(drop - k * math.log(m)), Jp, fitted)


def gauss_newton_start(scores: Scores, label: str) -> dict[str, Tensor]:
    """Scaled steps (by block label) of the current model's blocks and candidate
    ``label`` that minimise the linearised residual: where its refit starts."""
    start, cols, labels = 0, [], []
    for b in scores.blocks:  # the current model's blocks first, then the candidates'
        if start < scores.n_current or b.label == label:
            cols.append(torch.arange(start, start + b.size))
            labels.append((b.label, b.size))
        start += b.size
    idx = torch.cat(cols)
    J, r = scores.R[:, idx], scores.R[:, -1:]
    norms = J.norm(dim=0)
    unit = torch.where(norms > 0, norms, torch.ones_like(norms))
    # Directions weaker than RANK_TOLERANCE of the strongest (columns at unit norm) stay
    # where they are: the score test counts none of them, and the factor (its candidate
    # columns completed from the Gram) resolves them only to ~1e-5.
    fit = torch.linalg.lstsq(J / unit, r, rcond=RANK_TOLERANCE, driver="gelsd")
    step = -fit.solution[:, 0] / unit
    out, s0 = {}, 0
    for lbl, size in labels:
        out[lbl] = step[s0 : s0 + size]
        s0 += size
    return out


def try_candidate(
    model: ExtendedModel,
    res: FitResult,
    score: CandidateScore,
    scores: Scores,
    split: Split,
    progress: Callable[[str], None] | None = None,
) -> tuple[ExtendedModel, FitResult, dict]:
    """Refit ``model`` with the candidate; F-test, BIC and hold-out decide.

    The refit starts at the Gauss–Newton step of the score's linearisation (unless
    that start is worse than the current values). Returns the refitted model, its
    fit and the step record (``accepted`` says whether the candidate stays).
    """
    label, k, m = score.label, score.k, scores.m
    step = {
        "candidate": label,
        "score_F": score.F,
        "score_p": score.p,
        "threshold": scores.threshold,
    }
    if scores.blocked is not None:
        step.update(carry_record(scores, label))
    new = with_effects(model, [make_effect(model.robot, label)])
    # (a robust fit's cost is its IRLS sum; its F-test compares robust costs)
    ssr_old = res.cost if res.cost is not None and res.robust is None else _ssr(model, split, res)
    sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
    start = with_effects(new)
    shift_parameters(start, gauss_newton_start(scores, label), split.position_only)
    r_start = weighted_residual(start, split.train, split.cond_fit, res)
    start_cost = float(r_start @ r_start) if res.robust is None else _ssr(start, split, res)
    if start_cost < ssr_old:
        # The start is (linearised) optimal under the current noise weights: its
        # residuals give the noise levels the refit's second pass would start from.
        new = start
        n_params = scores.n_current + sum(b.size for b in scores.blocks if b.label == label)
        noise = reestimated_noise(
            r_start, split.train.n, n_params, sigmas, position_only=split.position_only
        )
        sigmas = (noise[0], None if split.position_only else noise[1])
        if scores.near is not None and res.robust is None:  # the refit's first residual
            scores.near.start = (r_start, (res.sigma_pos_mm, res.sigma_rot_rad or 1.0))
    new_res = fit(
        new, split.train, cond=split.cond_fit, initial_sigma=sigmas, progress=progress,
        near=scores.near, report_frames=False, **res.settings(),
    )  # fmt: skip
    scores.near = None  # its rows (~the whole Jacobian) are not needed again
    # F-test and BIC of the refit, both models' residuals under the same weights.
    ssr_new = _ssr(new, split, res)
    dof_new = max(m - new_res.n_params, 1)
    F_fit = ((ssr_old - ssr_new) / k) / max(ssr_new / dof_new, 1e-300)
    p_fit = f_sf(F_fit, k, dof_new) if F_fit > 0 else 1.0
    d_bic = m * math.log(max(ssr_new, 1e-300) / max(ssr_old, 1e-300)) + k * math.log(m)
    # Same weights on both sides (the refit's noise estimate is smaller).
    current_hold = holdout_score(model, split.test, split.cond_hold, res)
    new_hold = holdout_score(new, split.test, split.cond_hold, res)
    step.update(
        {
            "fit_F": F_fit,
            "fit_p": p_fit,
            "delta_bic": d_bic,
            "holdout_score_before": current_hold,
            "holdout_score_after": new_hold,
        }
    )
    step["accepted"] = p_fit < scores.threshold and d_bic < 0 and new_hold < current_hold
    step["accepted"] = step["accepted"] and scores.carries(label)
    if not step["accepted"]:
        step["why"] = "refit not significant, BIC not lower, or hold-out not better"
    else:
        release_shared()  # the model moves on: no question is asked at its point again
    return new, new_res, step


def carry_record(scores: Scores, label: str) -> dict:
    """A step record's blocked gain of candidate ``label``, its standard error and the
    margin."""
    out = {
        "blocked_gain_mm": scores.carry[label],
        "blocked_gain_se_mm": scores.carry_se.get(label, 0.0),
        "min_gain_mm": scores.margin,
    }
    if scores.pair is not None and scores.pair["lead"] == label:
        out["entered_with"] = dict(scores.pair)  # its partner, their gain and its se
    return out


def _ssr(model: ExtendedModel, split: Split, res: FitResult) -> float:
    return weighted_ssr(model, split.train, split.cond_fit, res)

"""What a campaign cannot show: the smallest effect of each candidate the diagnosis
would have detected (``detectable`` of the diagnosis JSON).

Linearised at the final model: a candidate's Jacobian columns, projected off the
columns already in the model (frames included) and divided by the noise estimate
(the score test of :mod:`.selection`), give its information ``G``. A true value
``theta`` makes the score test's F statistic noncentral with ``lambda = theta^T G
theta``; the test at the step's level (``alpha`` over the candidates, Bonferroni)
detects it with 80 % power once ``lambda`` reaches ``lambda_80`` (noncentral F). The
smallest such ``theta`` along the candidate's worst identifiable direction is
``sqrt(lambda_80 / g_min)`` (``g_min`` the smallest eigenvalue of ``G``): any effect
of that size or more, whatever its direction, is detected with >= 80 % probability.
``mm_rms`` is the rms change of the measured point such an effect makes over the
fit rows (plain position Jacobian, before the frames absorb any of it).

Significance is not enough to be named: a cause must also gain the practical margin
``m`` on the blocked hold-out (:mod:`.carryover`). Along the same direction, an effect
whose projected signature adds ``s^2`` per row to the noise-normalised mean square
(``d`` per row from the noise: 3 position coordinates, 6 with rotation) raises the RMS
error from ``sigma sqrt(d)`` to ``sigma sqrt(d + s^2)``; it gains the margin once
``s^2 >= (sqrt(d) + m / sigma)^2 - d`` (linearised, in sample). The limit is the larger
of the two sizes, and ``set_by`` says which: ``"power"`` (the F-test) or ``"margin"``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.blocked import position_channel, whole_campaign
from hybrid_pk.calibration.diagnosis.carryover import Carry
from hybrid_pk.calibration.diagnosis.cyclic_screen import screen_cyclic
from hybrid_pk.calibration.diagnosis.selection import RANK_TOLERANCE, Scores, score_candidates
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.variants import with_effects
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.distributions import chi2_isf, f_isf, ncf_sf, ncx2_sf
from hybrid_pk.effects import ExtendedModel, entry_label, make_effect
from hybrid_pk.effects.joint import CYCLIC_PREFIX
from hybrid_pk.effects.limits import effect_limit
from hybrid_pk.errors import HybridPKError

__all__ = [
    "beyond_credible",
    "check_determined",
    "detectable_json",
    "detection_limits",
    "family_of",
    "frame_parameters",
    "little_power",
    "noncentrality",
    "nothing_above",
]


def noncentrality(alpha: float, d1: int, d2: int, power: float | None = None) -> float:
    """``lambda`` at which the F-test of level ``alpha`` with ``(d1, d2)`` degrees of
    freedom rejects with probability ``power`` (noncentral F; chi-squared for large
    ``d2``, where the two agree)."""
    from scipy import optimize  # on first use

    power = diagnosis_tuning().power if power is None else power
    if d2 > 1e5:  # F(d1, inf) = chi2(d1) / d1: the noncentral chi-squared
        crit = chi2_isf(alpha, d1)

        def miss(lam: float) -> float:
            return ncx2_sf(crit, d1, lam) - power
    else:
        crit = f_isf(alpha, d1, d2)

        def miss(lam: float) -> float:
            return ncf_sf(crit, d1, d2, lam) - power

    hi = 1.0
    while miss(hi) < 0:
        hi *= 2
    return float(optimize.brentq(miss, 0.0, hi, xtol=1e-6 * hi))


def family_of(label: str) -> str:
    """The family of a candidate label: its kind, every cyclic order as one."""
    kind = label.split(":")[0]
    return CYCLIC_PREFIX.rstrip("_") if kind.startswith(CYCLIC_PREFIX) else kind


def detection_limits(
    model: ExtendedModel,
    res: FitResult,
    pool: list[str],
    split: Split,
    alpha: float,
    progress: Callable[[str], None] | None = None,
    carry: Carry | None = None,
) -> tuple[list[dict], Scores | None]:
    """The detection limit of every candidate of ``pool`` not in the model, and the
    scoring it comes from (None without candidates; its factor serves
    :func:`.stand_ins.group_stand_ins`).

    ``carry``: the search's blocked hold-out; its blocks screen the cyclic orders as
    the search does (without it every order is scored).

    Returns one entry per candidate with an identifiable signature: ``effect``,
    ``joint``, ``family``, ``value`` (the smallest detectable size, in ``unit``),
    ``mm_rms`` (the rms motion of the point it makes [mm]), ``alpha`` (the level per
    candidate) and ``power``.
    """
    chosen = {e.label for e in model.effects}
    pool = [c for c in pool if c not in chosen]
    if not pool:
        return [], None
    # as the search does: the best cyclic orders per joint are scored, the others count
    folds, margin = (None, 0.0) if carry is None else (carry.folds, carry.margin(res))
    pool, screened = screen_cyclic(model, split, pool, res.weights, folds, margin)
    # gains judged on position (pose data): the margin needs the fit's position Gram
    on_position = folds is not None and position_channel() and not split.position_only
    whole = Carry(whole_campaign(split.train.n)) if on_position else None
    scores = score_candidates(
        model, res, pool, split, alpha, False, progress=progress, screened=screened, carry=whole
    )
    scores.near = None  # no refit steps from this scoring: its rows are not needed
    if not scores.scored:
        return [], scores
    level = scores.threshold
    columns = _position_columns(model, [sc.label for sc in scores.scored], split)
    # the margin binds only where blocks decide: its lambda along any direction
    per_row = 3 if split.position_only or on_position else 6
    margin_used = margin if folds is not None else 0.0
    carry_lam = _margin_noncentrality(margin_used, res, per_row, split.train.n)
    position_grams = _position_signature_grams(scores) if on_position else None
    out = []
    for sc in scores.scored:
        _, S, Vt = torch.linalg.svd(sc.signature, full_matrices=False)
        k = int((S > RANK_TOLERANCE * float(S[0])).sum())
        d2 = max(scores.m - scores.n_current - sc.k, 1)
        lam = noncentrality(level, sc.k, d2)
        theta = math.sqrt(lam) / float(S[k - 1]) * Vt[k - 1]  # worst direction, scaled
        if position_grams is None:  # the margin along the same signature
            by_margin = math.sqrt(carry_lam) / float(S[k - 1]) * Vt[k - 1]
        else:
            by_margin = _margin_theta(position_grams[sc.label], Vt[:k], S[0], carry_lam)
            if by_margin is None:
                continue  # moves the point in no direction it can be fitted along
        set_by = "power" if float(theta.norm()) >= float(by_margin.norm()) else "margin"
        theta = theta if set_by == "power" else by_margin
        effect = make_effect(model.robot, sc.label)
        J_pos, n_sub = columns[sc.label]
        moved = float((J_pos @ theta).norm()) / math.sqrt(n_sub)  # rms point motion [mm]
        name, _, joint = sc.label.partition(":")
        out.append(
            {
                "effect": name,
                "joint": joint or None,
                "family": family_of(sc.label),
                "value": float(theta.norm()) * effect.scale,
                "unit": effect.unit,
                "mm_rms": moved,
                "alpha": level,
                "power": diagnosis_tuning().power,
                "set_by": set_by,
            }
        )
    return out, scores


def _margin_noncentrality(margin: float, res: FitResult, per_row: int, rows: int) -> float:
    """The squared norm of the projected, noise-normalised signature (summed over the
    fit rows' ``per_row`` judged components, as ``lambda``) at which an effect gains
    ``margin`` [mm] (module)."""
    root = math.sqrt(per_row)
    return max((root + margin / res.sigma_pos_mm) ** 2 - per_row, 0.0) * rows


def _position_signature_grams(scores) -> dict[str, Tensor]:
    """Per scored candidate the Gram ``(size, size)`` of the position part of its
    signature: its position columns with what the current model's columns can absorb
    of them *on the position rows* taken out. Projected in the fit's metric instead
    (orientations included), an effect whose orientation signature the frames absorb
    would seem to move positions through them, at the fit's rotation noise level; but
    the effect's own orientation signature raises that level when it is in the rows,
    and the gain never came (sweep seed 101010: a wrist gear ratio twice its limit,
    4 mm off its axis, gained 0.0006 mm against a 0.005 mm margin). On positions alone
    the current model takes the most it can, so the limit holds whatever weight the
    orientations get."""
    Gp = scores.blocked.pos[0][:-1, :-1]
    n = scores.n_current
    out, start = {}, 0
    scored = {sc.label for sc in scores.scored}
    for b in scores.blocks:  # the current model's blocks (the first n columns), then the pool's
        c = slice(start, start + b.size)
        start += b.size
        if c.start < n or b.label not in scored:
            continue
        B = torch.linalg.lstsq(Gp[:n, :n], Gp[:n, c], driver="gelsd").solution
        out[b.label] = Gp[c, c] - Gp[c, :n] @ B
    return out


def _margin_theta(Gp: Tensor, V: Tensor, s_max: Tensor, lam: float) -> Tensor | None:
    """The scaled effect of the smallest size that gains the margin (``lam``) in
    position along its worst direction within the fitted directions ``V (k, size)``;
    None when some fitted direction moves the point not at all."""
    g, U = torch.linalg.eigh(V @ Gp @ V.T)
    if float(g[0]) <= (RANK_TOLERANCE * float(s_max)) ** 2:
        return None
    return math.sqrt(lam / float(g[0])) * (U[:, 0] @ V)


# Rows of the plain position Jacobian used for the mm at the measured point (an even
# subset: an rms over the workspace, not a sum); an rms over 400 rows has a relative
# standard error of 1/sqrt(2 x 400) = 3.5 %, fine for a limit stated at 80 % power.
MM_ROWS = 400


def _position_columns(model: ExtendedModel, labels: list[str], split: Split) -> dict:
    """Each candidate's position columns [mm per scaled unit] on an even subset of the
    fit rows (the plain motion of the point, no noise weights)."""
    step = max(1, -(-split.train.n // MM_ROWS))
    rows = torch.arange(0, split.train.n, step)
    sub, cond = split.train.subset(rows), split.cond_fit.subset(rows)
    trial = with_effects(model, [make_effect(model.robot, c) for c in labels])
    blocks = param_blocks(trial, labels, split.position_only)
    _, J = Problem(trial, sub, cond, blocks, 1.0, 1e-3).jacobian(
        torch.zeros(sum(b.size for b in blocks), dtype=torch.float64)
    )
    J = J.detach()
    out, start = {}, 0
    for b in blocks:
        out[b.label] = (J[: 3 * sub.n, start : start + b.size], sub.n)
        start += b.size
    return out


def nothing_above(detectable: list[dict], limit: int = 6, blind: list[str] = ()) -> str:
    """``nothing above: <family> <limit> <unit> at <joint> (<mm>), ...; below that these data
    cannot tell``: per family its largest limit (true of every joint but those in
    ``blind``, whose limit exceeds any credible size: they are named after it), the
    families whose limit moves the point the most first; ``(<mm>, margin)`` where the
    practical margin, not the F-test's power, sets the limit."""
    if not detectable:
        return "nothing the data could test (no candidate has a signature in them)"
    worst: dict[str, dict] = {}
    missed = []
    for d in detectable:  # the largest limit of a family holds for all its joints
        if entry_label(d) in blind:
            missed.append(f"{d['family']} at {d['joint']}" if d["joint"] else d["family"])
            continue
        w = worst.get(d["family"])
        if w is None or d["value"] > w["value"]:
            worst[d["family"]] = d
    ranked = sorted(worst.values(), key=lambda d: -d["mm_rms"])
    parts = []
    for d in ranked[:limit]:
        at = f" at {d['joint']}" if d["joint"] else ""
        by = ", margin" if d.get("set_by") == "margin" else ""
        parts.append(f"{d['family']} {d['value']:.2g} {d['unit']}{at} ({d['mm_rms']:.2g} mm{by})")
    more = f", {len(ranked) - limit} more families" if len(ranked) > limit else ""
    shown = ", ".join(missed[:limit]) + (
        f" and {len(missed) - limit} more" if len(missed) > limit else ""
    )
    if not parts:  # every candidate blind: no empty "nothing above" list
        return f"these data would miss every candidate at any credible size: {shown}"
    text = f"nothing above: {', '.join(parts)}{more}; below that these data cannot tell"
    return text + (f"; missed at any credible size: {shown}" if missed else "")


def beyond_credible(model: ExtendedModel, detectable: list[dict]) -> list[str]:
    """Labels of the candidates whose detection limit exceeds the largest credible size
    of their effect (:func:`~hybrid_pk.effects.limits.effect_limit`): this campaign
    would miss them at any physical size."""
    out = []
    for d in detectable:
        label = entry_label(d)
        limit = effect_limit(make_effect(model.robot, label), model.robot)
        if limit is not None and d["value"] > limit:
            out.append(label)
    return out


def detectable_json(
    model: ExtendedModel, detectable: list[dict], sigma_pos_mm: float, min_gain_mm: float
) -> dict:
    """The ``detectable`` field of the diagnosis JSON (``min_gain_mm``: the practical
    margin the limits set by ``"margin"`` reach)."""
    blind = beyond_credible(model, detectable)
    return {
        "power": diagnosis_tuning().power,
        "min_gain_mm": min_gain_mm,
        "limits": detectable,
        "beyond_credible": blind,
        "summary": nothing_above(detectable, blind=blind),
        "little_power": little_power(detectable, sigma_pos_mm, blind),
    }


def little_power(detectable: list[dict], sigma_pos_mm: float, blind: list[str]) -> str | None:
    """A sentence when the campaign has little power: the typical (median) candidate
    must move the measured point by more than the position noise itself to be detected,
    i.e. an error as large as the noise can hide in these data. None otherwise."""
    if not detectable:
        return None
    typical = float(torch.tensor([d["mm_rms"] for d in detectable]).median())
    if typical <= sigma_pos_mm:
        return None
    also = f"; {len(blind)} would be missed at any credible size" if blind else ""
    return (
        f"little power: a typical candidate effect must move the measured point by "
        f"{typical:.2g} mm (rms) to be detected, {typical / sigma_pos_mm:.2g} times the "
        f"position noise{also}; a cause below that cannot be ruled out: measure more poses"
    )


def check_determined(split: Split, n_frame: int) -> None:
    """Refuse a campaign whose fit rows cannot determine the frames plus one effect
    and leave one residual for the noise (the F-test's denominator).

    Raises:
        HybridPKError: naming rows, residuals and parameters.
    """
    n_fit, n_hold = split.train.n, split.test.n
    per_row = 3 if split.position_only else 6
    residuals = per_row * n_fit
    needed = n_frame + 1 + 1
    if n_fit >= 3 and residuals >= needed:
        return
    raise HybridPKError(
        f"too little data: {n_fit + n_hold} rows ({n_fit} fit, {n_hold} hold-out) give "
        f"{residuals} fit residuals, fewer than the {n_frame} frame parameters plus one "
        f"effect and one for the noise ({needed}; registration also needs 3 fit rows): "
        "measure more poses"
    )


def frame_parameters(model: ExtendedModel, split: Split, priors) -> int:
    """Frame parameters the diagnosis fits (known frames' components left out)."""
    fixed = set() if priors is None else set(priors.fixed_labels())
    blocks = param_blocks(model, None, split.position_only)
    return sum(b.size for b in blocks if b.label not in fixed)

"""Diagnosis: what the nominal model gets wrong, and which physical effects explain it.

1. Split rows into fit and hold-out sets; fit base and tool frames to the nominal
   robot (the ``nominal`` errors of the report are on the hold-out rows).
2. Forward selection. At the current model, one Jacobian of *every* candidate effect
   gives each candidate's score: the drop of the (noise-normalised) sum of squares
   it would bring once projected off what the model already explains (a Lagrange
   multiplier / score test, linear in the candidates). The best candidate is added
   and the model refitted; it stays only if the refit passes an F-test at
   ``alpha / n_candidates`` (Bonferroni over the candidates tried), lowers BIC and
   lowers the hold-out error. Then the next step.
3. Candidates whose signature lies entirely in what the frames (or the chosen
   effects) already explain cannot be identified from any data of this kind: they
   are reported as ``ambiguous`` with the frame they are equivalent to. Chosen causes
   whose signature is nearly collinear with an unchosen candidate's, or whose
   estimates correlate strongly, are reported as ambiguous too.
4. Each cause's gain is measured by leaving it out (refit without it) on the
   hold-out rows. What remains is tested for structure: residuals of neighbouring
   configurations (in joint space) correlate when a smooth error is left unexplained.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.calibration.fit import (
    FitResult,
    Problem,
    _blocks,
    fit,
    initialise_frames,
    model_errors,
)
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import (
    EFFECTS,
    Conditions,
    Effect,
    ExtendedModel,
    Gravity,
    conditions_from_data,
    effect_joint_names,
    make_effect,
)
from hybrid_pk.evaluation.metrics import error_stats
from hybrid_pk.robot import Robot

__all__ = ["Cause", "Diagnosis", "candidate_labels", "diagnose"]

# A candidate whose signature keeps less than this fraction of its norm once projected
# off the current model's columns is taken as equivalent to them (unidentifiable).
EQUIVALENCE_FRACTION = 1e-8
# Signatures more alike than this (|cosine| of the projected columns) are ambiguous.
AMBIGUITY_COSINE = 0.98
# Singular values of a candidate's projected signature below this fraction of its own
# norm are directions the current model already explains.
RANK_TOLERANCE = 1e-4
# A candidate whose refit fails is set aside; the search stops after this many in a row.
MAX_REJECTED_IN_A_ROW = 2
# Estimates correlated beyond this are reported as an ambiguous group.
AMBIGUITY_CORRELATION = 0.95
# Temperature must vary by at least this much [K] for thermal expansion to be tested.
MIN_TEMPERATURE_SPREAD = 0.5


@dataclass
class Cause:
    """One statistically supported error cause (contract section 4, ``causes``)."""

    effect: str
    joint: str | None
    value: float | list[float]
    unit: str
    std: float | list[float]
    position_gain_mm: float
    orientation_gain_deg: float | None
    evidence: str
    components: list[float] | None = None

    def to_json(self) -> dict:
        out = {
            "effect": self.effect,
            "joint": self.joint,
            "value": self.value,
            "unit": self.unit,
            "std": self.std,
            "position_gain_mm": self.position_gain_mm,
            "orientation_gain_deg": self.orientation_gain_deg,
            "evidence": self.evidence,
        }
        if self.joint is None:
            del out["joint"]
        if self.components is not None:
            out["components"] = self.components
        return out


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`; ``to_json()`` is the contract's diagnosis JSON."""

    robot: str
    n_samples: int
    n_holdout: int
    nominal: dict
    extended: dict
    causes: list[Cause]
    ambiguous: list[dict]
    unexplained: dict
    identifiability: dict
    model: ExtendedModel
    nominal_model: ExtendedModel
    fit_rows: Tensor
    holdout_rows: Tensor
    steps: list[dict] = field(default_factory=list)
    warnings: list[dict] = field(default_factory=list)

    def to_json(self) -> dict:
        return {
            "robot": self.robot,
            "n_samples": self.n_samples,
            "n_holdout": self.n_holdout,
            "nominal": self.nominal,
            "causes": [c.to_json() for c in self.causes],
            "ambiguous": self.ambiguous,
            "extended": self.extended,
            "unexplained": self.unexplained,
            "identifiability": self.identifiability,
            "selection": self.steps,
            "warnings": self.warnings,
            "gravity": _gravity_json(self.model),
        }


def _gravity_json(model: ExtendedModel) -> dict:
    """The mounting the statics used, with gravity in the root frame of each base set."""
    out = model.gravity.to_dict()
    with torch.no_grad():
        if model.gravity.levelled:
            R = model.base.matrix()[:, :3, :3]
            g = torch.tensor(model.gravity.vector, dtype=R.dtype)
            out["root_frame"] = [(R[k].T @ g).tolist() for k in range(R.shape[0])]
        else:
            out["root_frame"] = [list(model.gravity.vector)]
    return out


def candidate_labels(robot: Robot, data: MeasuredData) -> list[str]:
    """Every effect of the vocabulary that this data could reveal."""
    labels = []
    for kind, cls in EFFECTS.items():
        if not cls.per_joint:
            continue
        for i, joint in enumerate(effect_joint_names(robot, cls)):
            if cls.stage == "geometry" and i == 0:
                continue  # origin 0 is the base frame's business
            if kind in ("gear_ratio", "joint_eccentricity", "backlash", "joint_compliance") and (
                robot.joint_types[i] == "prismatic"
            ):
                continue
            if kind == "column_bending" and robot.chain_joint_types[i] != "prismatic":
                continue  # a column's bending grows with its extension
            labels.append(f"{kind}:{joint}")
    if data.temperature is not None:
        spread = float(data.temperature.max() - data.temperature.min())
        if spread >= MIN_TEMPERATURE_SPREAD:
            labels.append("thermal_expansion")
    return labels


def _split(n: int, holdout: float, seed: int) -> tuple[Tensor, Tensor]:
    if not 0 < holdout < 1:
        raise ValueError(f"--holdout must lie in (0, 1), got {holdout}")
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    n_hold = max(1, round(holdout * n))
    return perm[n_hold:].sort().values, perm[:n_hold].sort().values


def _stats_json(pos: Tensor, ori: Tensor | None) -> dict:
    return {
        "position_mm": error_stats(pos).to_dict(),
        "orientation_deg": None if ori is None else error_stats(ori).to_dict(),
    }


def _clone_model(model: ExtendedModel, extra: list[Effect] = ()) -> ExtendedModel:
    """Same robot, frames and effect values, plus ``extra`` effects."""
    robot = model.robot
    effects = [make_effect(robot, e.label, e.value.detach().clone()) for e in model.effects]
    out = ExtendedModel(
        robot, effects + list(extra), frame_sets=model.base.sets, gravity=model.gravity
    )
    out.base.reset_to(model.base.matrix().detach())
    out.tool.reset_to(model.tool.matrix().detach())
    return out


def _without(model: ExtendedModel, label: str) -> ExtendedModel:
    out = _clone_model(model)
    out.effects = torch.nn.ModuleList([e for e in out.effects if e.label != label])
    return out


def _refit_without(
    model: ExtendedModel, label: str, data: MeasuredData, cond: Conditions, res: FitResult
) -> ExtendedModel:
    """``model`` without effect ``label``, refitted under ``res``'s noise weights."""
    reduced = _without(model, label)
    fit(
        reduced,
        data,
        cond=cond,
        sigma_pos_mm=res.sigma_pos_mm,
        sigma_rot_rad=res.sigma_rot_rad,
        covariance=False,
        max_iter=15,  # warm start from the full model: a few steps re-balance the rest
    )
    return reduced


def _projector_residual(Jc: Tensor, Q: Tensor) -> Tensor:
    return Jc - Q @ (Q.T @ Jc)


def _frame_of_equivalence(Jc: Tensor, J_cur: Tensor, blocks) -> str:
    """Which of base/tool frame (or which effect) explains a candidate's signature."""
    start, groups = 0, {}
    for b in blocks:
        key = b.label.split(".")[0]
        groups.setdefault(key, []).append(slice(start, start + b.size))
        start += b.size
    best, best_frac = "the fitted frames", math.inf
    for key, slices in groups.items():
        cols = torch.cat([J_cur[:, s] for s in slices], 1)
        Q, _ = torch.linalg.qr(cols)
        frac = float(_projector_residual(Jc, Q).norm() ** 2 / Jc.norm().clamp_min(1e-300) ** 2)
        if frac < best_frac:
            best, best_frac = key, frac
    return best


def _structured(residual: Tensor, q: Tensor, lower: Tensor, upper: Tensor) -> tuple[bool, float]:
    """Do neighbouring configurations share their residuals? (smooth leftover error)"""
    n = residual.shape[0]
    if n < 20:
        return False, 0.0
    span = torch.where(torch.isfinite(upper - lower), upper - lower, 2 * math.pi)
    x = (q - lower.where(torch.isfinite(lower), -math.pi)) / span
    d = torch.cdist(x, x)
    d.fill_diagonal_(math.inf)
    nn_idx = d.argmin(1)
    a = residual.reshape(n, -1)
    a = a - a.mean(0)
    b = a[nn_idx]
    corr = float((a * b).sum() / (a.norm() * b.norm()).clamp_min(1e-300))
    # Under no structure the correlation is ~N(0, 1/(n*k)); 4 sigma is "structured".
    threshold = 4.0 / math.sqrt(a.numel())
    return corr > max(threshold, 0.1), corr


def _f_sf(F: float, d1: int, d2: int) -> float:
    """Survival function of the F distribution (scipy imported on first use: slow)."""
    from scipy import stats

    return float(stats.f.sf(F, d1, d2))


def diagnose(
    robot: Robot,
    data: MeasuredData,
    *,
    holdout: float = 0.2,
    seed: int = 0,
    candidates: list[str] | None = None,
    alpha: float = 1e-3,
    max_causes: int = 8,
    frames_per_file: bool = False,
    progress: Callable[[str], None] | None = None,
    gravity: Gravity | None = None,
) -> Diagnosis:
    """Name the physical causes of the nominal model's errors on ``data``.

    Args:
        robot: nominal robot (not modified).
        data: measured rows, in acquisition order (backlash reads the order).
        holdout: fraction of rows kept out of every fit and used to compare models.
        seed: seed of the hold-out split.
        candidates: effect labels to consider (default :func:`candidate_labels`).
        alpha: family-wise false-positive rate of the F-tests per step.
        max_causes: stop after this many causes.
        frames_per_file: give each input file its own base and tool frames.
        progress: called with a short text at each stage.
        gravity: the mounting (root-frame vector or levelled tracker); default upright.
    """
    say = progress or (lambda _msg: None)
    robot.requires_grad_(False)
    cond_all = conditions_from_data(data, frames_per_file)
    fit_rows, hold_rows = _split(data.n, holdout, seed)
    train, test = data.subset(fit_rows), data.subset(hold_rows)
    cond_fit, cond_hold = cond_all.subset(fit_rows), cond_all.subset(hold_rows)
    position_only = data.quat is None

    say("fitting base and tool frames to the nominal model")
    model = ExtendedModel(
        robot, frame_sets=len(data.sources) if frames_per_file else 1, gravity=gravity
    )
    initialise_frames(model, train, cond_fit)
    res = fit(model, train, cond=cond_fit)
    nominal_model = _clone_model(model)
    pos0, ori0 = model_errors(model, test, cond_hold)
    nominal = _stats_json(pos0, ori0)

    pool = candidates if candidates is not None else candidate_labels(robot, data)
    pool = [
        c
        for c in pool
        if make_effect(robot, c).needs != "temperature" or data.temperature is not None
    ]
    ambiguous: list[dict] = []
    steps: list[dict] = []
    unobservable: list[str] = []
    first_step = True
    rejected_in_a_row = 0
    while pool and len(model.effects) < max_causes:
        say(f"scoring {len(pool)} candidate effects (step {len(steps) + 1})")
        trial = _clone_model(model, [make_effect(robot, c) for c in pool])
        blocks = _blocks(trial, None, position_only)
        sig_r = res.sigma_rot_rad or 1.0
        problem = Problem(trial, train, cond_fit, blocks, res.sigma_pos_mm, sig_r)
        r, J = problem.jacobian(torch.zeros_like(problem.x0))
        n_cur = sum(b.size for b in blocks[: len(blocks) - len(pool)])
        J_cur, J_pool = J[:, :n_cur], J[:, n_cur:]
        Q, _ = torch.linalg.qr(J_cur)
        ssr = float(r @ r)
        m = r.numel()
        scores, projected, start = [], {}, 0
        for b, label in zip(blocks[len(blocks) - len(pool) :], pool, strict=True):
            Jc = J_pool[:, start : start + b.size]
            start += b.size
            Jp = _projector_residual(Jc, Q)
            norm_c = float(Jc.norm() ** 2)
            frac = float(Jp.norm() ** 2) / max(norm_c, 1e-300)
            if norm_c < 1e-20:
                unobservable.append(label)  # no signature at all in this data
                continue
            if frac < EQUIVALENCE_FRACTION:
                if first_step:
                    other = _frame_of_equivalence(Jc, J_cur, blocks[: len(blocks) - len(pool)])
                    ambiguous.append(
                        {
                            "effects": [label, other],
                            "why": f"{label} moves the measured pose exactly as {other} "
                            f"does (signature {100 * (1 - frac):.4f} % inside it): "
                            "no data of this kind can separate them, the fitted frame "
                            "absorbs it",
                        }
                    )
                continue
            # Rank-revealing projection: directions of the candidate that the model
            # already explains (e.g. a misalignment about a neighbouring parallel axis
            # after that joint's offset was chosen) carry no information.
            U, S, _ = torch.linalg.svd(Jp, full_matrices=False)
            keep = S > RANK_TOLERANCE * float(Jc.norm())
            k = int(keep.sum())
            if k == 0:
                continue
            Ur = U[:, keep]
            fitted = Ur @ (Ur.T @ r)  # the correction this candidate would make
            drop = min(float(fitted @ fitted), ssr)
            F = (drop / k) / max((ssr - drop) / max(m - n_cur - k, 1), 1e-300)
            p = _f_sf(F, k, max(m - n_cur - k, 1))
            # Rank significant candidates by BIC gain: among equally certain ones
            # (p-values underflow to 0) the one with fewer parameters wins ties.
            scores.append((-(drop - k * math.log(m)), p, label, k, F))
            projected[label] = (Jp, fitted)
        first_step = False
        pool = [lbl for lbl in pool if lbl in projected]
        if not scores:
            break
        threshold = alpha / len(scores)
        scores.sort(key=lambda sc: (sc[1] >= threshold, sc[0]))
        _, p, label, k, F = scores[0]
        step = {"candidate": label, "score_F": F, "score_p": p, "threshold": threshold}
        if p >= threshold:
            step["accepted"] = False
            step["why"] = "best remaining candidate is not significant"
            steps.append(step)
            break
        say(f"testing {label}")
        new = _clone_model(model, [make_effect(robot, label)])
        sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
        new_res = fit(new, train, cond=cond_fit, initial_sigma=sigmas)
        # F-test and BIC of the refit, both models' residuals under the same weights.
        ssr_old = _weighted_ssr(model, train, cond_fit, res)
        ssr_new = _weighted_ssr(new, train, cond_fit, res)
        dof_new = max(m - new_res.n_params, 1)
        F_fit = ((ssr_old - ssr_new) / k) / max(ssr_new / dof_new, 1e-300)
        p_fit = _f_sf(F_fit, k, dof_new) if F_fit > 0 else 1.0
        d_bic = m * math.log(max(ssr_new, 1e-300) / max(ssr_old, 1e-300)) + k * math.log(m)
        # Same weights on both sides (the refit's noise estimate is smaller).
        current_hold = _hold_score(model, test, cond_hold, res)
        new_hold = _hold_score(new, test, cond_hold, res)
        step.update(
            {
                "fit_F": F_fit,
                "fit_p": p_fit,
                "delta_bic": d_bic,
                "holdout_score_before": current_hold,
                "holdout_score_after": new_hold,
            }
        )
        ok = p_fit < threshold and d_bic < 0 and new_hold < current_hold
        step["accepted"] = ok
        steps.append(step)
        if not ok:
            step["why"] = "refit not significant, BIC not lower, or hold-out not better"
            rejected_in_a_row += 1
            pool = [c for c in pool if c != label]
            if rejected_in_a_row >= MAX_REJECTED_IN_A_ROW:
                break
            continue
        rejected_in_a_row = 0
        # Near-duplicates among the remaining candidates make this choice ambiguous.
        fitted = projected[label][1]
        for other, (Jo, _) in projected.items():
            if other == label:
                continue
            cos = _explained_fraction(fitted, Jo)
            if cos > AMBIGUITY_COSINE:
                ambiguous.append(
                    {
                        "effects": [label, other],
                        "why": f"signatures {100 * cos:.1f} % alike in this data "
                        f"(|cos| = {cos:.4f}); chose {label} by score, "
                        f"{other} would explain nearly as much",
                    }
                )
        model, res = new, new_res
        pool = [c for c in pool if c != label]
        # Backward elimination: a cause chosen early may have stood in for one chosen
        # later (an eccentricity sin(q) looks like a gear ratio q over a small range).
        model, res, removed = _eliminate(model, res, train, cond_fit, alpha, label, steps, say)
        pool = [c for c in pool if c not in removed]

    say("measuring each cause's gain")
    pos1, ori1 = model_errors(model, test, cond_hold)
    causes = []
    for e in model.effects:
        reduced = _refit_without(model, e.label, train, cond_fit, res)
        pos_r, ori_r = model_errors(reduced, test, cond_hold)
        sl = res.block_slice(e.label)
        value, std, components = _report_value(e, res.std[sl])
        step = next(s for s in steps if s["candidate"] == e.label and s.get("accepted"))
        gain_p = float(pos_r.mean() - pos1.mean())
        gain_o = None if ori1 is None else float(ori_r.mean() - ori1.mean())
        evidence = (
            f"F-test of the refit F = {step['fit_F']:.3g} on {e.value.numel()} dof, "
            f"p = {step['fit_p']:.2g} < {step['threshold']:.1g} (Bonferroni over "
            f"{round(alpha / step['threshold'])} candidates); BIC change "
            f"{step['delta_bic']:.1f}; hold-out mean position error without it "
            f"{float(pos_r.mean()):.4f} mm, with it {float(pos1.mean()):.4f} mm"
        )
        causes.append(
            Cause(
                effect=e.kind,
                joint=e.joint,
                value=value,
                unit=e.unit,
                std=std,
                position_gain_mm=gain_p,
                orientation_gain_deg=gain_o,
                evidence=evidence,
                components=components,
            )
        )
    causes.sort(key=lambda c: c.position_gain_mm, reverse=True)

    # Strongly correlated estimates (frames included) are ambiguous groups too.
    seen = set()
    for a, _, b, _, r in res.correlated_pairs(AMBIGUITY_CORRELATION):
        if (a, b) in seen or (a.endswith("_frame") and b.endswith("_frame")):
            continue
        seen.add((a, b))
        ambiguous.append(
            {
                "effects": [a, b],
                "why": f"estimates correlated at {abs(r):.3f}: the data "
                "barely separates them, their values trade off",
            }
        )

    residual_hold = _residual_vectors(model, test, cond_hold)
    structured, nn_corr = _structured(residual_hold, test.q, *robot.joint_limits)
    sv = res.singular_values
    identifiability = {
        "n_parameters": res.n_params,
        "condition_number": res.condition,
        "singular_values": [float(v) for v in sv],
        "observability_index": float(
            sv.clamp_min(1e-300).log().mean().exp() / math.sqrt(res.n_obs)
        ),
        "unobservable_candidates": unobservable,
        "noise_estimate": {"position_mm": res.sigma_pos_mm, "orientation_rad": res.sigma_rot_rad},
    }
    unexplained = {
        "position_mm_rms": float(pos1.pow(2).mean().sqrt()),
        "orientation_deg_rms": None if ori1 is None else float(ori1.pow(2).mean().sqrt()),
        "structured": structured,
        "neighbour_correlation": nn_corr,
    }
    warnings = plausibility_warnings(causes, data)
    return Diagnosis(
        warnings=warnings,
        robot=robot.name,
        n_samples=data.n,
        n_holdout=test.n,
        nominal=nominal,
        extended=_stats_json(pos1, ori1),
        causes=causes,
        ambiguous=ambiguous,
        unexplained=unexplained,
        identifiability=identifiability,
        model=model,
        nominal_model=nominal_model,
        fit_rows=fit_rows,
        holdout_rows=hold_rows,
        steps=steps,
    )


# Largest credible linear expansion coefficient [1/K]: structural metals are 1e-5..2.5e-5,
# polymers reach ~1e-4.
MAX_CREDIBLE_EXPANSION = 5e-5


def plausibility_warnings(causes: list[Cause], data: MeasuredData) -> list[dict]:
    """Statistically supported is not physically credible: flag values that are not.

    A negative compliance or backlash, or an expansion coefficient no structure has,
    usually means the effect stands in for something else (e.g. a temperature that
    differs mostly between files, so that it tells the files apart).
    """
    out = []
    for c in causes:
        label = c.effect if c.joint is None else f"{c.effect}:{c.joint}"
        if c.effect in ("joint_compliance", "backlash") and float(c.value) < 0:
            out.append(
                {
                    "cause": label,
                    "why": f"negative {c.effect} ({c.value:.3g} {c.unit}) is not physical: "
                    "it likely absorbs another, unmodelled error",
                }
            )
        if c.effect != "thermal_expansion":
            continue
        alpha = float(c.value)
        reasons = []
        if alpha < 0 or abs(alpha) > MAX_CREDIBLE_EXPANSION:
            reasons.append(
                f"alpha = {alpha:.3g} 1/K is outside any structural material "
                f"(0 .. {MAX_CREDIBLE_EXPANSION:.0e})"
            )
        if data.temperature is not None and len(data.sources) > 1:
            t, f = data.temperature, data.file_index
            files = range(len(data.sources))
            means = torch.stack([t[f == i].mean() for i in files])
            within = float(torch.stack([t[f == i].std() for i in files]).nan_to_num().max())
            between = float(means.max() - means.min())
            if between > 2 * within:
                reasons.append(
                    f"temperature differs {between:.2f} K between files but at most "
                    f"{within:.2f} K (std) within one: the effect may stand for a "
                    "difference between the files"
                )
        if reasons:
            out.append({"cause": label, "why": "; ".join(reasons)})
    return out


def _eliminate(
    model: ExtendedModel,
    res: FitResult,
    train: MeasuredData,
    cond: Conditions,
    alpha: float,
    newest: str,
    steps: list[dict],
    say: Callable[[str], None],
) -> tuple[ExtendedModel, FitResult, set[str]]:
    """Drop earlier causes that are no longer significant given the others.

    Each cause but ``newest`` is tested by the F-test of removing it (the reduced model
    refitted, both residuals under the full fit's weights) at the Bonferroni level
    ``alpha / #causes``; the least significant failing one is removed, the model
    refitted, and the test repeated. Removals are logged in ``steps``.
    """
    removed: set[str] = set()
    while len(model.effects) > 1:
        ssr_full = _weighted_ssr(model, train, cond, res)
        dof = max(res.n_obs - res.n_params, 1)
        threshold = alpha / len(model.effects)
        worst = None
        for e in model.effects:
            if e.label == newest:
                continue
            reduced = _refit_without(model, e.label, train, cond, res)
            k = e.value.numel()
            ssr_red = _weighted_ssr(reduced, train, cond, res)
            F = ((ssr_red - ssr_full) / k) / max(ssr_full / dof, 1e-300)
            p = _f_sf(F, k, dof) if F > 0 else 1.0
            if p >= threshold and (worst is None or p > worst[1]):
                worst = (e.label, p, F)
        if worst is None:
            break
        label, p, F = worst
        say(f"removing {label}: no longer significant")
        steps.append(
            {
                "candidate": label,
                "removed": True,
                "removal_F": F,
                "removal_p": p,
                "threshold": threshold,
                "accepted": False,
                "why": "backward elimination: no longer significant once later causes were added",
            }
        )
        model = _without(model, label)
        res = fit(model, train, cond=cond, initial_sigma=(res.sigma_pos_mm, res.sigma_rot_rad))
        removed.add(label)
    return model, res, removed


def _explained_fraction(v: Tensor, B: Tensor) -> float:
    """|cosine| between ``v`` and its projection on the column space of ``B``: how much
    of the correction ``v`` another candidate could make as well."""
    Qb, _ = torch.linalg.qr(B)
    return float((Qb.T @ v).norm() / v.norm().clamp_min(1e-300))


def _weighted_ssr(model: ExtendedModel, data: MeasuredData, cond: Conditions, res: FitResult):
    problem = Problem(model, data, cond, (), res.sigma_pos_mm, res.sigma_rot_rad or 1.0)
    with torch.no_grad():
        r = problem.residual(torch.zeros(0, dtype=torch.float64))
    return float(r @ r)


def _hold_score(model: ExtendedModel, test: MeasuredData, cond: Conditions, res: FitResult):
    """Hold-out sum of squares under the fit's noise weights (position and rotation)."""
    return _weighted_ssr(model, test, cond, res) / max(test.n, 1)


def _residual_vectors(model: ExtendedModel, data: MeasuredData, cond: Conditions) -> Tensor:
    problem = Problem(model, data, cond, (), 1.0, 1e-3)  # mm and mrad
    with torch.no_grad():
        r = problem.residual(torch.zeros(0, dtype=torch.float64))
    k = 6 if data.quat is not None else 3
    return r.reshape(k // 3, data.n, 3).permute(1, 0, 2).reshape(data.n, k)


def _report_value(e: Effect, std: Tensor):
    v = e.value.detach().to(torch.float64)
    if e.kind == "axis_misalignment":  # internal (u, v) on a basis -> rotation vector
        basis = e.basis.to(torch.float64)
        w_std = ((std[:, None] * basis) ** 2).sum(0).sqrt()  # ignores the u-v covariance
        return e.report_value(), [float(x) for x in w_std], None
    if e.kind == "joint_eccentricity":
        amp = float(v.norm())
        # std of the amplitude by first-order propagation
        grad = (v / max(amp, 1e-300)).numpy()
        s = float(np.sqrt((grad**2 * std.numpy() ** 2).sum()))
        return amp, s, [float(x) for x in v]
    if v.numel() == 1:
        return float(v), float(std[0]), None
    return [float(x) for x in v], [float(x) for x in std], None

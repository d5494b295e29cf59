"""Backward elimination and leave-one-out gains of the chosen causes.

A cause chosen early may have stood in for one chosen later (an eccentricity
``sin(q)`` looks like a gear ratio ``q`` over a small range): after each addition,
every earlier cause is tested by the F-test of removing it.
"""

from __future__ import annotations

from collections.abc import Callable

from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import weighted_ssr
from hybrid_pk.calibration.diagnosis.variants import (
    linearised_removal,
    refit_without,
    without_effect,
)
from hybrid_pk.calibration.fit import FitResult, fit
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.distributions import f_isf, f_sf
from hybrid_pk.effects import ExtendedModel

__all__ = ["eliminate"]


def eliminate(
    model: ExtendedModel,
    res: FitResult,
    split: Split,
    alpha: float,
    newest: str,
    steps: list[dict],
    say: Callable[[str], None],
) -> tuple[ExtendedModel, FitResult, set[str]]:
    """Drop earlier causes that are no longer significant given the others.

    Each cause but ``newest`` is tested by the F-test of removing it (the reduced model
    refitted, both residuals under the full fit's weights) at the Bonferroni level
    ``alpha / #causes``; the least significant failing one is removed, the model
    refitted, and the test repeated. Removals are logged in ``steps``. Clearly
    significant causes are kept on their linearised statistic without a refit.
    """
    train, cond = split.train, split.cond_fit
    removed: set[str] = set()
    while len(model.effects) > 1:
        threshold = alpha / len(model.effects)
        worst = _least_significant(model, res, split, threshold, newest, say)
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
        model = without_effect(model, label)
        sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
        res = fit(model, train, cond=cond, initial_sigma=sigmas, progress=say, **res.settings())
        removed.add(label)
    return model, res, removed


def _least_significant(
    model: ExtendedModel,
    res: FitResult,
    split: Split,
    threshold: float,
    newest: str,
    say: Callable[[str], None],
) -> tuple[str, float, float] | None:
    """``(label, p, F)`` of the cause (not ``newest``) whose removal is least significant,
    among those with ``p >= threshold``; None when every cause is significant.

    A cause whose linearised removal statistic (Wald) exceeds the critical F by
    the tuning's ``linearised_margin`` stays without a refit; the others are decided by the
    F-test of the refitted reduced model.
    """
    train, cond = split.train, split.cond_fit
    ssr_full = res.cost if res.cost is not None else weighted_ssr(model, train, cond, res)
    dof = max(res.n_obs - res.n_params, 1)
    worst = None
    for e in model.effects:
        if e.label == newest:
            continue
        k = e.value.numel()
        if res.normal_matrix is not None:
            increase, _ = linearised_removal(res, e.label)
            F_lin = (increase / k) / max(ssr_full / dof, 1e-300)
            if F_lin > diagnosis_tuning().linearised_margin * f_isf(threshold, k, dof):
                continue  # clearly significant: the refit could not change the decision
        say(f"testing whether {e.label} is still needed")
        reduced = refit_without(model, e.label, train, cond, res, say)
        ssr_red = weighted_ssr(reduced, train, cond, res)
        F = ((ssr_red - ssr_full) / k) / max(ssr_full / dof, 1e-300)
        p = f_sf(F, k, dof) if F > 0 else 1.0
        if p >= threshold and (worst is None or p > worst[1]):
            worst = (e.label, p, F)
    return worst

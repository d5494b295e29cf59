"""Statistically supported is not physically credible: flag cause values that are not
(:func:`implausibility`: a fitted effect beyond what its physics can be, the limits of
:mod:`hybrid_pk.effects.limits`; :func:`plausibility_warnings`: signs and expansions)."""

from __future__ import annotations

import math

import torch

from hybrid_pk.calibration.diagnosis.result import Cause
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import EFFECTS, Effect
from hybrid_pk.effects.geometric import MAX_CREDIBLE_EXPANSION
from hybrid_pk.effects.limits import (
    MAX_COMPLIANCE,
    MAX_ROTATION_DEG,
    MAX_TRANSLATION_M,
    effect_limit,
)
from hybrid_pk.robot import Robot

__all__ = [
    "MAX_CREDIBLE_EXPANSION",
    "carried_finding",
    "effect_std",
    "finding_entry",
    "implausibility",
    "implausible_effect",
    "oversized",
    "plausibility_warnings",
    "refusal_why",
]


def plausibility_warnings(causes: list[Cause], data: MeasuredData) -> list[dict]:
    """Statistically supported is not physically credible: flag values that are not.

    A negative compliance or backlash, or an expansion coefficient no structure has,
    usually means the effect stands in for something else (e.g. a temperature that
    differs mostly between files, so that it tells the files apart).
    """
    out = []
    for c in causes:
        label = c.effect if c.joint is None else f"{c.effect}:{c.joint}"
        cls = EFFECTS[c.effect]
        reasons = cls.implausible(c.value, c.std)
        if cls.needs == "temperature":
            reasons += _temperature_reasons(data)
        if reasons:
            out.append({"cause": label, "why": "; ".join(reasons)})
    return out


def _temperature_reasons(data: MeasuredData) -> list[str]:
    """A temperature that differs mostly between the files may tell them apart."""
    reasons = []
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
    return reasons


def finding_entry(cause: str, value, limit: float | None, unit: str, why: str) -> dict:
    """A structural finding: ``{"cause", "value", "limit", "unit", "why"}``."""
    return {"cause": cause, "value": value, "limit": limit, "unit": unit, "why": why}


def implausibility(
    effect: Effect, robot: Robot, data: MeasuredData | None = None, std=None
) -> dict | None:
    """Why ``effect``'s value is not a small physical correction, or None.

    Args:
        effect: a fitted effect of ``robot``.
        data: the rows (compliance: the gravity torques they load the joint with).
        std: ``(size,)`` standard deviations of its parameters from the fit (None, or
            NaN: the fit gave none): a sign rule then reads a value within
            :data:`~hybrid_pk.effects.base.SIGN_SIGMAS` of them as zero.

    Returns:
        ``{"cause", "value", "limit", "unit", "why"}`` when beyond the limits.
    """
    unit = effect.unit
    size = float(effect.value.detach().norm())
    wrong_sign = _wrong_sign(effect, std)
    if wrong_sign is not None:
        return wrong_sign
    if effect.stage == "compliance":
        return _compliance_check(effect, robot, data)
    if effect.stage == "deflection":
        return _deflection_check(effect, robot, data)
    limit = effect_limit(effect, robot)
    if limit is None or size <= limit:
        return None
    if unit == "1":  # a gear ratio error
        what, shown, limit_text = "gear ratio error", f"{100 * size:.3g} %", f"{100 * limit:g} %"
    elif unit == "1/K":  # a thermal expansion coefficient
        what, shown, limit_text = "thermal expansion", f"{size:.3g} 1/K", f"{limit:g} 1/K"
    elif limit == MAX_TRANSLATION_M:  # a length: unit m, or a prismatic joint's shift
        what, shown, limit_text = "translation", f"{1e3 * size:.4g} mm", f"{1e3 * limit:g} mm"
    else:
        what, shown = "rotation", f"{math.degrees(size):.3g}°"
        limit_text = f"{math.degrees(limit):g}°"
    why = f"a {what} of {shown} is beyond what a small correction of the URDF can be ({limit_text})"
    return finding_entry(effect.label, size, limit, unit, why)


def implausible_effect(
    model, data: MeasuredData | None, first: str | None = None, res=None
) -> dict | None:
    """The :func:`implausibility` entry of the first effect of ``model`` (``first``, by
    label, checked before the others) that is not a small physical correction, or None.
    ``res``: the fit of ``model``, whose standard deviations the sign rules read.

    Every effect, not only the one a refit added: a refit moves all of them, and along
    a direction the data barely determine (two link lengths along parallel axes) it can
    carry an earlier cause to metres while the two cancel (the UR10 series without the
    cause limit: +-2455 mm, after a group swap)."""
    effects = sorted(model.effects, key=lambda e: e.label != first)
    for e in effects:
        why = implausibility(e, model.robot, data, effect_std(res, e.label))
        if why is not None:
            return why
    return None


def oversized(model) -> bool:
    """Whether an effect of ``model`` is beyond the largest size a small physical
    correction can have (:func:`~hybrid_pk.effects.limits.effect_limit`; its sign and its
    loads aside): the test a trial's refit stops at. A refit that ends so is refused;
    the walk on, along a direction the data barely determine (link lengths along
    parallel axes, to metres), costs Jacobians for nothing else."""
    return any(
        (limit := effect_limit(e, model.robot)) is not None
        and float(e.value.detach().norm()) > limit
        for e in model.effects
    )


def effect_std(res, label: str):
    """The standard deviations of effect ``label``'s parameters in fit ``res`` (a list),
    or None (no fit, or not one of its blocks)."""
    if res is None:
        return None
    try:
        return [float(x) for x in res.std[res.block_slice(label)]]
    except KeyError:
        return None


def _wrong_sign(effect: Effect, std=None) -> dict | None:
    """The finding of an effect whose physics fixes its sign, fitted beyond it: its
    class's own rule (:meth:`Effect.refused`), which the warnings state too. A load
    cannot bend a structure towards itself, nor a play be negative (``positive``
    effects: a play, a compliance, a bend under load), nor a robot shrink as it warms
    by more than any structure does (thermal expansion), so a value significantly
    beyond measures something else the effect absorbs, whatever its size; one within
    :data:`~hybrid_pk.effects.base.SIGN_SIGMAS` of its ``std`` (where the fit gave
    one) is not beyond as far as the rows can tell (a component the data barely
    determine, next to one they do)."""
    v = effect.value.detach().reshape(-1)
    value = float(v[0]) if v.numel() == 1 else [float(x) for x in v]
    reasons = type(effect).refused(value, std)
    if not reasons:
        return None
    floor = type(effect).floor
    return finding_entry(effect.label, float(v.min()), floor, effect.unit, "; ".join(reasons))


def refusal_why(implausible: dict) -> str:
    """Why a step or settle refuses an effect (its :func:`implausibility` entry)."""
    return f"not a small correction of the URDF: {implausible['why']}"


def carried_finding(implausible: dict, label: str) -> dict:
    """The finding of candidate ``label`` whose refit left ``implausible``'s effect (it,
    or an effect it carried along a direction the data barely determine) beyond a
    small correction (``moved``: that effect)."""
    if implausible["cause"] == label:
        return implausible
    why = f"its refit carries {implausible['cause']} off: {implausible['why']}"
    return {**implausible, "cause": label, "why": why, "moved": implausible["cause"]}


def _compliance_check(effect: Effect, robot: Robot, data: MeasuredData | None) -> dict | None:
    c = float(effect.value.detach())
    reasons = []
    if abs(c) > MAX_COMPLIANCE:
        reasons.append(
            f"a compliance of {c:.3g} rad/Nm is beyond what metal joints show "
            f"({MAX_COMPLIANCE:g} rad/Nm)"
        )
    if data is not None:
        with torch.no_grad():
            tau = robot.gravity_torques(data.q, payload=_payload(data))[:, effect.joint_index]
        reasons += _sag_reasons("bend", effect.joint, math.degrees(abs(c) * float(tau.abs().max())))
    if not reasons:
        return None
    return finding_entry(effect.label, c, MAX_COMPLIANCE, effect.unit, "; ".join(reasons))


def _deflection_check(effect: Effect, robot: Robot, data: MeasuredData | None) -> dict | None:
    """A bearing or link compliance beyond what metal shows (a column's per metre of
    extension, times the longest extension of the data)."""
    c = float(effect.value.detach().abs().max())
    what = f"a compliance of {c:.3g} {effect.unit}"
    if effect.joints == "prismatic":  # a column's bending is per metre of extension
        reach = 1.0
        if data is not None:
            with torch.no_grad():
                reach = float(robot.chain_q(data.q)[:, effect.joint_index].abs().max())
        what += f" ({c * reach:.3g} rad/Nm at the longest extension, {reach:.3g} m)"
        c *= reach
    reasons = []
    if c > MAX_COMPLIANCE:
        reasons.append(
            f"{what} is beyond what metal joints and links show ({MAX_COMPLIANCE:g} rad/Nm)"
        )
    if data is not None:
        reasons += _sag_reasons("tilt", effect.joint, _largest_tilt_deg(effect, robot, data))
    if not reasons:
        return None
    return finding_entry(effect.label, c, MAX_COMPLIANCE, "rad/Nm", "; ".join(reasons))


@torch.no_grad()
def _largest_tilt_deg(effect: Effect, robot: Robot, data: MeasuredData) -> float:
    """The largest tilt [deg] a deflection effect makes over the rows of ``data`` under
    upright gravity (the data's payload)."""
    wrench = robot.static_wrenches(data.q, payload=_payload(data), frame="joint")
    w, _ = effect.rotation(wrench[:, effect.joint_index], robot.chain_q(data.q))
    return math.degrees(float(w.norm(dim=-1).max()))


def _payload(data: MeasuredData):
    """The rows' payload [kg] (0 where the data give none)."""
    return 0.0 if data.payload is None else data.payload


def _sag_reasons(verb: str, joint: str, degrees: float) -> list[str]:
    """The reason a load-driven effect is implausible when it would ``verb`` (bend,
    tilt) its joint beyond ``MAX_ROTATION_DEG`` under the data's gravity; else none."""
    if degrees <= MAX_ROTATION_DEG:
        return []
    return [
        f"it would {verb} {joint} by {degrees:.3g}° under the gravity of these poses "
        f"({MAX_ROTATION_DEG:g}° at most)"
    ]

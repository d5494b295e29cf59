"""Evidence of a periodic joint error, phase-folded, and the gain a cause earns.

A cyclic error of ``n`` cycles per turn repeats every ``360 / n`` degrees of its joint.
Binned against the joint angle, a bin wider than that period averages whole cycles
away, so the medians show nothing whether the error is there or not. Folded onto one
period (the phase ``n θ mod 360°``) every row lands where its cycle puts it, so the
binned medians trace the sinusoid when the data carry it and stay flat when not.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Effect
from hybrid_pk.effects.joint import JointEccentricity
from hybrid_pk.evaluation.plots import binned_median

__all__ = ["gain_text", "phase_folded"]


def phase_folded(evidence, effect: Effect, data: MeasuredData):
    """``evidence`` of a periodic joint effect against its phase ``n θ mod 360°`` when
    the plotted rows span more than one period; any other evidence unchanged."""
    if not isinstance(effect, JointEccentricity) or evidence.rows.size == 0:
        return evidence
    n = effect.order
    theta = data.q[evidence.rows, effect.joint_index].double().numpy()
    if n * float(theta.max() - theta.min()) <= 2 * math.pi:
        return evidence  # at most one period: the joint angle shows the cycle as it is
    x = np.degrees(np.mod(n * theta, 2 * math.pi))
    a, b = (float(v) for v in effect.value.detach().double())
    curve_x = np.linspace(0.0, 360.0, 181)
    phase = np.radians(curve_x)
    curve_y = 1e3 * (a * np.sin(phase) + b * np.cos(phase))  # [mrad], as the points
    mx, my = binned_median(x, evidence.y)
    nth = "θ" if n == 1 else f"{n}·θ"
    return replace(
        evidence,
        x=x,
        x_label=f"phase {nth} mod 360° of {effect.joint} [deg] (folded onto one period)",
        curve_x=curve_x,
        curve_y=curve_y,
        median_x=mx,
        median_y=my,
    )


def gain_text(cause) -> str:
    """``blocked hold-out gain … mm`` where the cause carries one (the gain on
    contiguous regions of joint space no fit saw), else its hold-out gain."""
    blocked = getattr(cause, "blocked_holdout_gain_mm", None)
    if blocked is not None and math.isfinite(blocked):
        return f"blocked hold-out gain {blocked:.3g} mm"
    gain = getattr(cause, "position_gain_mm", None)
    if gain is None or not math.isfinite(gain):
        return ""
    return f"hold-out gain {gain:.3g} mm"

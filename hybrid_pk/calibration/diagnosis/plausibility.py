"""Statistically supported is not physically credible: flag cause values that are not."""

from __future__ import annotations

import torch

from hybrid_pk.calibration.diagnosis.result import Cause
from hybrid_pk.data.measured import MeasuredData

__all__ = ["MAX_CREDIBLE_EXPANSION", "plausibility_warnings"]

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
        if c.effect in ("tilt_compliance", "column_bending") and min(c.value) < 0:
            out.append(
                {
                    "cause": label,
                    "why": f"negative {c.effect} ({', '.join(f'{v:.3g}' for v in c.value)} "
                    f"{c.unit}): a load cannot bend a structure towards itself; it likely "
                    "absorbs another, unmodelled error",
                }
            )
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
        reasons = _expansion_reasons(float(c.value), data)
        if reasons:
            out.append({"cause": label, "why": "; ".join(reasons)})
    return out


def _expansion_reasons(alpha: float, data: MeasuredData) -> list[str]:
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
    return reasons

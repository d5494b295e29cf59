"""Statistically supported is not physically credible: flag cause values that are not."""

from __future__ import annotations

import torch

from hybrid_pk.calibration.diagnosis.result import Cause
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import EFFECTS
from hybrid_pk.effects.geometric import MAX_CREDIBLE_EXPANSION

__all__ = ["MAX_CREDIBLE_EXPANSION", "plausibility_warnings"]


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
        reasons = cls.implausible(c.value)
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

"""What a geometric export leaves out, and how much it moves the measured points.

A DH / modified-DH table, a URDF and UR's kinematics YAML carry the geometry: link
lengths, axis misalignments, frames and joint offsets, at the reference temperature
(20 °C). Compliance, deflection, backlash, gear ratios, eccentricity and cyclic errors,
residual networks and a thermal expansion away from 20 °C are not in the file: each is
listed with its value and its size at the points, the distance [mm] the end
point moves when that one effect is taken out of the full model (rms and max), and
the total, full model against the exported geometry alone. ``hybrid-pk compensate`` (or
the model file) is the way to carry them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.geometry import so3_log
from hybrid_pk.io.dh_export import geometric_model
from hybrid_pk.io.hybrid_file import forward_model, networks_used
from hybrid_pk.io.model_file import LoadedModel

__all__ = ["LeftOut", "left_out", "summary_lines"]


@dataclass(frozen=True)
class LeftOut:
    """One thing an export cannot carry: its name, value and size at the points."""

    what: str
    value: str
    size_mm: tuple[float, float]  # position: rms, max over the points
    turn_mrad: float  # orientation: max over the points

    def line(self) -> str:
        rms, peak = self.size_mm
        value = "" if self.value == "-" else f" = {self.value}"  # networks have no value
        return (
            f"{self.what}{value}: {rms:.4g} mm rms, {peak:.4g} mm max, "
            f"{self.turn_mrad:.4g} mrad max"
        )


def _size(a: Tensor, b: Tensor) -> tuple[tuple[float, float], float]:
    """``((rms, max) [mm] of the position difference, max angle [mrad] between them)``."""
    d = (a[..., :3, 3] - b[..., :3, 3]).norm(dim=-1) * 1000.0
    angle = so3_log(a[..., :3, :3].transpose(-1, -2) @ b[..., :3, :3]).norm(dim=-1)
    return (float(d.pow(2).mean().sqrt()), float(d.max())), float(angle.max()) * 1000.0


def _value(e) -> str:
    v = e.report_value()
    text = f"[{', '.join(f'{x:.4g}' for x in v)}]" if isinstance(v, list) else f"{v:.4g}"
    return f"{text} {e.unit}"


def _temperatures(model, q: Tensor, cond: Conditions) -> tuple[Conditions, Conditions, str]:
    """``(cond at the points, cond at the file's reference temperature, label suffix)``.

    The file holds the geometry at 20 °C. Where the points have no temperature (random
    configurations, or data without the column) a temperature-dependent effect is sized
    1 K from it, per kelvin (an expansion is linear in the temperature)."""
    if not any(e.needs == "temperature" for e in model.effects):
        return cond, cond, ""
    ref = torch.full(q.shape[:-1], REFERENCE_TEMPERATURE, dtype=q.dtype)
    at_ref = replace(cond, temperature=ref)
    label = f" (the file holds it at {REFERENCE_TEMPERATURE:g} °C"
    if cond.temperature is None:
        return replace(cond, temperature=ref + 1.0), at_ref, f"{label}; size per K from it)"
    return cond, at_ref, f"{label}; size at the points' temperatures)"


def left_out(loaded: LoadedModel, q: Tensor, cond: Conditions) -> list[LeftOut]:
    """Effects (and networks) of ``loaded`` that a geometric export drops, each with its
    size at joint values ``q (N, dof)`` under ``cond``; a last ``total`` entry when any.
    A temperature-dependent geometric effect (thermal expansion) is written at the
    reference temperature: listed with its size away from it."""
    model = loaded.model
    cond, at_ref, thermal = _temperatures(model, q, cond)
    kept = {id(e) for e in geometric_model(model).effects if e.needs != "temperature"}
    out = []
    with torch.no_grad():
        full = model(q, cond)  # the measured point in the measurement frame
        for e in model.effects:
            if id(e) in kept:
                continue
            without = model.with_effects([x for x in model.effects if x is not e])
            what = e.label + (thermal if e.needs == "temperature" else "")
            out.append(LeftOut(what, _value(e), *_size(full, without(q, cond))))
        if networks_used(loaded):
            hybrid = forward_model(loaded)(q, cond)
            out.append(LeftOut("residual networks", "-", *_size(hybrid, full)))
            full = hybrid
        if out:
            total = _size(full, geometric_model(model)(q, at_ref))
            out.append(LeftOut("total", "all of the above", *total))
    return out


def summary_lines(items: list[LeftOut], where: str) -> list[str]:
    """Summary lines of :func:`left_out`'s result; ``where`` names the points."""
    if not items:
        return ["every effect of the model is geometric: the export carries all of it"]
    return [
        f"not carried by a geometric table (size at {where}; 'hybrid-pk compensate MODEL "
        "PROGRAM --controller FILE' carries them for a controller running this file):",
        *(f"  {item.line()}" for item in items),
    ]

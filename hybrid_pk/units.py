"""Units of the numbers users bring (tracker exports, datasheets' DH tables): one table
for the column-mapping import (:mod:`hybrid_pk.data.units`) and ``import dh``
(:mod:`hybrid_pk.robot.dh_table`). The package computes in m, rad, s, °C, kg.
"""

from __future__ import annotations

import math

__all__ = ["UNITS"]

# unit -> (quantity, scale, offset): table value = scale * value + offset
UNITS: dict[str, tuple[str, float, float]] = {
    "m": ("length", 1.0, 0.0),
    "mm": ("length", 1e-3, 0.0),
    "cm": ("length", 1e-2, 0.0),
    "um": ("length", 1e-6, 0.0),
    "µm": ("length", 1e-6, 0.0),
    "in": ("length", 0.0254, 0.0),
    "rad": ("angle", 1.0, 0.0),
    "deg": ("angle", math.pi / 180, 0.0),
    "°": ("angle", math.pi / 180, 0.0),
    "mrad": ("angle", 1e-3, 0.0),
    "urad": ("angle", 1e-6, 0.0),
    "s": ("time", 1.0, 0.0),
    "ms": ("time", 1e-3, 0.0),
    "us": ("time", 1e-6, 0.0),
    "ns": ("time", 1e-9, 0.0),
    "min": ("time", 60.0, 0.0),
    "h": ("time", 3600.0, 0.0),
    "C": ("temperature", 1.0, 0.0),
    "degC": ("temperature", 1.0, 0.0),
    "°C": ("temperature", 1.0, 0.0),
    "K": ("temperature", 1.0, -273.15),
    "F": ("temperature", 5 / 9, -32 * 5 / 9),
    "degF": ("temperature", 5 / 9, -32 * 5 / 9),
    "kg": ("mass", 1.0, 0.0),
    "g": ("mass", 1e-3, 0.0),
    "lb": ("mass", 0.45359237, 0.0),
}

"""Units of the column-mapping import and the grammar of one source column.

A SOURCE is ``COLUMN`` (table unit, or the map's default unit for the target's
quantity), ``COLUMN[unit]``, ``COLUMN*FACTOR`` or ``COLUMN/FACTOR`` (a factor into the
table unit). Table units: length [m], angle [rad], time [s], temperature [°C],
mass [kg].
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

from hybrid_pk.errors import DataError
from hybrid_pk.units import UNITS

__all__ = [
    "EULER",
    "POSITION",
    "QUAT",
    "SCALARS",
    "TABLE_UNIT",
    "TARGET_QUANTITY",
    "UNITS",
    "Source",
    "parse_source",
    "unit_of",
]

TABLE_UNIT = {"length": "m", "angle": "rad", "time": "s", "temperature": "C", "mass": "kg"}
POSITION = ("x", "y", "z")
EULER = ("e1", "e2", "e3")
QUAT = ("qw", "qx", "qy", "qz")
SCALARS = ("t", "temperature", "payload")
# Quantity of every target that is not a joint (joints: angle, or length if prismatic).
TARGET_QUANTITY = {
    **dict.fromkeys(POSITION, "length"),
    **dict.fromkeys(EULER, "angle"),
    **dict.fromkeys(QUAT, "unitless"),
    "t": "time",
    "temperature": "temperature",
    "payload": "mass",
}


@dataclass(frozen=True)
class Source:
    """One source column and its conversion to the table unit.

    Attributes:
        column: source column name.
        unit: unit text as written (for summaries), or None.
        scale, offset: ``table value = scale * value + offset``.
        explicit: True when the unit or factor was written for this column.
    """

    column: str
    unit: str | None = None
    scale: float = 1.0
    offset: float = 0.0
    explicit: bool = False

    def describe(self) -> str:
        if self.unit is not None:
            return f"{self.column!r} [{self.unit}]"
        if self.scale != 1.0:
            return f"{self.column!r} *{self.scale:g}"
        return repr(self.column)


def unit_of(text: str, where: str) -> tuple[str, float, float]:
    """``(quantity, scale, offset)`` of a unit; ``where`` names it in the error."""
    unit = text.strip()
    if unit not in UNITS:
        close = difflib.get_close_matches(unit, list(UNITS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise DataError(
            f"column map: unknown unit {unit!r} in {where}{hint}; known: {', '.join(UNITS)}"
        )
    return UNITS[unit]


def parse_source(target: str, text: str, defaults: Mapping[str, str]) -> Source:
    """``COLUMN``, ``COLUMN[unit]``, ``COLUMN*k``, ``COLUMN/k`` -> :class:`Source`.

    ``defaults`` maps a quantity to the unit of columns written without one.
    """
    where = f"{target}={text}"
    text = text.strip()
    if not text:
        raise DataError(f"column map: {target!r} has no source column")
    m = re.fullmatch(r"(.*?)\s*([*/])\s*([-+0-9.eE]+)", text)
    if m and m.group(1):
        try:
            factor = float(m.group(3))
        except ValueError:
            raise DataError(f"column map: bad factor {m.group(3)!r} in {where}") from None
        if factor == 0 or not math.isfinite(factor):
            raise DataError(f"column map: factor must be finite and non-zero in {where}")
        scale = factor if m.group(2) == "*" else 1.0 / factor
        return Source(m.group(1), None, scale, 0.0, explicit=True)
    m = re.fullmatch(r"(.*?)\s*\[([^\[\]]+)\]", text)
    if m and m.group(1):
        _, scale, offset = unit_of(m.group(2), where)
        # Keep the full text as an alternative name: the header may carry the unit.
        return Source(m.group(1), m.group(2).strip(), scale, offset, explicit=True)
    quantity = TARGET_QUANTITY.get(target, "joint")
    unit = defaults.get("angle" if quantity == "joint" else quantity)
    if unit is not None and quantity != "unitless":
        _, scale, offset = unit_of(unit, f"units of {target}")
        return Source(text, unit, scale, offset)
    return Source(text)

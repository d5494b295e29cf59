"""Denavit–Hartenberg tables: read and check a robot maker's DH / modified-DH table.

A table has one row per joint, in chain order, with the columns (CSV header or YAML
keys) ``name, a, alpha, d, theta, type, lower, upper``: lengths [m], angles [rad],
``theta`` the joint's zero offset, ``type`` ``revolute``, ``continuous`` or
``prismatic`` (limits [rad or m]; a continuous joint may leave them empty). Optional:

- ``beta`` [rad]: Hayati's rotation about ``y``, for consecutive parallel axes (see
  :mod:`hybrid_pk.robot.dh`); 0 when absent;
- ``mass`` [kg], ``com_x, com_y, com_z`` [m] and ``ixx, ixy, ixz, iyy, iyz, izz``
  [kg m²]: the link's inertial, in the table's frame ``i`` (the frame the row ends in
  for ``dh``, the frame on joint ``i``'s axis for ``mdh``), the centre of mass as origin
  of the inertia; what the statics and compliance effects read.

A YAML file holds either a list of rows or a mapping with ``joints`` (the rows) and
optionally ``convention`` (``dh`` or ``mdh``), ``name``, ``base`` and ``flange``
(``{xyz: [m], rpy: [rad]}``, URDF roll-pitch-yaw).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from hybrid_pk.errors import DataError, missing_file, not_utf8_error
from hybrid_pk.units import UNITS

__all__ = [
    "CONVENTIONS",
    "DH_COLUMNS",
    "INERTIA_COLUMNS",
    "DHTable",
    "TableUnits",
    "pose_matrix",
    "read_dh_table",
]

CONVENTIONS = ("dh", "mdh")
DH_COLUMNS = ("name", "a", "alpha", "d", "theta", "type", "lower", "upper")
INERTIA_COLUMNS = ("mass", "com_x", "com_y", "com_z", "ixx", "ixy", "ixz", "iyy", "iyz", "izz")
_TYPES = ("revolute", "continuous", "prismatic")
# What a YAML DH table holds, said by the errors of a file laid out otherwise.
_LAYOUT = (
    f"a YAML DH table holds joints: (a list with one mapping of {', '.join(DH_COLUMNS)} "
    "per joint) and convention: dh|mdh, or that list alone"
)
_ANGLES = ("alpha", "theta", "beta")
# A DH angle is defined modulo one turn, so a table states it within [-2 pi, 2 pi]; a
# larger figure is a degree value (90, 180). Joint limits may span two turns (UR arms
# rotate +-2 pi, some wrists more): beyond two turns a limit is read as degrees.
_MAX_ANGLE = 2 * math.pi * (1 + 1e-9)
_MAX_LIMIT = 4 * math.pi * (1 + 1e-9)
# The longest industrial arms reach under 5 m (4.7 m: the longest-reach heavy arms), and
# no link is longer than its arm's reach: a DH length, centre of mass, base or flange
# offset beyond 5 m is a figure in millimetres (89.159 for UR5's 0.089159 m), cm or inches.
_MAX_LENGTH = 5.0
_LENGTHS = ("a", "d", "com_x", "com_y", "com_z")
# A robot track runs tens of metres, and no instrument measures a robot farther than
# 50 m (the bound the data tables keep for positions): a prismatic limit beyond is mm.
_MAX_TRAVEL = 50.0


@dataclass(frozen=True)
class TableUnits:
    """The units a table is written in: ``length`` for ``a``, ``d``, the centres of mass,
    prismatic limits and the ``xyz`` of ``base`` / ``flange`` (inertias in kg per its
    square), ``angle`` for ``alpha``, ``theta``, ``beta``, revolute limits and ``rpy``
    (datasheets print mm and degrees). Masses are kg."""

    length: str = "m"
    angle: str = "rad"

    def factor(self, key: str, kind: str = "revolute") -> float:
        """Into m, rad or kg m^2 for column ``key`` of a joint of type ``kind``."""
        length, angle = UNITS[self.length][1], UNITS[self.angle][1]
        if key in ("lower", "upper"):
            return length if kind == "prismatic" else angle
        if key in _LENGTHS:
            return length
        if key in _ANGLES:
            return angle
        return length**2 if key in INERTIA_COLUMNS[4:] else 1.0

    @classmethod
    def parse(cls, given, stated, where: str) -> TableUnits:
        """From the ``units`` argument (``{"length": "mm", "angle": "deg"}``) and the
        YAML file's ``units``; they must agree where both name a quantity."""
        found = {}
        for source, what in ((stated, "the file's"), (given, "the given")):
            if source is None:
                continue
            if not isinstance(source, Mapping) or set(source) - {"length", "angle"}:
                raise DataError(
                    f"{what} units {source!r}: write {{length: m|mm|cm|um|in, angle: rad|deg}}",
                    file=where,
                    column="units",
                )
            for quantity, unit in source.items():
                if UNITS.get(str(unit), ("",))[0] != quantity:
                    known = ", ".join(u for u, q in UNITS.items() if q[0] == quantity)
                    raise DataError(
                        f"{quantity} unit {unit!r}: one of {known}", file=where, column="units"
                    )
                if found.get(quantity, unit) != unit:
                    raise DataError(
                        f"the file states {quantity} unit {found[quantity]!r}, but {unit!r} "
                        "was given",
                        file=where,
                        column="units",
                    )
                found[quantity] = str(unit)
        return cls(**found)


@dataclass
class DHTable:
    """A checked DH or modified-DH table.

    Attributes:
        convention: ``"dh"`` (distal, ``Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)``) or
            ``"mdh"`` (Craig's proximal, ``Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d)``).
        rows: ``(n, 5)`` float64 ``a, alpha, d, theta, beta`` per joint [m, rad].
        names, types: per joint.
        lower, upper: ``(n,)`` limits [rad or m], ``±inf`` for continuous joints.
        inertial: ``(n, 10)`` ``mass, com (3), ixx ixy ixz iyy iyz izz`` or None.
        base: ``(4, 4)`` robot root -> table frame 0; flange: ``(4, 4)`` table frame n ->
            the flange (end link).
        name: robot name; source: file the table came from (for messages).
    """

    convention: str
    rows: np.ndarray
    names: list[str]
    types: list[str]
    lower: np.ndarray
    upper: np.ndarray
    inertial: np.ndarray | None = None
    base: np.ndarray = field(default_factory=lambda: np.eye(4))
    flange: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = "dh_robot"
    source: str = "<table>"

    @property
    def n(self) -> int:
        return len(self.names)


def pose_matrix(xyz: Sequence[float], rpy: Sequence[float]) -> np.ndarray:
    """``(4, 4)`` from a translation [m] and URDF roll-pitch-yaw [rad] (``Rz Ry Rx``)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(p), math.sin(p)
    cy, sy = math.cos(y), math.sin(y)
    T = np.eye(4)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    T[:3, 3] = [float(v) for v in xyz]
    return T


def _records(source, where: str) -> tuple[list[dict], dict]:
    """Rows (dicts, file order) and the file-level keys of a table source."""
    if isinstance(source, pd.DataFrame):
        return source.to_dict("records"), {}
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if not path.is_file():
            raise DataError(missing_file(path, "DH table file"), file=where)
        if path.suffix.lower() in (".yaml", ".yml"):
            try:
                doc = yaml.safe_load(path.read_text(encoding="utf-8"))
            except UnicodeDecodeError:
                raise not_utf8_error(path, table=False) from None
            except yaml.YAMLError as exc:
                reason = " ".join(str(exc).split())
                raise DataError(f"not valid YAML ({reason})", file=where) from exc
            if not isinstance(doc, (Mapping, list)):  # a text would be read as a path
                what = "nothing" if doc is None else repr(str(doc)[:40])
                raise DataError(f"holds {what}, not a table; {_LAYOUT}", file=where)
            return _records(doc, where)
        try:
            frame = pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
        except UnicodeDecodeError:
            raise not_utf8_error(path) from None
        except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
            raise DataError(f"not a readable CSV table ({exc})", file=where) from exc
        frame.columns = [str(c).strip() for c in frame.columns]
        return frame.to_dict("records"), {}
    if isinstance(source, Mapping):
        rows = source.get("joints")
        if not isinstance(rows, list):
            raise DataError("a YAML DH table needs a list of rows: joints", file=where)
        return rows, {k: v for k, v in source.items() if k != "joints"}
    if isinstance(source, Sequence) and not isinstance(source, (str, bytes)):
        return list(source), {}
    raise DataError(f"cannot read a DH table from a {type(source).__name__}", file=where)


def _number(row: dict, key: str, where: str, i: int, default: float | None = None) -> float:
    raw = row.get(key)
    if raw is None or (isinstance(raw, str) and not raw.strip()):
        if default is not None:
            return default
        raise DataError("empty cell: a number is required", file=where, row=i, column=key)
    try:
        value = float(raw)
    except (TypeError, ValueError):
        raise DataError(f"not a number: {raw!r}", file=where, row=i, column=key) from None
    if not math.isfinite(value) and key not in ("lower", "upper"):
        raise DataError(f"not a finite number: {raw!r}", file=where, row=i, column=key)
    return value


def _check_units(
    key: str, value: float, kind: str, where: str, i: int, units: TableUnits = TableUnits()
) -> None:
    """``value`` (in m / rad) of column ``key``: refused where it cannot be one of an arm's
    (a figure in another unit), with the figure as written."""
    written = value / units.factor(key, kind)
    if key in _ANGLES and abs(value) > _MAX_ANGLE:
        raise DataError(
            _turns(written, units, "an angle", "one turn"), file=where, row=i, column=key
        )
    if key in ("lower", "upper") and kind != "prismatic" and abs(value) > _MAX_LIMIT:
        why = _turns(written, units, "a joint limit", "two turns")
        raise DataError(why, file=where, row=i, column=key)
    if key in ("lower", "upper") and kind == "prismatic" and abs(value) > _MAX_TRAVEL:
        why = f"{_as_written(written, units)} no joint travel (robot tracks run tens of metres)"
        raise DataError(why + _mm_hint(written, units), file=where, row=i, column=key)
    if key in _LENGTHS and abs(value) > _MAX_LENGTH:
        raise DataError(_too_long(written, units), file=where, row=i, column=key)


def _as_written(written: float, units: TableUnits) -> str:
    if units.length == "m":
        return f"{written:g} m is"
    return f"{written:g} {units.length} is {written * units.factor('a'):g} m:"


def _mm_hint(written: float, units: TableUnits) -> str:
    if units.length != "m":
        return ""
    return (
        f": the column is in metres, write {written / 1000:g} for {written:g} mm, or read "
        "the table in mm (--length-unit mm)"
    )


def _turns(written: float, units: TableUnits, what: str, bound: str) -> str:
    if units.angle != "rad":
        return f"{written:g} {units.angle} is not {what} (beyond {bound})"
    return (
        f"{written:g} is not {what} in radians (beyond {bound}): write "
        f"{math.radians(written):.10g} for {written:g} degrees, or read the table in "
        "degrees (--angle-unit deg)"
    )


def _too_long(written: float, units: TableUnits = TableUnits()) -> str:
    return (
        f"{_as_written(written, units)} longer than any arm's link (the longest industrial "
        f"arms reach under {_MAX_LENGTH:g} m){_mm_hint(written, units)}"
    )


def _row(row: dict, where: str, i: int, inertial: bool, units: TableUnits) -> tuple:
    """``(name, type, [a, alpha, d, theta, beta], lower, upper, inertial or None)`` in
    m, rad, kg."""
    name = str(row.get("name", "")).strip()
    if not name:
        raise DataError("empty joint name", file=where, row=i, column="name")
    kind = str(row.get("type", "")).strip().lower()
    if kind not in _TYPES:
        raise DataError(
            f"joint type {row.get('type')!r}: write one of {', '.join(_TYPES)}",
            file=where,
            row=i,
            column="type",
        )
    values = [
        _number(row, k, where, i, 0.0 if k == "beta" else None) * units.factor(k, kind)
        for k in _ROW_KEYS
    ]
    bounds = [-math.inf, math.inf]  # a continuous joint has none (URDF ignores them too)
    if kind != "continuous":
        bounds = [_number(row, k, where, i) * units.factor(k, kind) for k in ("lower", "upper")]
    checked = (*_ROW_KEYS, "lower", "upper")
    for key, value in zip(checked, (*values, *bounds), strict=True):
        if math.isfinite(value):
            _check_units(key, value, kind, where, i, units)
    if not bounds[0] < bounds[1]:
        f = units.factor("lower", kind)
        lo, hi = (
            f"{b / f:g} {units.length if kind == 'prismatic' else units.angle}" for b in bounds
        )
        raise DataError(
            f"lower limit {lo} is not below upper limit {hi}",
            file=where,
            row=i,
            column="upper",
        )
    extra = None
    if inertial:
        extra = [_number(row, k, where, i, 0.0) * units.factor(k) for k in INERTIA_COLUMNS]
        for key, value in zip(INERTIA_COLUMNS[1:4], extra[1:4], strict=True):
            _check_units(key, value, kind, where, i, units)
        if extra[0] < 0:
            raise DataError(f"negative mass {extra[0]:g} kg", file=where, row=i, column="mass")
    return name, kind, values, *bounds, extra


_ROW_KEYS = ("a", "alpha", "d", "theta", "beta")


def _frame(value, key: str, where: str, units: TableUnits = TableUnits()) -> np.ndarray:
    """``{xyz, rpy}`` in the table's units, or a ``(4, 4)`` matrix [m]."""
    if value is None:
        return np.eye(4)
    if isinstance(value, Mapping):
        try:
            xyz = [float(v) * units.factor("a") for v in value.get("xyz", (0, 0, 0))]
            rpy = [float(v) * units.factor("alpha") for v in value.get("rpy", (0, 0, 0))]
        except (TypeError, ValueError):
            xyz = rpy = []
        if len(xyz) == 3 and len(rpy) == 3:
            _check_offset(xyz, key, where, units)
            return pose_matrix(xyz, rpy)
    arr = np.asarray(value, dtype=np.float64) if not isinstance(value, Mapping) else None
    if arr is not None and arr.shape == (4, 4):
        _check_offset(arr[:3, 3], key, where)
        return arr.copy()
    raise DataError(
        f"{key} must be {{xyz: [x, y, z] (m), rpy: [roll, pitch, yaw] (rad)}} or a 4x4 matrix",
        file=where,
        column=key,
    )


def _check_offset(xyz, key: str, where: str, units: TableUnits = TableUnits()) -> None:
    for axis, value in zip("xyz", xyz, strict=True):
        if abs(value) > _MAX_LENGTH:
            written = value / units.factor("a")
            raise DataError(f"{axis}: {_too_long(written, units)}", file=where, column=key)


def read_dh_table(
    source,
    convention: str | None = None,
    *,
    name: str | None = None,
    base: np.ndarray | Mapping | None = None,
    flange: np.ndarray | Mapping | None = None,
    units: Mapping[str, str] | None = None,
) -> DHTable:
    """Read and check a DH table.

    Args:
        source: a ``.csv`` / ``.yaml`` file, a list of row mappings, a YAML-like mapping
            with ``joints``, a pandas DataFrame, or a :class:`DHTable` (returned checked).
        convention: ``"dh"`` or ``"mdh"``; required unless the YAML file states it (and
            must then agree with it).
        name: robot name (default the file's ``name``, else the file stem).
        base, flange: ``(4, 4)`` [m] or ``{xyz, rpy}`` (the table's units), replacing
            the file's.
        units: ``{"length": "mm", "angle": "deg"}`` (either key; default m and rad):
            the units the table is written in (:class:`TableUnits`), as a YAML file's
            ``units`` may state them; the table returned is in m, rad, kg.

    Raises:
        DataError: naming the file, row (1-based, in table order) and column.
    """
    if isinstance(source, DHTable):
        return source
    where = os.fspath(source) if isinstance(source, (str, os.PathLike)) else "<table>"
    records, head = _records(source, where)
    for i, r in enumerate(records, start=1):  # before the convention: the file is wrong
        if not isinstance(r, Mapping):
            raise DataError(
                f"found {r!r} where a row (a mapping of column: value) belongs; {_LAYOUT}",
                file=where,
                row=i,
            )
    stated = head.get("convention")
    if stated is not None and str(stated).lower() not in CONVENTIONS:
        raise DataError(f"convention {stated!r}: write dh or mdh", file=where, column="convention")
    if convention is not None and str(convention).lower() not in CONVENTIONS:
        raise DataError(f"convention {convention!r}: give dh or mdh", file=where)
    if convention is None and stated is None:
        raise DataError(
            "the axis convention is not given: pass convention='dh' or 'mdh' "
            "(--convention dh|mdh), or write 'convention:' in the YAML file",
            file=where,
            column="convention",
        )
    conv = str(convention or stated).lower()
    if stated is not None and str(stated).lower() != conv:
        raise DataError(
            f"the file states convention {stated!r}, but {convention!r} was given",
            file=where,
            column="convention",
        )
    table_units = TableUnits.parse(units, head.get("units"), where)
    if not records:
        raise DataError("the DH table has no rows", file=where)
    keys = set().union(*(r.keys() for r in records))
    for i, r in enumerate(records, start=1):
        optional = ("lower", "upper") if str(r.get("type", "")).strip() == "continuous" else ()
        missing = [c for c in DH_COLUMNS if c not in r and c not in optional]
        if missing:
            header = missing[0] not in keys  # absent from the CSV header / every row
            raise DataError(
                f"missing column{' in the header' if header else ''} (a DH table needs "
                f"{', '.join(DH_COLUMNS)})",
                file=where,
                row=None if header else i,
                column=missing[0],
            )
    inertial = any(k in keys for k in INERTIA_COLUMNS)
    parsed = [_row(r, where, i, inertial, table_units) for i, r in enumerate(records, start=1)]
    names = [p[0] for p in parsed]
    for i, n in enumerate(names[1:], start=2):
        if n in names[: i - 1]:
            raise DataError(f"joint name {n!r} appears twice", file=where, row=i, column="name")
    return DHTable(
        convention=conv,
        rows=np.array([p[2] for p in parsed], dtype=np.float64),
        names=names,
        types=[p[1] for p in parsed],
        lower=np.array([p[3] for p in parsed]),
        upper=np.array([p[4] for p in parsed]),
        inertial=np.array([p[5] for p in parsed]) if inertial else None,
        base=_frame(base if base is not None else head.get("base"), "base", where, table_units),
        flange=_frame(
            flange if flange is not None else head.get("flange"), "flange", where, table_units
        ),
        name=str(name or head.get("name") or (Path(where).stem if where != "<table>" else "dh")),
        source=where,
    )

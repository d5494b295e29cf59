"""Column-mapping import: any tracker or robot export -> the measured pose table.

A *column map* says which source column holds which table column (contract section
1), in which unit, how the file is written (separator, decimal mark, lines before the
header) and how orientation is given (Euler angles in any scipy sequence, or a
quaternion in any component order). Output units are the table's: joints [rad, m for
prismatic], ``x, y, z`` [m], ``qw, qx, qy, qz`` (unit, ``w >= 0``), ``t`` [s],
``temperature`` [°C], ``payload`` [kg].

Example: a Leica-style export with ``;`` separator, ``,`` decimal, two comment lines,
positions in mm, Euler angles in degrees (intrinsic XYZ), joints in degrees, a time
column in ms::

    # spec.json (the same keys work in YAML)
    {
      "separator": ";", "decimal": ",", "skip_lines": 2,
      "units": {"length": "mm", "angle": "deg"},
      "columns": {
        "x": "X", "y": "Y", "z": "Z",
        "shoulder_pan_joint": "J1", "shoulder_lift_joint": "J2", "elbow_joint": "J3",
        "wrist_1_joint": "J4", "wrist_2_joint": "J5", "wrist_3_joint": "J6",
        "e1": "Rx", "e2": "Ry", "e3": "Rz",
        "t": "Time [ms]", "temperature": "Air temp"
      },
      "euler": "XYZ",
      "keep": ["Std X"]
    }

    hybrid-pk import columns export.csv --map spec.json --out table.csv

The same map written inline (one ``TARGET=SOURCE`` per item, separated by commas)::

    hybrid-pk import columns export.csv --sep ';' --decimal , --skip-lines 2 \\
        --euler XYZ --map "x=X[mm],y=Y[mm],z=Z[mm],e1=Rx[deg],e2=Ry[deg],e3=Rz[deg],\\
        shoulder_pan_joint=J1[deg],...,t=Time [ms][ms]" --out table.csv

Grammar of a SOURCE: ``COLUMN`` (table unit, or the default unit of ``units``),
``COLUMN[unit]``, ``COLUMN*FACTOR`` or ``COLUMN/FACTOR`` (a factor into the table
unit, e.g. ``X_mm*0.001``). A header that carries its unit, ``"X [mm]"``, can be
written as ``X [mm]``: when the name before the bracket is not a column but the whole
text is, the whole text is the column and the bracket still gives its unit.

Targets: joint names (any name that is not one of the others; the joint renames),
``x, y, z``, ``e1, e2, e3`` (Euler angles in the order of the ``euler`` sequence:
upper case intrinsic, lower case extrinsic, e.g. ``XYZ`` = ``Rx(e1) Ry(e2) Rz(e3)``),
``qw, qx, qy, qz`` (quaternion components, from any columns in any order; or
``"quaternion": {"columns": [...], "order": "xyzw"}``), ``t``, ``temperature``,
``payload``. ``"time_format": "datetime"`` reads ``t`` from date-time text (seconds
since the first row).

Units: length ``m mm cm um in``; angle ``rad deg mrad urad``; time ``s ms us ns min
h``; temperature ``C K F``; mass ``kg g lb``.

Every problem is a one-line :class:`~hybrid_pk.errors.DataError` naming the file, the
1-based data row and the source column. With ``skip_bad_rows`` rows with unreadable
cells are left out and listed instead.
"""

from __future__ import annotations

import difflib
import json
import math
import os
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from hybrid_pk.data.measured import SkippedRow
from hybrid_pk.data.table import (
    _cell_problem,
    _check_duplicates,
    _first_long_row,
    _to_float,
    write_frame,
)
from hybrid_pk.errors import DataError

__all__ = [
    "UNITS",
    "ColumnImport",
    "ColumnMap",
    "MappedTable",
    "Source",
    "convert_columns",
    "load_column_map",
    "parse_inline_map",
    "read_mapped",
    "source_columns",
]

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
_TABLE_UNIT = {"length": "m", "angle": "rad", "time": "s", "temperature": "C", "mass": "kg"}
POSITION = ("x", "y", "z")
EULER = ("e1", "e2", "e3")
QUAT = ("qw", "qx", "qy", "qz")
SCALARS = ("t", "temperature", "payload")
_QUANTITY = {
    **dict.fromkeys(POSITION, "length"),
    **dict.fromkeys(EULER, "angle"),
    **dict.fromkeys(QUAT, "unitless"),
    "t": "time",
    "temperature": "temperature",
    "payload": "mass",
}
_SEPARATORS = {"tab": "\t", "\\t": "\t", "whitespace": r"\s+", "space": " "}
# A quaternion further than this from unit norm is not a rounding problem: wrong columns.
QUAT_NORM_TOL = 1e-3
# Positions beyond this [m] after conversion are mm (or worse) written as m.
_MAX_POSITION_M = 50.0
_TWO_PI = 2 * math.pi


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


@dataclass(frozen=True)
class ColumnMap:
    """How to read one export: file format, column sources, orientation convention.

    Attributes:
        columns: target table column -> :class:`Source` (joints keep the spec's order).
        euler: scipy Euler sequence of ``e1, e2, e3``, or None.
        separator, decimal, encoding: text format of the file.
        skip_lines: lines before the header row.
        names: column names when the file has no header row (else None).
        time_format: ``"number"`` or ``"datetime"`` (``t`` from date-time text).
        keep: extra source columns copied unchanged (names kept).
    """

    columns: Mapping[str, Source]
    euler: str | None = None
    separator: str = ","
    decimal: str = "."
    encoding: str = "utf-8-sig"
    skip_lines: int = 0
    names: tuple[str, ...] | None = None
    time_format: str = "number"
    keep: tuple[str, ...] = ()
    defaults: Mapping[str, str] = field(default_factory=dict)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Targets that are joints, in spec order."""
        return tuple(c for c in self.columns if c not in _QUANTITY)

    def validate(self) -> ColumnMap:
        """Check the map for consistency; returns itself.

        Raises:
            DataError: partial position/orientation, Euler angles without a sequence,
                both Euler angles and a quaternion, an unknown sequence.
        """
        have = set(self.columns)
        for group, label in ((POSITION, "position"), (EULER, "Euler angle"), (QUAT, "quaternion")):
            found = [c for c in group if c in have]
            if found and len(found) < len(group):
                missing = [c for c in group if c not in have]
                raise DataError(
                    f"column map: partial {label} columns: found {', '.join(found)} but not "
                    f"{', '.join(missing)}"
                )
        if "e1" in have and "qw" in have:
            raise DataError("column map: give Euler angles (e1..e3) or a quaternion, not both")
        if "e1" in have:
            if self.euler is None:
                raise DataError(
                    'column map: Euler angles e1, e2, e3 need a sequence, e.g. "euler": '
                    '"XYZ" (upper case intrinsic, lower case extrinsic)'
                )
            try:
                Rotation.from_euler(self.euler, [0.0, 0.0, 0.0])
            except ValueError as exc:
                raise DataError(f"column map: Euler sequence {self.euler!r}: {exc}") from None
        if self.time_format not in ("number", "datetime"):
            raise DataError(
                f"column map: time_format must be 'number' or 'datetime', got {self.time_format!r}"
            )
        if self.skip_lines < 0:
            raise DataError(f"column map: skip_lines must be >= 0, got {self.skip_lines}")
        for name, src in self.columns.items():
            quantity = _QUANTITY.get(name, "joint")
            if src.unit is None or quantity == "joint":
                continue
            if quantity == "unitless" or UNITS[src.unit][0] != quantity:
                want = "none" if quantity == "unitless" else f"a {quantity} unit"
                raise DataError(
                    f"column map: {name}={src.column}[{src.unit}]: expected {want}",
                    column=src.column,
                )
        return self


# ----------------------------------------------------------------------------- parsing


def _unit_of(text: str, where: str) -> tuple[str, float, float]:
    unit = text.strip()
    if unit not in UNITS:
        close = difflib.get_close_matches(unit, list(UNITS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise DataError(
            f"column map: unknown unit {unit!r} in {where}{hint}; known: {', '.join(UNITS)}"
        )
    return UNITS[unit]


def _parse_source(target: str, text: str, defaults: Mapping[str, str]) -> Source:
    """``COLUMN``, ``COLUMN[unit]``, ``COLUMN*k``, ``COLUMN/k`` -> :class:`Source`."""
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
        _, scale, offset = _unit_of(m.group(2), where)
        # Keep the full text as an alternative name: the header may carry the unit.
        return Source(m.group(1), m.group(2).strip(), scale, offset, explicit=True)
    quantity = _QUANTITY.get(target, "joint")
    unit = defaults.get("angle" if quantity == "joint" else quantity)
    if unit is not None and quantity != "unitless":
        _, scale, offset = _unit_of(unit, f"units of {target}")
        return Source(text, unit, scale, offset)
    return Source(text)


def _as_str_tuple(value: Any, what: str) -> tuple[str, ...]:
    if isinstance(value, str):
        return tuple(v.strip() for v in value.split(",") if v.strip())
    if isinstance(value, list | tuple):
        return tuple(str(v) for v in value)
    raise DataError(f"column map: {what} must be a list of column names, got {value!r}")


_SPEC_KEYS = {
    "separator",
    "decimal",
    "encoding",
    "skip_lines",
    "names",
    "units",
    "columns",
    "euler",
    "quaternion",
    "time_format",
    "keep",
}


def _from_dict(spec: Mapping[str, Any]) -> ColumnMap:
    unknown = set(spec) - _SPEC_KEYS
    if unknown:
        raise DataError(
            f"column map: unknown key(s) {', '.join(sorted(unknown))}; "
            f"known: {', '.join(sorted(_SPEC_KEYS))}"
        )
    defaults = {str(k): str(v) for k, v in (spec.get("units") or {}).items()}
    for quantity, unit in defaults.items():
        if quantity not in _TABLE_UNIT:
            raise DataError(
                f"column map: units: unknown quantity {quantity!r}; one of {', '.join(_TABLE_UNIT)}"
            )
        if _unit_of(unit, f"units.{quantity}")[0] != quantity:
            raise DataError(f"column map: units.{quantity}: {unit!r} is not a {quantity} unit")
    columns: dict[str, Source] = {}
    raw_columns = spec.get("columns") or {}
    if not isinstance(raw_columns, Mapping):
        raise DataError("column map: 'columns' must map table columns to source columns")
    euler = spec.get("euler")
    if isinstance(euler, Mapping):  # {"sequence": "XYZ", "columns": [...], "unit": "deg"}
        cols = _as_str_tuple(euler.get("columns", ()), "euler.columns")
        if len(cols) != 3:
            raise DataError(f"column map: euler.columns needs 3 columns, got {list(cols)}")
        unit = euler.get("unit")
        raw_columns = dict(raw_columns)
        for target, col in zip(EULER, cols, strict=True):
            raw_columns[target] = f"{col}[{unit}]" if unit else col
        euler = euler.get("sequence")
    quat = spec.get("quaternion")
    if quat is not None:
        if not isinstance(quat, Mapping):
            raise DataError('column map: \'quaternion\' must be {"columns": [...], "order": ...}')
        cols = _as_str_tuple(quat.get("columns", ()), "quaternion.columns")
        order = str(quat.get("order", "wxyz")).lower()
        if sorted(order) != sorted("wxyz") or len(cols) != 4:
            raise DataError(
                f"column map: quaternion needs 4 columns and an order that is a permutation "
                f"of 'wxyz' (e.g. 'xyzw'), got {list(cols)} and {order!r}"
            )
        raw_columns = dict(raw_columns)
        for letter, col in zip(order, cols, strict=True):
            raw_columns[f"q{letter}"] = col
    for target, text in raw_columns.items():
        columns[str(target)] = _parse_source(str(target), str(text), defaults)
    names = spec.get("names")
    sep = str(spec.get("separator", ","))
    return ColumnMap(
        columns=columns,
        euler=None if euler is None else str(euler),
        separator=_SEPARATORS.get(sep, sep),
        decimal=str(spec.get("decimal", ".")),
        encoding=str(spec.get("encoding", "utf-8-sig")),
        skip_lines=int(spec.get("skip_lines", 0)),
        names=None if names is None else _as_str_tuple(names, "names"),
        time_format=str(spec.get("time_format", "number")),
        keep=_as_str_tuple(spec.get("keep", ()), "keep"),
        defaults=defaults,
    ).validate()


def parse_inline_map(text: str, **options: Any) -> ColumnMap:
    """Column map from ``"x=X[mm],y=Y[mm],...,shoulder_pan_joint=J1[deg]"``.

    Args:
        text: ``TARGET=SOURCE`` items separated by commas (module docstring grammar).
        **options: any other key of the JSON spec (``separator``, ``decimal``,
            ``skip_lines``, ``euler``, ``units``, ``keep``, ``time_format``, ...).
    """
    columns: dict[str, str] = {}
    for item in (s for s in text.split(",") if s.strip()):
        target, eq, source = item.partition("=")
        if not eq or not target.strip():
            raise DataError(f"column map: item {item.strip()!r} is not TARGET=SOURCE")
        if target.strip() in columns:
            raise DataError(f"column map: {target.strip()!r} is given twice")
        columns[target.strip()] = source
    if not columns:
        raise DataError("column map: no TARGET=SOURCE items given")
    return _from_dict({**options, "columns": columns})


def load_column_map(spec: str | os.PathLike | Mapping[str, Any], **overrides: Any) -> ColumnMap:
    """A column map from a dict, a ``.json``/``.yaml``/``.yml`` file, or inline text.

    Args:
        spec: the map (see the module docstring).
        **overrides: spec keys that replace the spec's (None values are ignored).
    """
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if isinstance(spec, Mapping):
        return _from_dict({**spec, **overrides})
    text = str(spec)
    path = Path(text)
    if path.suffix.lower() in (".json", ".yaml", ".yml"):
        if not path.is_file():
            raise DataError("column map file not found", file=text)
        raw = path.read_text(encoding="utf-8")
        try:
            if path.suffix.lower() == ".json":
                loaded = json.loads(raw)
            else:
                import yaml  # optional: only YAML maps need it

                loaded = yaml.safe_load(raw)
        except ImportError:
            raise DataError("YAML maps need PyYAML (pip install pyyaml)", file=text) from None
        except Exception as exc:  # json/yaml parse errors carry line and column
            raise DataError(
                f"not a readable map: {' '.join(str(exc).split())}", file=text
            ) from None
        if not isinstance(loaded, Mapping):
            raise DataError("a column map file must hold one object (key: value)", file=text)
        try:
            return _from_dict({**loaded, **overrides})
        except DataError as exc:
            raise DataError(exc.reason, file=text, column=exc.column) from None
    return parse_inline_map(text, **overrides)


# ----------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class MappedTable:
    """Columns read through a :class:`ColumnMap`, in table units.

    Attributes:
        frame: table columns (joints, x..z, qw..qz, t, temperature, payload, kept extras).
        rows: ``(n,)`` 1-based data rows of the source that were kept.
        skipped: rows left out with ``skip_bad_rows``.
        resolved: table column -> the source column it was read from.
    """

    frame: pd.DataFrame
    rows: np.ndarray
    skipped: tuple[SkippedRow, ...] = ()
    resolved: Mapping[str, str] = field(default_factory=dict)


def _read_cells(path: Path, cmap: ColumnMap) -> pd.DataFrame:
    file = str(path)
    if not path.is_file():
        raise DataError("no such file", file=file)
    if path.stat().st_size == 0:
        raise DataError("empty file", file=file)
    try:
        with warnings.catch_warnings():
            # pandas drops the extra fields of a row longer than the header with only
            # a warning: make it the error it is (nothing is dropped silently).
            warnings.simplefilter("error", pd.errors.ParserWarning)
            raw = pd.read_csv(
                path,
                sep=cmap.separator,
                dtype=str,
                keep_default_na=False,
                na_filter=False,
                index_col=False,
                skiprows=cmap.skip_lines,
                header=None if cmap.names else 0,
                names=list(cmap.names) if cmap.names else None,
                encoding=cmap.encoding,
                engine="python" if len(cmap.separator) > 1 else "c",
            )
    except pd.errors.ParserWarning:
        hint = (
            f"check the separator ({cmap.separator!r}), the decimal mark and skip_lines "
            f"({cmap.skip_lines})"
        )
        found = None  # the csv module reads single-character separators only
        if len(cmap.separator) == 1:
            found = _first_long_row(
                path,
                len(cmap.names) if cmap.names else None,
                delimiter=cmap.separator,
                encoding=cmap.encoding,
                skip_lines=cmap.skip_lines,
            )
        if found is None:
            raise DataError(
                f"a data row has more fields than the header; {hint}", file=file
            ) from None
        row, fields, width = found
        raise DataError(
            f"{len(fields)} fields where the header has {width}: a data row has more "
            f"fields than the header; {hint}",
            file=file,
            row=row,
            column=f"field {width + 1}",
        ) from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        found = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", str(exc))
        if found:
            want, line, saw = map(int, found.groups())
            raise DataError(
                f"{saw} fields where the header has {want} (file line {line}); check "
                f"the separator ({cmap.separator!r}) and skip_lines ({cmap.skip_lines})",
                file=file,
            ) from None
        raise DataError(f"not a readable table: {' '.join(str(exc).split())}", file=file) from None
    header = [str(c).strip() for c in raw.columns]
    _check_duplicates(file, header)
    raw.columns = header
    if len(raw) == 0:
        raise DataError("no data rows below the header", file=file)
    return raw


def source_columns(path: str | os.PathLike, cmap: ColumnMap) -> list[str]:
    """Header of ``path`` as ``cmap`` reads it (separator, skipped lines, names)."""
    return list(_read_cells(Path(path), cmap).columns)


def _resolve(src: Source, header: list[str], file: str, target: str) -> str:
    if src.column in header:
        return src.column
    if src.unit is not None:  # "X [mm]": the header carries the unit
        for full in (f"{src.column} [{src.unit}]", f"{src.column}[{src.unit}]"):
            if full in header:
                return full
    close = difflib.get_close_matches(src.column, header, n=1, cutoff=0.6)
    hint = f" (found {close[0]!r}?)" if close else ""
    if len(header) == 1 and any(s in header[0] for s in ";,\t"):
        hint += "; the header is one column: check the separator"
    raise DataError(
        f"missing source column {src.column!r} for {target!r}{hint}; "
        f"found columns: {', '.join(header)}",
        file=file,
        column=src.column,
    )


def _parse_datetime(cells: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    stamps = pd.to_datetime(cells, errors="coerce", format="mixed")
    bad = stamps.isna().to_numpy()
    seconds = np.full(len(cells), np.nan)
    ok = ~bad
    if ok.any():
        first = stamps[ok].iloc[0]
        seconds[ok] = (stamps[ok] - first).dt.total_seconds().to_numpy()
    return seconds, bad


def read_mapped(
    path: str | os.PathLike, cmap: ColumnMap, *, skip_bad_rows: bool = False
) -> MappedTable:
    """Read ``path`` through ``cmap``: table columns in table units.

    Orientation becomes ``qw, qx, qy, qz`` (normalised, ``w >= 0``); a quaternion off
    unit norm by more than :data:`QUAT_NORM_TOL` is an error (wrong columns or order).
    Positions beyond 50 m, or joint columns without a unit that look like degrees,
    are errors that name the unit to write.

    Raises:
        DataError: naming file, 1-based data row and source column.
    """
    path = Path(path)
    file = str(path)
    raw = _read_cells(path, cmap)
    header = list(raw.columns)
    n = len(raw)
    resolved = {t: _resolve(s, header, file, t) for t, s in cmap.columns.items()}
    for col in cmap.keep:
        _resolve(Source(col), header, file, "keep")

    problems: dict[int, tuple[str, str]] = {}
    values: dict[str, np.ndarray] = {}
    for target, src in cmap.columns.items():
        col = resolved[target]
        cells = raw[col].str.strip()
        if target == "t" and cmap.time_format == "datetime":
            v, bad = _parse_datetime(cells)
            for k in np.flatnonzero(bad):
                text = cells.iloc[k]
                problems.setdefault(int(k), (col, f"cannot read {text[:40]!r} as a date-time"))
            values[target] = v * src.scale
            continue
        if cmap.decimal != ".":
            cells = cells.str.replace(cmap.decimal, ".", regex=False)
        v, unparsable = _to_float(cells)
        bad = unparsable | ~np.isfinite(v)
        for k in np.flatnonzero(bad):
            reason = _cell_problem(raw[col].iloc[k], v[k], unparsable[k])
            if unparsable[k] and cmap.decimal == "." and "," in str(raw[col].iloc[k]):
                reason += " (',' decimal? give decimal ',')"
            problems.setdefault(int(k), (col, reason))
        values[target] = src.scale * v + src.offset

    def first_problem() -> None:
        if problems and not skip_bad_rows:
            k = min(problems)
            raise DataError(problems[k][1], file=file, row=k + 1, column=problems[k][0])

    first_problem()
    ok = np.ones(n, bool)
    ok[list(problems)] = False

    # Unit plausibility: whole-column problems, never skipped.
    if "x" in values and ok.any():
        pos = np.stack([values[c][ok] for c in POSITION], -1)
        worst = float(np.abs(pos).max())
        if worst > _MAX_POSITION_M:
            k = int(np.flatnonzero(ok)[np.abs(pos).max(-1).argmax()])
            col = resolved[POSITION[int(np.abs(pos[np.abs(pos).max(-1).argmax()]).argmax())]]
            raise DataError(
                f"position {worst:.6g} m after conversion: the column looks like mm; "
                "write COLUMN[mm] (or units: length: mm)",
                file=file,
                row=k + 1,
                column=col,
            )
    for name in cmap.joint_names:
        src = cmap.columns[name]
        if src.unit is not None or src.scale != 1.0 or not ok.any():
            continue
        v = np.abs(values[name][ok])
        if np.mean(v > _TWO_PI + 0.01) > 0.5:
            k = int(np.flatnonzero(ok)[v.argmax()])
            raise DataError(
                f"joint {name!r} up to {v.max():.4g} without a unit: looks like degrees; "
                f"write {name}={src.column}[deg] (or units: angle: deg)",
                file=file,
                row=k + 1,
                column=resolved[name],
            )

    if "e1" in values and ok.any():
        src = cmap.columns["e1"]
        v = np.abs(np.stack([values[c][ok] for c in EULER]))
        if src.unit is None and src.scale == 1.0 and v.max() > _TWO_PI + 0.01:
            k = int(np.flatnonzero(ok)[v.max(0).argmax()])
            raise DataError(
                f"Euler angle up to {v.max():.4g} without a unit: looks like degrees; write "
                "e1=COLUMN[deg] (or units: angle: deg)",
                file=file,
                row=k + 1,
                column=resolved[EULER[int(v.max(1).argmax())]],
            )

    out: dict[str, np.ndarray] = {name: values[name] for name in cmap.joint_names}
    for c in POSITION:
        if c in values:
            out[c] = values[c]
    if "e1" in values:
        angles = np.stack([values[c] for c in EULER], -1)
        quat = np.full((n, 4), np.nan)
        quat[ok] = Rotation.from_euler(cmap.euler, angles[ok]).as_quat()[:, [3, 0, 1, 2]]
        _store_quat(out, quat)
    elif "qw" in values:
        quat = np.stack([values[c] for c in QUAT], -1)
        norm = np.linalg.norm(quat, axis=-1)
        off = ok & (np.abs(norm - 1) > QUAT_NORM_TOL)
        for k in np.flatnonzero(off):
            problems.setdefault(
                int(k),
                (
                    resolved["qw"],
                    f"quaternion norm {norm[k]:.6g} is not 1 within {QUAT_NORM_TOL:g}: check "
                    "the quaternion columns and their order (wxyz / xyzw)",
                ),
            )
        first_problem()
        ok &= ~off
        _store_quat(out, quat / np.where(norm > 0, norm, 1.0)[:, None])
    for c in SCALARS:
        if c in values:
            out[c] = values[c]
    for col in cmap.keep:
        out[col] = raw[col].to_numpy()

    skipped = tuple(
        SkippedRow(file, k + 1, f"column {c!r}: {reason}")
        for k, (c, reason) in sorted(problems.items())
    )
    if not ok.any():
        raise DataError(
            f"no valid rows: all {n} data rows have problems ({skipped[0].reason})", file=file
        )
    frame = pd.DataFrame(out).loc[ok].reset_index(drop=True)
    rows = np.flatnonzero(ok) + 1
    if "t" in frame:
        t = frame["t"].to_numpy()
        back = np.flatnonzero(np.diff(t) < 0)
        if back.size:
            k = int(back[0]) + 1
            raise DataError(
                f"time decreases from {t[k - 1]:.9g} s (row {rows[k - 1]}) to {t[k]:.9g} s; "
                "t must be monotonic within a file",
                file=file,
                row=int(rows[k]),
                column=resolved["t"],
            )
    return MappedTable(frame, rows, skipped, resolved)


def _store_quat(out: dict[str, np.ndarray], quat: np.ndarray) -> None:
    quat = quat * np.where(quat[:, :1] < 0, -1.0, 1.0)
    out.update({c: quat[:, k] for k, c in enumerate(QUAT)})


# ----------------------------------------------------------------------------- convert


@dataclass(frozen=True)
class ColumnImport:
    """What :func:`convert_columns` did."""

    source: str
    destination: str
    n_rows: int
    columns: tuple[tuple[str, str], ...]  # (table column, source description)
    orientation: str
    skipped: tuple[SkippedRow, ...]

    def summary(self) -> str:
        """A short human summary, one fact per line."""
        lines = [f"{self.source} -> {self.destination}: {self.n_rows} rows"]
        lines += [f"  {dst:<22} <- {src}" for dst, src in self.columns]
        lines.append(f"  orientation: {self.orientation}")
        if self.skipped:
            rows = ", ".join(str(s.row) for s in self.skipped)
            lines.append(f"  skipped {len(self.skipped)} bad row(s): {rows}")
        return "\n".join(lines)


def convert_columns(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    cmap: ColumnMap,
    *,
    skip_bad_rows: bool = False,
) -> ColumnImport:
    """Convert one export to a section-1 table (CSV or Parquet by extension of ``dst``).

    Raises:
        DataError: a map without position or joint columns, or any reading problem.
    """
    if "x" not in cmap.columns:
        raise DataError("column map: x, y, z are required for a measured pose table")
    if not cmap.joint_names:
        raise DataError(
            "column map: no joint columns; map each URDF joint name to its source column"
        )
    table = read_mapped(src, cmap, skip_bad_rows=skip_bad_rows)
    write_frame(dst, table.frame)
    described = []
    for target, s in cmap.columns.items():
        if target in EULER or target in QUAT:
            continue
        described.append((target, replace(s, column=table.resolved[target]).describe()))
    if "e1" in cmap.columns:
        cols = ", ".join(
            replace(cmap.columns[c], column=table.resolved[c]).describe() for c in EULER
        )
        kind = "intrinsic" if cmap.euler.isupper() else "extrinsic"
        orientation = f"Euler {cmap.euler!r} ({kind}) of {cols}"
    elif "qw" in cmap.columns:
        orientation = "quaternion " + ", ".join(f"{c}={cmap.columns[c].column!r}" for c in QUAT)
    else:
        orientation = "none (position only)"
    return ColumnImport(
        str(src), str(dst), len(table.frame), tuple(described), orientation, table.skipped
    )

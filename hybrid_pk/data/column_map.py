"""Column maps: how one export is read (grammar in :mod:`hybrid_pk.data.mapping`).

A map comes from a dict, a JSON or YAML file, or inline ``TARGET=SOURCE`` text; all
three become one validated :class:`ColumnMap`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scipy.spatial.transform import Rotation

from hybrid_pk.data.units import (
    EULER,
    POSITION,
    QUAT,
    TABLE_UNIT,
    TARGET_QUANTITY,
    UNITS,
    Source,
    parse_source,
    unit_of,
)
from hybrid_pk.errors import DataError, not_utf8_error

__all__ = ["ColumnMap", "load_column_map", "parse_inline_map"]

_SEPARATORS = {"tab": "\t", "\\t": "\t", "whitespace": r"\s+", "space": " "}
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
        return tuple(c for c in self.columns if c not in TARGET_QUANTITY)

    def validate(self) -> ColumnMap:
        """Check the map for consistency; returns itself.

        Raises:
            DataError: partial position/orientation, Euler angles without a sequence,
                both Euler angles and a quaternion, an unknown sequence, a unit of the
                wrong quantity, a decimal mark that is not one character or is the
                separator.
        """
        self._check_groups()
        if self.time_format not in ("number", "datetime"):
            raise DataError(
                f"column map: time_format must be 'number' or 'datetime', got {self.time_format!r}"
            )
        if self.skip_lines < 0:
            raise DataError(f"column map: skip_lines must be >= 0, got {self.skip_lines}")
        if len(self.decimal) != 1 or self.decimal == self.separator:
            raise DataError(
                f"column map: decimal {self.decimal!r} must be one character other than the "
                f"separator ({self.separator!r})"
            )
        for name, src in self.columns.items():
            quantity = TARGET_QUANTITY.get(name, "joint")
            if src.unit is None or quantity == "joint":
                continue
            if quantity == "unitless" or UNITS[src.unit][0] != quantity:
                want = "none" if quantity == "unitless" else f"a {quantity} unit"
                raise DataError(
                    f"column map: {name}={src.column}[{src.unit}]: expected {want}",
                    column=src.column,
                )
        return self

    def _check_groups(self) -> None:
        """Position, Euler angles and quaternion complete; one orientation with a sequence."""
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
                    "column map: Euler angles e1, e2, e3 need a sequence, e.g. --euler XYZ "
                    '(a map file: "euler": "XYZ"; upper case intrinsic, lower case extrinsic)'
                )
            try:
                Rotation.from_euler(self.euler, [0.0, 0.0, 0.0])
            except ValueError as exc:
                raise DataError(f"column map: Euler sequence {self.euler!r}: {exc}") from None


# ----------------------------------------------------------------------------- parsing


def _as_str_tuple(value: Any, what: str) -> tuple[str, ...]:
    if isinstance(value, str):
        return tuple(v.strip() for v in value.split(",") if v.strip())
    if isinstance(value, list | tuple):
        return tuple(str(v) for v in value)
    raise DataError(f"column map: {what} must be a list of column names, got {value!r}")


def _default_units(spec: Mapping[str, Any]) -> dict[str, str]:
    """``units``: quantity -> unit of the columns written without one."""
    defaults = {str(k): str(v) for k, v in (spec.get("units") or {}).items()}
    for quantity, unit in defaults.items():
        if quantity not in TABLE_UNIT:
            raise DataError(
                f"column map: units: unknown quantity {quantity!r}; one of {', '.join(TABLE_UNIT)}"
            )
        if unit_of(unit, f"units.{quantity}")[0] != quantity:
            raise DataError(f"column map: units.{quantity}: {unit!r} is not a {quantity} unit")
    return defaults


def _euler_columns(euler: Any, raw: dict[str, Any]) -> Any:
    """Expand ``{"sequence": "XYZ", "columns": [...], "unit": "deg"}`` into ``raw``'s
    ``e1..e3``; returns the sequence."""
    if not isinstance(euler, Mapping):
        return euler
    cols = _as_str_tuple(euler.get("columns", ()), "euler.columns")
    if len(cols) != 3:
        raise DataError(f"column map: euler.columns needs 3 columns, got {list(cols)}")
    unit = euler.get("unit")
    for target, col in zip(EULER, cols, strict=True):
        raw[target] = f"{col}[{unit}]" if unit else col
    return euler.get("sequence")


def _quaternion_columns(quat: Any, raw: dict[str, Any]) -> None:
    """Expand ``{"columns": [...], "order": "xyzw"}`` into ``raw``'s ``qw..qz``."""
    if quat is None:
        return
    if not isinstance(quat, Mapping):
        raise DataError('column map: \'quaternion\' must be {"columns": [...], "order": ...}')
    cols = _as_str_tuple(quat.get("columns", ()), "quaternion.columns")
    order = str(quat.get("order", "wxyz")).lower()
    if sorted(order) != sorted("wxyz") or len(cols) != 4:
        raise DataError(
            f"column map: quaternion needs 4 columns and an order that is a permutation "
            f"of 'wxyz' (e.g. 'xyzw'), got {list(cols)} and {order!r}"
        )
    for letter, col in zip(order, cols, strict=True):
        raw[f"q{letter}"] = col


def _from_dict(spec: Mapping[str, Any]) -> ColumnMap:
    unknown = set(spec) - _SPEC_KEYS
    if unknown:
        raise DataError(
            f"column map: unknown key(s) {', '.join(sorted(unknown))}; "
            f"known: {', '.join(sorted(_SPEC_KEYS))}"
        )
    defaults = _default_units(spec)
    raw_columns = spec.get("columns") or {}
    if not isinstance(raw_columns, Mapping):
        raise DataError("column map: 'columns' must map table columns to source columns")
    raw_columns = dict(raw_columns)
    euler = _euler_columns(spec.get("euler"), raw_columns)
    _quaternion_columns(spec.get("quaternion"), raw_columns)
    columns = {str(t): parse_source(str(t), str(text), defaults) for t, text in raw_columns.items()}
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
        text: ``TARGET=SOURCE`` items separated by commas (grammar in
            :mod:`hybrid_pk.data.mapping`).
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


def _load_map_file(path: Path) -> Mapping[str, Any]:
    text = str(path)
    if not path.is_file():
        raise DataError("column map file not found", file=text)
    try:
        raw = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise not_utf8_error(path, table=False) from None
    try:
        if path.suffix.lower() == ".json":
            loaded = json.loads(raw)
        else:
            import yaml  # optional: only YAML maps need it

            loaded = yaml.safe_load(raw)
    except ImportError:
        raise DataError("YAML maps need PyYAML (pip install pyyaml)", file=text) from None
    except Exception as exc:  # json/yaml parse errors carry line and column
        raise DataError(f"not a readable map: {' '.join(str(exc).split())}", file=text) from None
    if not isinstance(loaded, Mapping):
        raise DataError("a column map file must hold one object (key: value)", file=text)
    return loaded


def load_column_map(spec: str | os.PathLike | Mapping[str, Any], **overrides: Any) -> ColumnMap:
    """A column map from a dict, a ``.json``/``.yaml``/``.yml`` file, or inline text.

    Args:
        spec: the map (grammar in :mod:`hybrid_pk.data.mapping`).
        **overrides: spec keys that replace the spec's (None values are ignored).
    """
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if isinstance(spec, Mapping):
        return _from_dict({**spec, **overrides})
    text = str(spec)
    path = Path(text)
    if path.suffix.lower() in (".json", ".yaml", ".yml"):
        loaded = _load_map_file(path)
        try:
            return _from_dict({**loaded, **overrides})
        except DataError as exc:
            raise DataError(exc.reason, file=text, column=exc.column) from None
    return parse_inline_map(text, **overrides)

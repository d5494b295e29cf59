"""Cell- and row-level checks shared by the table reader and the importers.

Numbers from text cells, the reason a cell cannot be used, header and row-length
checks, the per-row problems of one file (first problem per row wins, so a row is
reported once, at its first bad column) and the time-order check. Every failure is a
one-line :class:`~hybrid_pk.errors.DataError` naming file, 1-based data row and column.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hybrid_pk.data.measured import SkippedRow
from hybrid_pk.errors import DataError

__all__ = [
    "ABSOLUTE_ZERO_C",
    "LIMIT_SLACK",
    "MAX_PAYLOAD_KG",
    "MAX_POSITION_M",
    "MAX_TEMPERATURE_C",
    "RowProblems",
    "cell_problem",
    "check_conditions",
    "check_header_names",
    "check_joint_unit",
    "check_time_order",
    "first_long_row",
    "missing_columns_error",
    "note_joint_limits",
    "numeric_column",
    "refuse_booleans",
    "to_float",
]

# A measured position beyond this [m] is mm (or cm) written as m: a laser tracker measures
# within a few tens of metres (the largest, e.g. Leica AT403, to 160 m diameter, but a
# robot cell is never that far from the instrument).
MAX_POSITION_M = 50.0
# The heaviest industrial arm carries 2.3 t (FANUC M-2000iA/2300): a larger payload [kg]
# is grams written as kg.
MAX_PAYLOAD_KG = 2300.0
# No robot runs at 100 °C (motor windings, grease and encoders are rated far below the
# boiling point of water): a higher temperature [°C] is kelvin (or °F) written as °C.
MAX_TEMPERATURE_C = 100.0
# Absolute zero [°C] (0 K): nothing is colder, so a lower value is no temperature at all.
ABSOLUTE_ZERO_C = -273.15


def _booleans(values: pd.Series) -> bool:
    """True for a column of booleans (a Parquet bool column, with or without nulls)."""
    return pd.api.types.infer_dtype(values, skipna=True) == "boolean"


def refuse_booleans(file: str, values: pd.Series, column: str) -> None:
    """Raise if column ``column`` of ``file`` holds booleans: True is no 1 rad or 1 m,
    and a whole column of them is the wrong column (or type), never a bad row."""
    if _booleans(values):
        raise DataError("boolean, expected numbers", file=file, column=column)


def to_float(values: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """Cells -> ``(floats, unparsable)``; unparsable cells are NaN in ``floats``.
    Booleans are no numbers: every cell of a boolean column is unparsable
    (:func:`refuse_booleans` names the column)."""
    if _booleans(values):
        return np.full(len(values), np.nan), np.ones(len(values), bool)
    if pd.api.types.is_numeric_dtype(values):
        return values.to_numpy(np.float64), np.zeros(len(values), bool)
    cells = values.to_numpy(object)
    try:
        return cells.astype(np.float64), np.zeros(len(cells), bool)
    except (ValueError, TypeError):
        pass
    out = np.full(len(cells), np.nan)
    bad = np.zeros(len(cells), bool)
    for k, cell in enumerate(cells):
        try:
            out[k] = float(cell)
        except (ValueError, TypeError):
            bad[k] = True
    return out, bad


def cell_problem(raw: Any, value: float, unparsable: bool) -> str | None:
    """Why the cell ``raw``, read as ``value``, is not a finite number (None if it is)."""
    if unparsable:
        text = str(raw).strip()
        return "empty value" if not text else f"text {text[:40]!r} in a numeric column"
    if math.isnan(value):
        return "value is NaN" if isinstance(raw, str) else "missing value (NaN)"
    if math.isinf(value):
        return f"value is {value}"
    return None


def check_header_names(file: str, header: Sequence[str]) -> None:
    """Raise at the first column name that appears twice in ``header``."""
    seen: dict[str, int] = {}
    for pos, name in enumerate(header, start=1):
        if name in seen:
            raise DataError(
                f"duplicated header: column {name!r} appears at positions {seen[name]} and {pos}",
                file=file,
                column=name,
            )
        seen[name] = pos


def missing_columns_error(
    file: str,
    missing: Sequence[str],
    found: Sequence[str],
    what: str = "",
    note: str = "",
    hint: str = "",
) -> DataError:
    """``missing {what}column(s) 'a', 'b'{note}; found columns: ...{hint}`` for ``file``."""
    return DataError(
        f"missing {what}column(s) {', '.join(map(repr, missing))}{note}; "
        f"found columns: {', '.join(found)}{hint}",
        file=file,
    )


def first_long_row(
    path: Path,
    width: int | None = None,
    *,
    delimiter: str = ",",
    encoding: str = "utf-8-sig",
    skip_lines: int = 0,
) -> tuple[int, list[str], int] | None:
    """``(data row, its fields, header width)`` of the first data row with more fields
    than the header, or None. Rows are 1-based and counted as pandas does (blank lines
    are not data rows); ``width`` None reads it from the header line after
    ``skip_lines``."""
    with path.open(newline="", encoding=encoding) as fh:
        reader = csv.reader(fh, delimiter=delimiter)
        for _ in range(skip_lines):
            next(reader, None)
        header = next(reader, [])
        width = len(header) if width is None else width
        row = 0
        for fields in reader:
            if not fields:
                continue
            row += 1
            if len(fields) > width:
                return row, fields, width
    return None


def check_time_order(
    file: str, t: np.ndarray, rows: np.ndarray, column: str, noun: str = "time stamp"
) -> None:
    """Raise where ``t`` [s] decreases; ``rows`` are the 1-based data rows of ``t``."""
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        k = int(back[0]) + 1
        raise DataError(
            f"{noun} decreases from {t[k - 1]:.9g} s (row {rows[k - 1]}) to {t[k]:.9g} s; "
            "t must be monotonic within a file",
            file=file,
            row=int(rows[k]),
            column=column,
        )


class RowProblems:
    """Per-row problems of one file of ``n`` data rows: the first problem of a row wins.

    Attributes:
        file: the file, for messages.
        found: 0-based row -> ``(column, reason)``.
    """

    def __init__(self, file: str, n: int) -> None:
        self.file = file
        self.n = n
        self.found: dict[int, tuple[str, str]] = {}

    def add(self, k: int, column: str, reason: str) -> None:
        """Record ``reason`` for 0-based row ``k`` unless the row already has one."""
        self.found.setdefault(int(k), (column, reason))

    def note(self, mask: np.ndarray, column: str, reason: Callable[[int], str]) -> None:
        """Record ``reason(k)`` for every row ``k`` where ``mask`` is True."""
        for k in np.flatnonzero(mask):
            self.add(int(k), column, reason(int(k)))

    def note_cells(
        self, column: str, raw: np.ndarray, values: np.ndarray, unparsable: np.ndarray
    ) -> np.ndarray:
        """Record every cell of ``column`` that is not a finite number; returns that mask."""
        bad = unparsable | ~np.isfinite(values)
        self.note(bad, column, lambda k: cell_problem(raw[k], values[k], unparsable[k]))
        return bad

    def raise_first(self, skip: bool = False) -> None:
        """Raise at the first row with a problem, unless ``skip``."""
        if self.found and not skip:
            k = min(self.found)
            column, reason = self.found[k]
            raise DataError(reason, file=self.file, row=k + 1, column=column)

    def ok(self) -> np.ndarray:
        """``(n,)`` True where a row has no problem so far."""
        ok = np.ones(self.n, bool)
        ok[list(self.found)] = False
        return ok

    def skipped(self) -> tuple[SkippedRow, ...]:
        """The rows with a problem, in row order, as :class:`SkippedRow` records."""
        return tuple(
            SkippedRow(self.file, k + 1, f"column {c!r}: {reason}")
            for k, (c, reason) in sorted(self.found.items())
        )

    def raise_if_none_left(self) -> None:
        """Raise when every row has a problem."""
        if len(self.found) == self.n:
            first = self.skipped()[0].reason
            raise DataError(
                f"no valid rows: all {self.n} data rows have problems (first: {first})",
                file=self.file,
            )


def numeric_column(file: str, values: pd.Series, name: str) -> np.ndarray:
    """The cells of column ``name`` as floats; a DataError at a boolean column or the
    first cell that is not a finite number (file, 1-based row, column)."""
    refuse_booleans(file, values, name)
    out, unparsable = to_float(values)
    for k, (raw, v, bad) in enumerate(zip(values.to_numpy(object), out, unparsable, strict=True)):
        why = cell_problem(raw, float(v), bool(bad))
        if why:
            raise DataError(why, file=file, row=k + 1, column=name)
    return out


def check_conditions(file: str, columns: dict[str, np.ndarray], rows: np.ndarray) -> None:
    """Raise at the first payload below 0 kg or beyond :data:`MAX_PAYLOAD_KG` (grams), or
    temperature beyond :data:`MAX_TEMPERATURE_C` (kelvin, °F) or below
    :data:`ABSOLUTE_ZERO_C` (impossible): a problem of the file, never skipped. ``rows``:
    the 1-based row of each value."""
    checks = (
        ("payload", lambda v: v < 0, "a payload is a mass >= 0 kg"),
        (
            "payload",
            lambda v: v > MAX_PAYLOAD_KG,
            f"looks like grams (no arm carries more than {MAX_PAYLOAD_KG:g} kg); the column "
            "is kg: divide by 1000",
        ),
        (
            "temperature",
            lambda v: v > MAX_TEMPERATURE_C,
            f"looks like kelvin or °F (no robot runs at {MAX_TEMPERATURE_C:g} °C); the column "
            "is °C: subtract 273.15 from kelvin",
        ),
        (
            "temperature",
            lambda v: v < ABSOLUTE_ZERO_C,
            f"below absolute zero ({ABSOLUTE_ZERO_C:g} °C), which no temperature is; the "
            "column is °C",
        ),
    )
    for name, wrong, why in checks:
        if name not in columns:
            continue
        bad = np.flatnonzero(wrong(columns[name]))
        if bad.size:
            k = int(bad[0])
            value = f"{columns[name][k]:g}"
            raise DataError(f"{value}: {why}", file=file, row=int(rows[k]), column=name)


# Slack on joint limits [rad or m] for values written with fewer digits than the URDF.
LIMIT_SLACK = 1e-9
_TWO_PI = 2 * math.pi


def check_joint_unit(
    file: str, name: str, kind: str, lo: float, hi: float, values: np.ndarray, ok: np.ndarray
) -> None:
    """Raise if joint ``name``'s column (of type ``kind``, limits ``lo``, ``hi`` [rad or
    m]) holds degrees (revolute) or mm (prismatic): a file-level problem, never skipped.
    ``ok``: the rows to judge."""
    if not ok.any():
        return
    v = values[ok]
    mag = np.abs(v)
    k = int(np.argmax(mag))
    row = int(np.flatnonzero(ok)[k]) + 1
    if kind == "revolute" and mag[k] > _TWO_PI + 0.01:
        lo = lo if np.isfinite(lo) else -_TWO_PI
        hi = hi if np.isfinite(hi) else _TWO_PI
        rad = np.deg2rad(v)
        if not np.all((rad >= lo - LIMIT_SLACK) & (rad <= hi + LIMIT_SLACK)):
            return  # not plausible as degrees either: the limits check reports the rows
        # A few large values may be typos in a radian column; degrees are large in most
        # rows (or far beyond anything the joint can reach in radians).
        if np.mean(mag > _TWO_PI) > 0.5 or mag[k] > 2 * max(abs(lo), abs(hi)):
            raise DataError(
                f"looks like degrees (max {mag[k]:.1f}); convert to rad "
                f"(limits [{lo:.4g}, {hi:.4g}] rad)",
                file=file,
                row=row,
                column=name,
            )
    if kind != "prismatic" or not (np.isfinite(lo) and np.isfinite(hi)):
        return
    beyond = (v < lo - LIMIT_SLACK) | (v > hi + LIMIT_SLACK)
    m = v / 1000.0
    if np.mean(beyond) > 0.5 and np.all((m >= lo - LIMIT_SLACK) & (m <= hi + LIMIT_SLACK)):
        raise DataError(
            f"looks like mm (max {mag[k]:.1f}); prismatic joints are metres: divide by "
            f"1000 (limits [{lo:.4g}, {hi:.4g}] m)",
            file=file,
            row=row,
            column=name,
        )


def note_joint_limits(
    problems: RowProblems,
    columns: dict[str, np.ndarray],
    joints: Sequence[str],
    lower: Sequence[float],
    upper: Sequence[float],
    types: Sequence[str],
    ok: np.ndarray,
) -> None:
    """Record in ``problems`` the ``ok`` rows whose joint value lies outside the joint's
    limits (``lower``, ``upper`` [rad or m] and ``types`` per joint of ``joints``, each a
    column of ``columns``); continuous joints have none. The slack is
    :data:`LIMIT_SLACK`."""
    for j, name in enumerate(joints):
        lo, hi, kind = lower[j], upper[j], types[j]
        if kind == "continuous":
            continue
        v = columns[name]
        unit = "m" if kind == "prismatic" else "rad"
        out = ok & ((v < lo - LIMIT_SLACK) | (v > hi + LIMIT_SLACK))
        problems.note(
            out,
            name,
            lambda k, v=v, lo=lo, hi=hi, name=name, unit=unit: (
                f"joint {name!r} value {v[k]:.6g} {unit} outside its limits "
                f"[{lo:.6g}, {hi:.6g}] {unit}"
            ),
        )

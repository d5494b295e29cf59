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

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from hybrid_pk.data.cells import MAX_POSITION_M, RowProblems, check_time_order
from hybrid_pk.data.column_map import ColumnMap, load_column_map, parse_inline_map
from hybrid_pk.data.export_cells import convert_cells, read_cells, resolve_column, source_columns
from hybrid_pk.data.files import write_frame
from hybrid_pk.data.measured import SkippedRow
from hybrid_pk.data.units import EULER, POSITION, QUAT, SCALARS, UNITS, Source
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

# A quaternion further than this from unit norm is not a rounding problem: wrong columns.
QUAT_NORM_TOL = 1e-3
_TWO_PI = 2 * math.pi


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


# ----------------------------------------------------------------------------- plausibility


def _check_positions(values, resolved, ok: np.ndarray, file: str) -> None:
    """Positions beyond 50 m after conversion are mm written as m."""
    if "x" not in values or not ok.any():
        return
    pos = np.stack([values[c][ok] for c in POSITION], -1)
    worst = float(np.abs(pos).max())
    if worst > MAX_POSITION_M:
        i = int(np.abs(pos).max(-1).argmax())
        raise DataError(
            f"position {worst:.6g} m after conversion: the column looks like mm; "
            "write COLUMN[mm] (or units: length: mm)",
            file=file,
            row=int(np.flatnonzero(ok)[i]) + 1,
            column=resolved[POSITION[int(np.abs(pos[i]).argmax())]],
        )


def _check_angles(values, cmap: ColumnMap, resolved, ok: np.ndarray, file: str) -> None:
    """Joint and Euler columns without a unit whose values look like degrees."""
    if not ok.any():
        return
    for name in cmap.joint_names:
        src = cmap.columns[name]
        if src.unit is not None or src.scale != 1.0:
            continue
        v = np.abs(values[name][ok])
        if np.mean(v > _TWO_PI + 0.01) > 0.5:
            raise DataError(
                f"joint {name!r} up to {v.max():.4g} without a unit: looks like degrees; "
                f"write {name}={src.column}[deg] (or units: angle: deg)",
                file=file,
                row=int(np.flatnonzero(ok)[v.argmax()]) + 1,
                column=resolved[name],
            )
    if "e1" in values:
        src = cmap.columns["e1"]
        v = np.abs(np.stack([values[c][ok] for c in EULER]))
        if src.unit is None and src.scale == 1.0 and v.max() > _TWO_PI + 0.01:
            raise DataError(
                f"Euler angle up to {v.max():.4g} without a unit: looks like degrees; write "
                "e1=COLUMN[deg] (or units: angle: deg)",
                file=file,
                row=int(np.flatnonzero(ok)[v.max(0).argmax()]) + 1,
                column=resolved[EULER[int(v.max(1).argmax())]],
            )


# ----------------------------------------------------------------------------- table


def _store_quat(out: dict[str, np.ndarray], quat: np.ndarray) -> None:
    quat = quat * np.where(quat[:, :1] < 0, -1.0, 1.0)
    out.update({c: quat[:, k] for k, c in enumerate(QUAT)})


def _orientation(
    values, cmap: ColumnMap, resolved, ok: np.ndarray, problems: RowProblems
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """``qw..qz`` (unit, ``w >= 0``) from Euler angles or a quaternion, and the rows
    still usable (a quaternion off unit norm is a problem of its row)."""
    out: dict[str, np.ndarray] = {}
    if "e1" in values:
        angles = np.stack([values[c] for c in EULER], -1)
        quat = np.full((len(ok), 4), np.nan)
        quat[ok] = Rotation.from_euler(cmap.euler, angles[ok]).as_quat()[:, [3, 0, 1, 2]]
        _store_quat(out, quat)
    elif "qw" in values:
        quat = np.stack([values[c] for c in QUAT], -1)
        norm = np.linalg.norm(quat, axis=-1)
        off = ok & (np.abs(norm - 1) > QUAT_NORM_TOL)
        problems.note(
            off,
            resolved["qw"],
            lambda k: (
                f"quaternion norm {norm[k]:.6g} is not 1 within {QUAT_NORM_TOL:g}: check "
                "the quaternion columns and their order (wxyz / xyzw)"
            ),
        )
        ok = ok & ~off
        _store_quat(out, quat / np.where(norm > 0, norm, 1.0)[:, None])
    return out, ok


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
    raw = read_cells(path, cmap)
    header = list(raw.columns)
    resolved = {t: resolve_column(s, header, file, t) for t, s in cmap.columns.items()}
    for col in cmap.keep:
        resolve_column(Source(col), header, file, "keep")
    problems = RowProblems(file, len(raw))
    values = convert_cells(raw, cmap, resolved, problems)
    problems.raise_first(skip_bad_rows)
    ok = problems.ok()
    # Unit plausibility: whole-column problems, never skipped.
    _check_positions(values, resolved, ok, file)
    _check_angles(values, cmap, resolved, ok, file)

    out = {name: values[name] for name in cmap.joint_names}
    out.update({c: values[c] for c in POSITION if c in values})
    quat, ok = _orientation(values, cmap, resolved, ok, problems)
    problems.raise_first(skip_bad_rows)
    out.update(quat)
    out.update({c: values[c] for c in SCALARS if c in values})
    out.update({col: raw[col].to_numpy() for col in cmap.keep})
    problems.raise_if_none_left()
    frame = pd.DataFrame(out).loc[ok].reset_index(drop=True)
    rows = np.flatnonzero(ok) + 1
    if "t" in frame:
        check_time_order(file, frame["t"].to_numpy(), rows, resolved["t"], noun="time")
    return MappedTable(frame, rows, problems.skipped(), resolved)


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


def _describe_orientation(cmap: ColumnMap, resolved: Mapping[str, str]) -> str:
    if "e1" in cmap.columns:
        cols = ", ".join(replace(cmap.columns[c], column=resolved[c]).describe() for c in EULER)
        kind = "intrinsic" if cmap.euler.isupper() else "extrinsic"
        return f"Euler {cmap.euler!r} ({kind}) of {cols}"
    if "qw" in cmap.columns:
        return "quaternion " + ", ".join(f"{c}={cmap.columns[c].column!r}" for c in QUAT)
    return "none (position only)"


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
    described = tuple(
        (target, replace(s, column=table.resolved[target]).describe())
        for target, s in cmap.columns.items()
        if target not in EULER and target not in QUAT
    )
    orientation = _describe_orientation(cmap, table.resolved)
    return ColumnImport(str(src), str(dst), len(table.frame), described, orientation, table.skipped)

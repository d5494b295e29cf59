"""Measured pose tables (contract section 1): read, validate, write.

One row per measurement, in acquisition order: one column per actuated joint
[rad, m for prismatic joints], the measured point ``x, y, z`` [m], optionally its
orientation ``qw, qx, qy, qz`` (unit quaternion), ``t`` [s], ``temperature`` [°C]
and ``payload`` [kg]. CSV (``,`` separator, ``.`` decimal, header row) or Parquet
(``.parquet``/``.pq``), chosen by extension.

Every problem is a one-line :class:`~hybrid_pk.errors.DataError` that names the
file, the 1-based data row and the column. With ``on_bad_row="skip"`` rows with a
per-row problem are left out and each one is recorded in ``MeasuredData.skipped``
and reported once as a :class:`SkippedRowsWarning`; extra columns are kept out of
the data and reported once as an :class:`IgnoredColumnsWarning`. Nothing is
dropped silently.
"""

from __future__ import annotations

import csv
import difflib
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
import torch

from hybrid_pk.data.measured import (
    OPTIONAL_COLUMNS,
    POSITION_COLUMNS,
    QUAT_COLUMNS,
    MeasuredData,
    SkippedRow,
)
from hybrid_pk.errors import DataError

__all__ = [
    "OPTIONAL_COLUMNS",
    "POSITION_COLUMNS",
    "QUAT_COLUMNS",
    "DataWarning",
    "IgnoredColumnsWarning",
    "MeasuredData",
    "SkippedRow",
    "SkippedRowsWarning",
    "read_table",
    "read_table_for",
    "to_frame",
    "write_frame",
    "write_table",
]

JOINT_TYPES = ("revolute", "continuous", "prismatic")

_CSV_SUFFIXES = (".csv",)
_PARQUET_SUFFIXES = (".parquet", ".pq")
QUAT_NORM_TOL = 1e-6
# Slack on joint limits [rad or m] for values written with fewer digits than the URDF.
_LIMIT_TOL = 1e-9
_TWO_PI = 2 * math.pi


class DataWarning(UserWarning):
    """Something in the input that was accepted but the user should know about."""


class IgnoredColumnsWarning(DataWarning):
    """Extra columns that are not part of the table format and were not read."""


class SkippedRowsWarning(DataWarning):
    """Rows left out because ``on_bad_row="skip"`` was asked for."""


# ----------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class _JointSpec:
    names: tuple[str, ...]
    lower: np.ndarray  # (dof,) [rad or m], -inf where unlimited
    upper: np.ndarray
    types: tuple[str, ...]


def _joint_spec(joint_names, lower, upper, joint_types) -> _JointSpec:
    names = tuple(str(n) for n in joint_names)
    dof = len(names)

    def limits(value, fill: float) -> np.ndarray:
        if value is None:
            return np.full(dof, fill)
        arr = np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value, float)
        if arr.shape != (dof,):
            raise ValueError(f"joint limits have shape {arr.shape}, expected ({dof},)")
        return arr

    types = tuple(joint_types) if joint_types is not None else ("revolute",) * dof
    if len(types) != dof or any(t not in JOINT_TYPES for t in types):
        raise ValueError(f"joint_types must be {dof} of {JOINT_TYPES}, got {list(types)}")
    reserved = set(POSITION_COLUMNS + QUAT_COLUMNS + OPTIONAL_COLUMNS)
    if len(set(names)) != dof or reserved & set(names):
        raise ValueError(f"joint names must be distinct and not one of {sorted(reserved)}")
    return _JointSpec(names, limits(lower, -np.inf), limits(upper, np.inf), types)


def _fail(file: str, message: str, row: int | None = None, column: str | None = None):
    raise DataError(message, file=file, row=row, column=column)


def _load(path: Path) -> pd.DataFrame:
    """Raw cells of a CSV (strings) or Parquet file (typed), after header checks."""
    file = str(path)
    suffix = path.suffix.lower()
    if suffix in _CSV_SUFFIXES:
        if path.stat().st_size == 0:
            _fail(file, "empty file: expected a header row and data rows")
        with path.open(newline="", encoding="utf-8-sig") as fh:
            header = next(csv.reader(fh), [])
        header = [h.strip() for h in header]
        if not any(header):
            _fail(file, "empty file: expected a header row and data rows")
        _check_duplicates(file, header)
        try:
            with warnings.catch_warnings():
                # With index_col=False pandas drops the extra fields of a row longer than
                # the header (when the first data row is) with only a ParserWarning.
                warnings.simplefilter("error", pd.errors.ParserWarning)
                frame = pd.read_csv(
                    path,
                    dtype=str,
                    keep_default_na=False,
                    na_filter=False,
                    index_col=False,
                    encoding="utf-8-sig",
                )
        except (pd.errors.ParserError, pd.errors.ParserWarning, UnicodeDecodeError) as exc:
            if not isinstance(exc, UnicodeDecodeError):
                _check_row_lengths(path, len(header))
            _fail(file, f"not a readable CSV table: {' '.join(str(exc).split())}")
        frame.columns = header
    elif suffix in _PARQUET_SUFFIXES:
        import pyarrow as pa
        import pyarrow.parquet as pq

        try:
            parquet = pq.ParquetFile(path)
        except (pa.ArrowException, OSError) as exc:
            _fail(file, f"not a readable Parquet file: {' '.join(str(exc).split())}")
        _check_duplicates(file, [str(n).strip() for n in parquet.schema_arrow.names])
        frame = parquet.read().to_pandas()
        frame.columns = [str(c).strip() for c in frame.columns]
    else:
        _fail(file, f"unsupported file type {path.suffix!r}; expected .csv, .parquet or .pq")
    if len(frame) == 0:
        _fail(file, "empty file: the header has no data rows below it")
    return frame


def _first_long_row(
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


def _check_row_lengths(path: Path, width: int) -> None:
    """Fail at the first data row with more fields than the header's ``width``, naming
    its first field without a column."""
    found = _first_long_row(path, width)
    if found is not None:
        row, fields, _ = found
        _fail(
            str(path),
            f"{len(fields)} fields where the header has {width}: "
            f"field {width + 1} ({fields[width]!r}) has no column name "
            "(check the separator and the header)",
            row=row,
            column=f"field {width + 1}",
        )


def _check_duplicates(file: str, header: list[str]) -> None:
    seen: dict[str, int] = {}
    for pos, name in enumerate(header, start=1):
        if name in seen:
            _fail(
                file,
                f"duplicated header: column {name!r} appears at positions {seen[name]} and {pos}",
                column=name,
            )
        seen[name] = pos


def _to_float(values: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """Cells -> ``(floats, unparsable)``; unparsable cells are NaN in ``floats``."""
    if pd.api.types.is_numeric_dtype(values) and not pd.api.types.is_bool_dtype(values):
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


def _cell_problem(raw: Any, value: float, unparsable: bool) -> str | None:
    if unparsable:
        text = str(raw).strip()
        return "empty value" if not text else f"text {text[:40]!r} in a numeric column"
    if math.isnan(value):
        return "value is NaN" if isinstance(raw, str) else "missing value (NaN)"
    if math.isinf(value):
        return f"value is {value}"
    return None


class _FilePart(NamedTuple):
    columns: dict[str, np.ndarray]  # kept rows only
    rows: np.ndarray  # (n,) 1-based data rows kept
    skipped: list[SkippedRow]
    ignored: list[str]
    has_joints: bool


def _read_file(path: Path, spec: _JointSpec, skip: bool, require_joints: bool) -> _FilePart:
    file = str(path)
    frame = _load(path)
    found = list(frame.columns)
    present = set(found)

    missing_joints = [n for n in spec.names if n not in present]
    has_joints = len(missing_joints) < len(spec.names) or require_joints or not spec.names
    if has_joints and missing_joints:
        hints = [
            f"{n!r} (found {m[0]!r}?)"
            for n in missing_joints
            if (m := difflib.get_close_matches(n, found, n=1, cutoff=0.8))
        ]
        hint = f"; close matches: {', '.join(hints)}" if hints else ""
        if len(found) == 1 and ";" in found[0]:
            hint += "; the file looks ';'-separated, tables need ','"
        _fail(
            file,
            f"missing joint column(s) {', '.join(map(repr, missing_joints))}; "
            f"found columns: {', '.join(found)}{hint}",
        )
    missing_xyz = [c for c in POSITION_COLUMNS if c not in present]
    if missing_xyz:
        _fail(
            file,
            f"missing position column(s) {', '.join(map(repr, missing_xyz))} [m]; "
            f"found columns: {', '.join(found)}",
        )
    quat_present = [c for c in QUAT_COLUMNS if c in present]
    if quat_present and len(quat_present) < 4:
        absent = [c for c in QUAT_COLUMNS if c not in present]
        _fail(
            file,
            f"partial orientation: found {', '.join(quat_present)} but not {', '.join(absent)}; "
            "give all of qw, qx, qy, qz or none",
            column=absent[0],
        )

    joint_cols = list(spec.names) if has_joints else []
    wanted = joint_cols + list(POSITION_COLUMNS) + quat_present
    wanted += [c for c in OPTIONAL_COLUMNS if c in present]
    ignored = [c for c in found if c not in wanted and c not in spec.names]

    n = len(frame)
    problems: dict[int, tuple[str, str]] = {}  # 0-based row -> (column, reason), first wins

    def note(mask: np.ndarray, column: str, reason) -> None:
        for k in np.flatnonzero(mask):
            problems.setdefault(int(k), (column, reason(int(k))))

    def raise_first() -> None:
        if problems and not skip:
            k = min(problems)
            _fail(file, problems[k][1], row=k + 1, column=problems[k][0])

    columns: dict[str, np.ndarray] = {}
    for col in wanted:
        values, unparsable = _to_float(frame[col])
        columns[col] = values
        raw = frame[col].to_numpy(object)
        bad = unparsable | ~np.isfinite(values)
        note(bad, col, lambda k, r=raw, v=values, u=unparsable: _cell_problem(r[k], v[k], u[k]))
    raise_first()

    ok = np.ones(n, bool)
    ok[list(problems)] = False
    for j, name in enumerate(joint_cols):
        _check_degrees(file, name, spec, j, columns[name], ok)
    for j, name in enumerate(joint_cols):
        lo, hi, kind = spec.lower[j], spec.upper[j], spec.types[j]
        if kind == "continuous":
            continue
        v = columns[name]
        unit = "m" if kind == "prismatic" else "rad"
        out = ok & ((v < lo - _LIMIT_TOL) | (v > hi + _LIMIT_TOL))
        note(
            out,
            name,
            lambda k, v=v, lo=lo, hi=hi, name=name, unit=unit: (
                f"joint {name!r} value {v[k]:.6g} {unit} outside its limits "
                f"[{lo:.6g}, {hi:.6g}] {unit}"
            ),
        )
    if quat_present:
        norm = np.sqrt(sum(columns[c] ** 2 for c in QUAT_COLUMNS))
        off = ok & (np.abs(norm - 1) > QUAT_NORM_TOL)
        note(
            off,
            "qw..qz",
            lambda k: f"quaternion norm {norm[k]:.9g} is not 1 within {QUAT_NORM_TOL:g}",
        )
    raise_first()

    keep = np.ones(n, bool)
    keep[list(problems)] = False
    skipped = [
        SkippedRow(file, k + 1, f"column {c!r}: {reason}")
        for k, (c, reason) in sorted(problems.items())
    ]
    if not keep.any():
        _fail(file, f"no valid rows: all {n} data rows have problems (first: {skipped[0].reason})")
    columns = {c: v[keep] for c, v in columns.items()}
    rows = np.flatnonzero(keep) + 1
    if "t" in columns:
        back = np.flatnonzero(np.diff(columns["t"]) < 0)
        if back.size:
            k = back[0] + 1
            _fail(
                file,
                f"time stamp decreases from {columns['t'][k - 1]:.9g} s (row {rows[k - 1]}) "
                f"to {columns['t'][k]:.9g} s; t must be monotonic within a file",
                row=int(rows[k]),
                column="t",
            )
    return _FilePart(columns, rows, skipped, ignored, has_joints)


def _check_degrees(
    file: str, name: str, spec: _JointSpec, j: int, values: np.ndarray, ok: np.ndarray
) -> None:
    """Raise if a revolute joint column holds degrees: a file-level problem, never skipped."""
    if spec.types[j] != "revolute" or not ok.any():
        return
    v = values[ok]
    mag = np.abs(v)
    k = int(np.argmax(mag))
    if mag[k] <= _TWO_PI + 0.01:
        return
    lo = spec.lower[j] if np.isfinite(spec.lower[j]) else -_TWO_PI
    hi = spec.upper[j] if np.isfinite(spec.upper[j]) else _TWO_PI
    rad = np.deg2rad(v)
    if not np.all((rad >= lo - _LIMIT_TOL) & (rad <= hi + _LIMIT_TOL)):
        return  # not plausible as degrees either: the limits check reports the rows
    # A few large values may be typos in a radian column; degrees are large in most rows
    # (or far beyond anything the joint can reach in radians).
    if np.mean(mag > _TWO_PI) > 0.5 or mag[k] > 2 * max(abs(lo), abs(hi)):
        row = int(np.flatnonzero(ok)[k]) + 1
        _fail(
            file,
            f"looks like degrees (max {mag[k]:.1f}); convert to rad "
            f"(limits [{lo:.4g}, {hi:.4g}] rad)",
            row=row,
            column=name,
        )


def _as_paths(paths) -> list[Path]:
    if isinstance(paths, str | os.PathLike):
        return [Path(paths)]
    out = [Path(p) for p in paths]
    if not out:
        raise ValueError("no input files given")
    return out


def read_table(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    joint_names: Sequence[str],
    lower: Any = None,
    upper: Any = None,
    joint_types: Sequence[str] | None = None,
    n_params: int | None = None,
    on_bad_row: str = "error",
    require_joints: bool = True,
) -> MeasuredData:
    """Read and validate one or several measured pose tables (contract section 1).

    Args:
        paths: one file or several (one campaign split in series; see ``file_index``).
        joint_names: ``dof`` joint column names, exactly as in the URDF.
        lower: ``(dof,)`` lower joint limits [rad or m]; None for no limit.
        upper: ``(dof,)`` upper joint limits [rad or m]; None for no limit.
        joint_types: ``'revolute'``, ``'continuous'`` or ``'prismatic'`` per joint;
            None means all revolute. Continuous joints have no limit or degrees check.
        n_params: number of model parameters; fewer rows than this is an error.
        on_bad_row: ``"error"`` raises at the first bad row; ``"skip"`` leaves out rows
            with a per-row problem (NaN/inf, text, joint limits, non-unit quaternion)
            and records them. File-level problems always raise.
        require_joints: False accepts files without any joint column (IK targets);
            ``q`` is then ``(N, 0)``.

    Returns:
        The rows of all files, in file order then row order.

    Raises:
        DataError: naming file, 1-based data row and column of the problem.
    """
    if on_bad_row not in ("error", "skip"):
        raise ValueError(f"on_bad_row must be 'error' or 'skip', got {on_bad_row!r}")
    spec = _joint_spec(joint_names, lower, upper, joint_types)
    files = _as_paths(paths)
    parts = [_read_file(p, spec, on_bad_row == "skip", require_joints) for p in files]

    first = parts[0]
    for path, part in zip(files[1:], parts[1:], strict=True):
        for label, a, b in (
            ("joint", first.has_joints, part.has_joints),
            ("orientation", "qw" in first.columns, "qw" in part.columns),
            *((c, c in first.columns, c in part.columns) for c in OPTIONAL_COLUMNS),
        ):
            if a != b:
                have, lack = (files[0], path) if a else (path, files[0])
                _fail(
                    str(lack),
                    f"has no {label} column(s) but {have} has; files of one "
                    "campaign need the same columns",
                )

    def stack(cols: Sequence[str]) -> np.ndarray:
        return np.concatenate([np.stack([p.columns[c] for c in cols], -1) for p in parts])

    def optional(col: str) -> torch.Tensor | None:
        if col not in first.columns:
            return None
        return torch.from_numpy(np.concatenate([p.columns[col] for p in parts]))

    names = spec.names if first.has_joints else ()
    n_rows = [len(p.rows) for p in parts]
    data = MeasuredData(
        q=stack(names) if names else np.zeros((sum(n_rows), 0)),
        position=stack(POSITION_COLUMNS),
        quat=stack(QUAT_COLUMNS) if "qw" in first.columns else None,
        joint_names=names,
        file_index=torch.repeat_interleave(torch.arange(len(parts)), torch.tensor(n_rows)),
        rows=torch.as_tensor(np.concatenate([p.rows for p in parts])),
        sources=tuple(str(p) for p in files),
        t=optional("t"),
        temperature=optional("temperature"),
        payload=optional("payload"),
        ignored_columns=tuple(dict.fromkeys(c for p in parts for c in p.ignored)),
        skipped=tuple(s for p in parts for s in p.skipped),
    )
    if n_params is not None and data.n < n_params:
        where = ", ".join(data.sources)
        note = f" ({len(data.skipped)} bad row(s) skipped)" if data.skipped else ""
        _fail(
            where, f"needs at least {n_params} rows for {n_params} parameters, found {data.n}{note}"
        )
    if data.ignored_columns:
        warnings.warn(
            f"ignored extra column(s): {', '.join(data.ignored_columns)}",
            IgnoredColumnsWarning,
            stacklevel=2,
        )
    if data.skipped:
        warnings.warn(data.skipped_summary(), SkippedRowsWarning, stacklevel=2)
    return data


def read_table_for(
    paths: str | os.PathLike | Sequence[str | os.PathLike], robot: Any, **kwargs: Any
) -> MeasuredData:
    """:func:`read_table` with joints, limits and types taken from ``robot``.

    ``robot`` is any object with ``joint_names`` and ``joint_limits`` (``(lower, upper)``),
    and optionally ``joint_types`` and ``n_kinematic_params`` (the default ``n_params``).
    """
    lower, upper = robot.joint_limits
    kwargs.setdefault("n_params", getattr(robot, "n_kinematic_params", None))
    return read_table(
        paths,
        joint_names=list(robot.joint_names),
        lower=lower,
        upper=upper,
        joint_types=getattr(robot, "joint_types", None),
        **kwargs,
    )


# ----------------------------------------------------------------------------- writing


def to_frame(data: MeasuredData) -> pd.DataFrame:
    """The table columns of ``data`` in contract order (joints, x..z, qw..qz, t, ...)."""
    cols: dict[str, np.ndarray] = {}
    q = data.q.detach().cpu().numpy()
    for j, name in enumerate(data.joint_names):
        cols[name] = q[:, j]
    pos = data.position.detach().cpu().numpy()
    cols.update({c: pos[:, k] for k, c in enumerate(POSITION_COLUMNS)})
    if data.quat is not None:
        quat = data.quat.detach().cpu().numpy()
        cols.update({c: quat[:, k] for k, c in enumerate(QUAT_COLUMNS)})
    for name in OPTIONAL_COLUMNS:
        value = getattr(data, name)
        if value is not None:
            cols[name] = value.detach().cpu().numpy()
    return pd.DataFrame(cols)


def write_frame(path: str | os.PathLike, frame: pd.DataFrame) -> Path:
    """Write a table to CSV (shortest round-trip floats) or Parquet, by extension."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in _CSV_SUFFIXES:
        frame.to_csv(path, index=False)  # float64 -> repr: exact on re-read
    elif suffix in _PARQUET_SUFFIXES:
        frame.to_parquet(path, index=False)
    else:
        raise DataError(
            f"unsupported file type {path.suffix!r}; expected .csv, .parquet or .pq", file=str(path)
        )
    return path


def write_table(path: str | os.PathLike, data: MeasuredData) -> Path:
    """Write ``data`` as one table (CSV or Parquet by extension); re-reading is exact.

    The file index of multi-file data is not written: one output file holds all rows.
    """
    return write_frame(path, to_frame(data))

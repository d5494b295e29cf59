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

import difflib
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from hybrid_pk.data.cells import (
    MAX_POSITION_M,
    RowProblems,
    check_conditions,
    check_joint_unit,
    check_time_order,
    missing_columns_error,
    note_joint_limits,
    refuse_booleans,
    to_float,
)
from hybrid_pk.data.files import load_cells, to_frame, write_frame
from hybrid_pk.data.measured import (
    OPTIONAL_COLUMNS,
    POSITION_COLUMNS,
    QUAT_COLUMNS,
    MeasuredData,
    SkippedRow,
)
from hybrid_pk.errors import DataError

__all__ = [
    "DataWarning",
    "IgnoredColumnsWarning",
    "RepeatedRowsWarning",
    "SkippedRowsWarning",
    "read_table",
    "read_table_for",
    "to_frame",
    "write_frame",
    "write_table",
]

JOINT_TYPES = ("revolute", "continuous", "prismatic")

QUAT_NORM_TOL = 1e-6


class DataWarning(UserWarning):
    """Something in the input that was accepted but the user should know about."""


class IgnoredColumnsWarning(DataWarning):
    """Extra columns that are not part of the table format and were not read."""


class SkippedRowsWarning(DataWarning):
    """Rows left out because ``on_bad_row="skip"`` was asked for."""


class RepeatedRowsWarning(DataWarning):
    """A file whose rows are those of an earlier file, value for value (a copy)."""


# ----------------------------------------------------------------------------- one file


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


class _Columns(NamedTuple):
    has_joints: bool
    joints: list[str]  # joint columns read (empty for a file without joints)
    quat: list[str]  # quaternion columns present (all four or none)
    wanted: list[str]  # every column read
    ignored: list[str]  # columns present but not part of the format


def _close_matches(missing: list[str], found: list[str]) -> str:
    """``; close matches: 'j1' (found 'J1'?)`` for the missing names that a found column
    spells in other case (names match exactly) or nearly; empty when none does."""
    hints = []
    for n in missing:
        m = [f for f in found if f.lower() == n.lower()]
        m = m or difflib.get_close_matches(n, found, n=1, cutoff=0.8)
        if m:
            hints.append(f"{n!r} (found {m[0]!r}?)")
    return f"; close matches: {', '.join(hints)}" if hints else ""


def _select_columns(
    file: str, found: list[str], spec: _JointSpec, require_joints: bool
) -> _Columns:
    """The columns to read; raises on missing joints or position, a partial quaternion."""
    present = set(found)
    missing_joints = [n for n in spec.names if n not in present]
    has_joints = len(missing_joints) < len(spec.names) or require_joints or not spec.names
    if has_joints and missing_joints:
        hint = _close_matches(missing_joints, found)
        if len(found) == 1 and ";" in found[0]:
            hint += "; the file looks ';'-separated, tables need ','"
        raise missing_columns_error(file, missing_joints, found, "joint ", hint=hint)
    missing_xyz = [c for c in POSITION_COLUMNS if c not in present]
    if missing_xyz:
        hint = _close_matches(missing_xyz, found)
        raise missing_columns_error(file, missing_xyz, found, "position ", " [m]", hint=hint)
    quat = [c for c in QUAT_COLUMNS if c in present]
    if quat and len(quat) < 4:
        absent = [c for c in QUAT_COLUMNS if c not in present]
        raise DataError(
            f"partial orientation: found {', '.join(quat)} but not {', '.join(absent)}; "
            "give all of qw, qx, qy, qz or none",
            file=file,
            column=absent[0],
        )
    joints = list(spec.names) if has_joints else []
    wanted = joints + list(POSITION_COLUMNS) + quat
    wanted += [c for c in OPTIONAL_COLUMNS if c in present]
    ignored = [c for c in found if c not in wanted and c not in spec.names]
    return _Columns(has_joints, joints, quat, wanted, ignored)


def _check_metres(file: str, columns: dict[str, np.ndarray], ok: np.ndarray) -> None:
    """Raise if the position columns hold mm (or cm): a file-level problem, never skipped."""
    if not ok.any() or any(c not in columns for c in POSITION_COLUMNS):
        return
    pos = np.abs(np.stack([columns[c][ok] for c in POSITION_COLUMNS], -1))
    i, c = np.unravel_index(int(np.argmax(pos)), pos.shape)
    if pos[i, c] > MAX_POSITION_M:
        raise DataError(
            f"position {pos[i, c]:.6g} m: looks like mm (no instrument measures a robot "
            f"beyond {MAX_POSITION_M:g} m); x, y, z are metres: divide by 1000",
            file=file,
            row=int(np.flatnonzero(ok)[i]) + 1,
            column=POSITION_COLUMNS[c],
        )


class _FilePart(NamedTuple):
    columns: dict[str, np.ndarray]  # kept rows only
    rows: np.ndarray  # (n,) 1-based data rows kept
    skipped: tuple[SkippedRow, ...]
    ignored: list[str]
    has_joints: bool


def _read_file(path: Path, spec: _JointSpec, skip: bool, require_joints: bool) -> _FilePart:
    file = str(path)
    frame = load_cells(path)
    select = _select_columns(file, list(frame.columns), spec, require_joints)
    problems = RowProblems(file, len(frame))
    columns: dict[str, np.ndarray] = {}
    for col in select.wanted:
        refuse_booleans(file, frame[col], col)
        columns[col], unparsable = to_float(frame[col])
        problems.note_cells(col, frame[col].to_numpy(object), columns[col], unparsable)
    problems.raise_first(skip)

    ok = problems.ok()
    _check_metres(file, columns, ok)
    check_conditions(file, {c: v[ok] for c, v in columns.items()}, np.flatnonzero(ok) + 1)
    for j, name in enumerate(select.joints):
        check_joint_unit(file, name, spec.types[j], spec.lower[j], spec.upper[j], columns[name], ok)
    note_joint_limits(problems, columns, select.joints, spec.lower, spec.upper, spec.types, ok)
    if select.quat:
        norm = np.sqrt(sum(columns[c] ** 2 for c in QUAT_COLUMNS))
        problems.note(
            ok & (np.abs(norm - 1) > QUAT_NORM_TOL),
            "qw..qz",
            lambda k: f"quaternion norm {norm[k]:.9g} is not 1 within {QUAT_NORM_TOL:g}",
        )
    problems.raise_first(skip)
    problems.raise_if_none_left()

    keep = problems.ok()
    columns = {c: v[keep] for c, v in columns.items()}
    rows = np.flatnonzero(keep) + 1
    if "t" in columns:
        check_time_order(file, columns["t"], rows, "t")
    return _FilePart(columns, rows, problems.skipped(), select.ignored, select.has_joints)


# ----------------------------------------------------------------------------- all files


def _as_paths(paths) -> list[Path]:
    if isinstance(paths, str | os.PathLike):
        return [Path(paths)]
    out = [Path(p) for p in paths]
    if not out:
        raise ValueError("no input files given")
    seen: dict[Path, Path] = {}
    for p in out:  # the same file twice counts each row twice: a slip, not a campaign
        key = p.resolve()
        if key in seen:
            also = "" if str(seen[key]) == str(p) else f" (also as {seen[key]})"
            raise DataError(f"given twice{also}: give each file once", file=str(p))
        seen[key] = p
    return out


def _repeated_files(files: list[Path], parts: list[_FilePart]) -> list[str]:
    """``"B repeats A row for row"`` for each file whose joints and measurements are
    those of an earlier file, value for value: the noise makes two measurements of one
    campaign differ, so such a file is a copy (its rows would count twice)."""
    out = []
    for j, b in enumerate(parts):
        for i in range(j):
            a = parts[i]
            same = set(a.columns) == set(b.columns) and len(a.rows) == len(b.rows)
            cols = [c for c in a.columns if c not in OPTIONAL_COLUMNS]  # joints, measurement
            if same and all(np.array_equal(a.columns[c], b.columns[c]) for c in cols):
                out.append(f"{files[j]} repeats {files[i]} row for row")
                break
    return out


def _check_same_columns(files: list[Path], parts: list[_FilePart]) -> None:
    """Files of one campaign must have the same kinds of columns as the first."""
    first = parts[0]
    for path, part in zip(files[1:], parts[1:], strict=True):
        for label, a, b in (
            ("joint", first.has_joints, part.has_joints),
            ("orientation", "qw" in first.columns, "qw" in part.columns),
            *((c, c in first.columns, c in part.columns) for c in OPTIONAL_COLUMNS),
        ):
            if a != b:
                have, lack = (files[0], path) if a else (path, files[0])
                raise DataError(
                    f"has no {label} column(s) but {have} has; files of one "
                    "campaign need the same columns",
                    file=str(lack),
                )


def _stack(parts: list[_FilePart], files: list[Path], spec: _JointSpec) -> MeasuredData:
    """One :class:`MeasuredData` of the rows of all files, in file order then row order."""
    first = parts[0]

    def stack(cols: Sequence[str]) -> np.ndarray:
        return np.concatenate([np.stack([p.columns[c] for c in cols], -1) for p in parts])

    def optional(col: str) -> torch.Tensor | None:
        if col not in first.columns:
            return None
        return torch.from_numpy(np.concatenate([p.columns[col] for p in parts]))

    names = spec.names if first.has_joints else ()
    n_rows = [len(p.rows) for p in parts]
    return MeasuredData(
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
    _check_same_columns(files, parts)
    for copy in _repeated_files(files, parts):
        warnings.warn(
            f"{copy} (joints and measurements): the same measurements twice? Each row "
            "counts twice in a fit and can sit on both sides of a hold-out",
            RepeatedRowsWarning,
            stacklevel=2,
        )
    data = _stack(parts, files, spec)
    if n_params is not None and data.n < n_params:
        note = f" ({len(data.skipped)} bad row(s) skipped)" if data.skipped else ""
        raise DataError(
            f"needs at least {n_params} rows for {n_params} parameters, found {data.n}{note}",
            file=", ".join(data.sources),
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


def write_table(path: str | os.PathLike, data: MeasuredData) -> Path:
    """Write ``data`` as one table (CSV or Parquet by extension); re-reading is exact.

    The file index of multi-file data is not written: one output file holds all rows.
    """
    return write_frame(path, to_frame(data))

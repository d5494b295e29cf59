"""Joint tables: one row of joint values per pose, no measurement (planned poses, robot
programs).

Same files as the pose tables (CSV with ``,`` and a header row, or Parquet): one column
per joint, named as in the URDF [rad, m for prismatic joints]; other columns are
returned as they are. Every problem is a one-line :class:`~hybrid_pk.errors.DataError`
naming the file, the 1-based data row and the column.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from hybrid_pk.data.cells import (
    LIMIT_SLACK,
    cell_problem,
    check_joint_unit,
    refuse_booleans,
    to_float,
)
from hybrid_pk.data.files import load_cells, write_frame
from hybrid_pk.errors import DataError, missing_file
from hybrid_pk.units import UNITS

__all__ = ["angle_factors", "has_joint_columns", "read_joint_table", "write_joint_table"]


def _load(path: Path) -> pd.DataFrame:
    if not path.is_file():
        raise DataError(missing_file(path), file=str(path))
    return load_cells(path)


def has_joint_columns(path: str | os.PathLike, joint_names: Sequence[str]) -> bool:
    """True when the table at ``path`` has at least one of the joint columns."""
    return any(name in _load(Path(path)).columns for name in joint_names)


def angle_factors(robot, angle_unit: str = "rad") -> np.ndarray:
    """``(dof,)`` per joint: radians per ``angle_unit`` for a revolute or continuous joint
    (a controller's program in degrees), 1 for a prismatic one (metres)."""
    if UNITS.get(angle_unit, ("",))[0] != "angle":
        known = ", ".join(u for u, q in UNITS.items() if q[0] == "angle")
        raise DataError(f"angle unit {angle_unit!r}: one of {known}")
    kinds = getattr(robot, "joint_types", ["revolute"] * len(robot.joint_names))
    return np.array([1.0 if k == "prismatic" else UNITS[angle_unit][1] for k in kinds])


def read_joint_table(
    path: str | os.PathLike, robot, angle_unit: str = "rad"
) -> tuple[Tensor, pd.DataFrame]:
    """Joint values of every row [rad, m], checked against ``robot``'s limits.

    Args:
        path: table with one column per joint of ``robot`` (``joint_names``).
        robot: anything with ``joint_names`` and ``joint_limits`` (and ``joint_types``:
            a revolute column in degrees or a prismatic one in mm is named as such).
        angle_unit: the unit of the revolute columns (``"deg"``: a controller's
            program), converted to rad; prismatic columns are metres.

    Returns:
        ``q (N, dof)`` float64 [rad, m] and the table's other columns.

    Raises:
        DataError: missing joint column, a cell that is not a finite number, a column
            in degrees or mm, or a value outside the joint limits (file, 1-based row and
            column).
    """
    path = Path(path)
    file = str(path)
    frame = _load(path)
    names = list(robot.joint_names)
    missing = [n for n in names if n not in frame.columns]
    if missing:
        hints = [
            f"{n!r} (found {m[0]!r}?)"
            for n in missing
            if (m := difflib.get_close_matches(n, list(frame.columns), n=1, cutoff=0.8))
        ]
        hint = f"; close matches: {', '.join(hints)}" if hints else ""
        raise DataError(
            f"missing joint column(s) {', '.join(map(repr, missing))} [rad, m]; found "
            f"columns: {', '.join(frame.columns)}{hint}",
            file=file,
        )
    lower, upper = (torch.as_tensor(x, dtype=torch.float64).numpy() for x in robot.joint_limits)
    factors = angle_factors(robot, angle_unit)
    q = np.empty((len(frame), len(names)))
    for j, name in enumerate(names):
        refuse_booleans(file, frame[name], name)
        values, unparsable = to_float(frame[name])
        values = values * factors[j]
        bad = ~np.isfinite(values) | unparsable
        if bad.any():
            k = int(np.argmax(bad))
            what = cell_problem(frame[name].iloc[k], values[k], bool(unparsable[k]))
            raise DataError(what, file=file, row=k + 1, column=name)
        kind = robot.joint_types[j] if hasattr(robot, "joint_types") else "revolute"
        if angle_unit == "rad":  # a column in another unit than stated
            check_joint_unit(file, name, kind, lower[j], upper[j], values, ~bad)
        out = (values < lower[j] - LIMIT_SLACK) | (values > upper[j] + LIMIT_SLACK)
        if out.any():
            k = int(np.argmax(out))
            raise DataError(
                f"{values[k] / factors[j]:.6g} lies outside the joint limits "
                f"[{lower[j] / factors[j]:.6g}, {upper[j] / factors[j]:.6g}] (joint values "
                f"are in {angle_unit}, m for prismatic joints)",
                file=file,
                row=k + 1,
                column=name,
            )
        q[:, j] = values
    rest = frame[[c for c in frame.columns if c not in names]]
    return torch.from_numpy(q), rest.reset_index(drop=True)


def write_joint_table(
    path: str | os.PathLike,
    q: Tensor,
    joint_names: Sequence[str],
    extra: pd.DataFrame | None = None,
) -> Path:
    """Write ``q (N, dof)`` as one column per joint, then the ``extra`` columns (CSV with
    round-trip floats, or Parquet, by extension)."""
    frame = pd.DataFrame(q.detach().cpu().to(torch.float64).numpy(), columns=list(joint_names))
    if extra is not None:
        frame = pd.concat([frame, extra.reset_index(drop=True)], axis=1)
    path = Path(path)
    if path.parent and not path.parent.is_dir():
        path.parent.mkdir(parents=True, exist_ok=True)
    return write_frame(path, frame)

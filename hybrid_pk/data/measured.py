"""The measured data value: what :func:`hybrid_pk.data.read_table` returns.

Float64 tensors, one row per measurement; see :class:`MeasuredData` for shapes and
units. Values are immutable: :meth:`MeasuredData.subset` and
:meth:`MeasuredData.concat` return new ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.errors import DataError
from hybrid_pk.geometry import quat_to_matrix, transform

__all__ = [
    "OPTIONAL_COLUMNS",
    "POSITION_COLUMNS",
    "QUAT_COLUMNS",
    "MeasuredData",
    "SkippedRow",
]

POSITION_COLUMNS = ("x", "y", "z")
QUAT_COLUMNS = ("qw", "qx", "qy", "qz")
OPTIONAL_COLUMNS = ("t", "temperature", "payload")


class SkippedRow(NamedTuple):
    """A row left out by ``on_bad_row="skip"``: file, 1-based data row, reason."""

    file: str
    row: int
    reason: str


def _f64(x: Any) -> Tensor:
    return torch.as_tensor(x, dtype=torch.float64)


@dataclass(frozen=True, eq=False)  # tensors have no truth value: compare fields instead
class MeasuredData:
    """A validated measurement campaign (one or several files), float64 tensors.

    Attributes:
        q: ``(N, dof)`` joint values [rad, m for prismatic joints].
        position: ``(N, 3)`` measured point in the measurement frame [m].
        quat: ``(N, 4)`` measured orientation ``(w, x, y, z)``, or None (position only).
        joint_names: the ``dof`` joint column names, in column order of ``q``.
        file_index: ``(N,)`` long, index into ``sources`` of the file a row came from.
        rows: ``(N,)`` long, 1-based data row of each row within its file.
        sources: the input file paths.
        t: ``(N,)`` time stamps [s], or None.
        temperature: ``(N,)`` [°C], or None.
        payload: ``(N,)`` mass at the flange [kg], or None.
        ignored_columns: extra input columns that were not read.
        skipped: every row left out by ``on_bad_row="skip"``.
    """

    q: Tensor
    position: Tensor
    quat: Tensor | None
    joint_names: tuple[str, ...]
    file_index: Tensor
    rows: Tensor
    sources: tuple[str, ...]
    t: Tensor | None = None
    temperature: Tensor | None = None
    payload: Tensor | None = None
    ignored_columns: tuple[str, ...] = ()
    skipped: tuple[SkippedRow, ...] = ()

    def __post_init__(self) -> None:
        # Coerce once here so that every MeasuredData holds float64/long tensors.
        set_ = object.__setattr__
        set_(self, "q", _f64(self.q))
        set_(self, "position", _f64(self.position))
        set_(self, "joint_names", tuple(self.joint_names))
        set_(self, "sources", tuple(str(s) for s in self.sources))
        set_(self, "ignored_columns", tuple(self.ignored_columns))
        set_(self, "skipped", tuple(SkippedRow(*s) for s in self.skipped))
        set_(self, "file_index", torch.as_tensor(self.file_index, dtype=torch.long))
        set_(self, "rows", torch.as_tensor(self.rows, dtype=torch.long))
        for name in ("quat", "t", "temperature", "payload"):
            if getattr(self, name) is not None:
                set_(self, name, _f64(getattr(self, name)))
        n = self.q.shape[0] if self.q.ndim == 2 else -1
        shapes = {
            "q": (self.q, (n, len(self.joint_names))),
            "position": (self.position, (n, 3)),
            "quat": (self.quat, (n, 4)),
            "file_index": (self.file_index, (n,)),
            "rows": (self.rows, (n,)),
            "t": (self.t, (n,)),
            "temperature": (self.temperature, (n,)),
            "payload": (self.payload, (n,)),
        }
        for name, (value, shape) in shapes.items():
            if value is not None and tuple(value.shape) != shape:
                got = tuple(value.shape)
                raise DataError(f"MeasuredData.{name} has shape {got}, expected {shape}")
        fi = self.file_index
        if n > 0 and (int(fi.min()) < 0 or int(fi.max()) >= len(self.sources)):
            raise DataError(f"MeasuredData.file_index must lie in [0, {len(self.sources)})")

    @property
    def n(self) -> int:
        """Number of rows N."""
        return self.q.shape[0]

    @property
    def dof(self) -> int:
        """Number of joint columns."""
        return self.q.shape[1]

    @property
    def has_orientation(self) -> bool:
        """True when the table has measured orientations (``qw, qx, qy, qz``)."""
        return self.quat is not None

    def T_measured(self) -> Tensor:
        """Measured poses ``(N, 4, 4)`` [m]; identity rotation for position-only data."""
        if self.quat is None:
            R = torch.eye(3, dtype=torch.float64).expand(self.n, 3, 3)
        else:
            R = quat_to_matrix(self.quat)
        return transform(R, self.position)

    def subset(self, index: Any) -> MeasuredData:
        """Rows picked by ``index`` (slice, bool mask or integer indices), as a new value."""
        if isinstance(index, Sequence | np.ndarray) and not isinstance(index, Tensor):
            index = torch.as_tensor(np.asarray(index))
        if isinstance(index, Tensor) and index.ndim == 0:
            index = index.reshape(1)
        if isinstance(index, int):
            index = [index]

        def pick(x: Tensor | None) -> Tensor | None:
            return None if x is None else x[index]

        return MeasuredData(
            q=self.q[index],
            position=self.position[index],
            quat=pick(self.quat),
            joint_names=self.joint_names,
            file_index=self.file_index[index],
            rows=self.rows[index],
            sources=self.sources,
            t=pick(self.t),
            temperature=pick(self.temperature),
            payload=pick(self.payload),
            ignored_columns=self.ignored_columns,
            skipped=self.skipped,
        )

    @staticmethod
    def concat(parts: Sequence[MeasuredData]) -> MeasuredData:
        """Rows of several values one after the other; equal source paths share an index.

        Raises:
            DataError: if the parts differ in joint names or in which optional columns
                (orientation, ``t``, ``temperature``, ``payload``) they have.
        """
        if not parts:
            raise DataError("concat needs at least one MeasuredData")
        first = parts[0]
        sources: list[str] = []
        index_parts = []
        for part in parts:
            if part.joint_names != first.joint_names:
                raise DataError(
                    f"cannot concat tables with joints {list(part.joint_names)} and "
                    f"{list(first.joint_names)}"
                )
            for name in ("quat", "t", "temperature", "payload"):
                if (getattr(part, name) is None) != (getattr(first, name) is None):
                    raise DataError(f"cannot concat tables where only some have {name!r}")
            remap = []
            for src in part.sources:
                if src not in sources:
                    sources.append(src)
                remap.append(sources.index(src))
            index_parts.append(torch.as_tensor(remap, dtype=torch.long)[part.file_index])

        def cat(name: str) -> Tensor | None:
            if getattr(first, name) is None:
                return None
            return torch.cat([getattr(p, name) for p in parts])

        return MeasuredData(
            q=torch.cat([p.q for p in parts]),
            position=torch.cat([p.position for p in parts]),
            quat=cat("quat"),
            joint_names=first.joint_names,
            file_index=torch.cat(index_parts),
            rows=torch.cat([p.rows for p in parts]),
            sources=tuple(sources),
            t=cat("t"),
            temperature=cat("temperature"),
            payload=cat("payload"),
            ignored_columns=tuple(dict.fromkeys(c for p in parts for c in p.ignored_columns)),
            skipped=tuple(dict.fromkeys(s for p in parts for s in p.skipped)),
        )

    def skipped_summary(self) -> str:
        """One line: how many rows were skipped, and which rows of which file."""
        if not self.skipped:
            return "no rows skipped"
        by_file: dict[str, list[int]] = {}
        for s in self.skipped:
            by_file.setdefault(s.file, []).append(s.row)
        where = "; ".join(f"{f} rows {', '.join(map(str, r))}" for f, r in by_file.items())
        return f"skipped {len(self.skipped)} bad row(s): {where}"

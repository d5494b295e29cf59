"""A file measured from two set-ups, cut into its parts (``--split-at FILE:ROW``).

The diagnosis names a set-up that moved within a file at a row (a tracker nudged, a tool
re-seated: :mod:`~hybrid_pk.calibration.diagnosis.setup_moves`, or refused beyond 20 mm
by :mod:`~hybrid_pk.calibration.setup_change`). The rows from that row on are then
another set-up: :func:`split_at` makes them a file of their own (``FILE (from row
ROW)``), so that ``--frames-per-file`` gives them frames of their own, without the table
being cut by hand. Every row keeps its row number in the file it came from.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.errors import DataError

__all__ = ["parse_split", "split_all", "split_at", "split_name"]


def split_name(source: str, row: int) -> str:
    """The source name of the part of ``source`` from data row ``row`` on."""
    return f"{source} (from row {row})"


def parse_split(spec: str) -> tuple[str, int]:
    """``FILE:ROW`` -> ``(FILE, ROW)``; a :class:`~hybrid_pk.errors.DataError` naming
    the form otherwise."""
    file, sep, row = spec.rpartition(":")
    if not sep or not file or not row.strip().isdigit() or int(row) < 1:
        raise DataError(
            f"--split-at {spec!r}: expected FILE:ROW, a DATA file and the data row (from "
            "1) where its second set-up starts, e.g. nudged.csv:501"
        )
    return file, int(row)


def split_at(data: MeasuredData, file: str, row: int) -> MeasuredData:
    """``data`` with the rows of ``file`` from data row ``row`` on as a file of their own
    (:func:`split_name`), placed right after ``file`` among the sources.

    Args:
        file: one of ``data.sources``, as given or by its name alone.
        row: the data row (numbered as in the file's errors and warnings) of the first
            row of the new set-up.

    Raises:
        DataError: ``file`` is none of the sources (or more than one by name), or
            ``row`` leaves one part empty.
    """
    matches = [i for i, s in enumerate(data.sources) if s == file]
    if not matches:
        matches = [i for i, s in enumerate(data.sources) if Path(s).name == Path(file).name]
    if len(matches) != 1:
        known = ", ".join(data.sources)
        raise DataError(f"--split-at {file}:{row}: {file} is not one DATA file ({known})")
    k = matches[0]
    mine = data.file_index == k
    later = mine & (data.rows >= row)
    if not later.any() or bool(later.eq(mine).all()):
        first, last = int(data.rows[mine].min()), int(data.rows[mine].max())
        raise DataError(
            f"--split-at {file}:{row}: both parts need rows; the file's rows are {first} .. {last}",
            file=data.sources[k],
            row=row,
        )
    index = data.file_index + (data.file_index > k).long()
    index[later] = k + 1
    sources = (*data.sources[: k + 1], split_name(data.sources[k], row), *data.sources[k + 1 :])
    return replace(data, file_index=index, sources=sources)


def split_all(data: MeasuredData, specs: list[str] | None) -> MeasuredData:
    """``data`` split at every ``FILE:ROW`` of ``specs`` (None: as it is)."""
    for spec in specs or []:
        data = split_at(data, *parse_split(spec))
    return data

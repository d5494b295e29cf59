"""Table files on disk: raw cells of a CSV or Parquet table, and writing one.

CSV: ``,`` separator, ``.`` decimal, one header row, read as text so that every cell
problem can be named; Parquet (``.parquet`` / ``.pq``): typed columns. The format is
chosen by the file extension, for reading and writing alike.
"""

from __future__ import annotations

import csv
import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from hybrid_pk.data.cells import check_header_names, first_long_row
from hybrid_pk.data.measured import (
    OPTIONAL_COLUMNS,
    POSITION_COLUMNS,
    QUAT_COLUMNS,
    MeasuredData,
)
from hybrid_pk.errors import DataError, missing_file, not_utf8_error
from hybrid_pk.output_file import replacing

__all__ = [
    "CSV_SUFFIXES",
    "PARQUET_SUFFIXES",
    "load_cells",
    "read_text_cells",
    "to_frame",
    "write_frame",
]

CSV_SUFFIXES = (".csv",)
PARQUET_SUFFIXES = (".parquet", ".pq")
_UNSUPPORTED = "unsupported file type {!r}; expected .csv, .parquet or .pq"


def load_cells(path: Path) -> pd.DataFrame:
    """Raw cells of a CSV (strings) or Parquet file (typed), after header checks.

    Raises:
        DataError: no such file, an empty file, a duplicated or missing header, a data
            row longer than the header (named by row), an unreadable file, an unknown
            extension.
    """
    if not Path(path).is_file():
        raise DataError(missing_file(path), file=str(path))
    suffix = path.suffix.lower()
    if suffix in CSV_SUFFIXES:
        frame = _load_csv(path)
    elif suffix in PARQUET_SUFFIXES:
        frame = _load_parquet(path)
    else:
        raise DataError(_UNSUPPORTED.format(path.suffix), file=str(path))
    if len(frame) == 0:
        raise DataError("empty file: the header has no data rows below it", file=str(path))
    return frame


def read_text_cells(path: Path, sep: str = ",") -> pd.DataFrame:
    """Every cell of the CSV file ``path`` as text (no missing-value guessing, no index
    column; a byte-order mark skipped); a file that is not UTF-8 is a :class:`DataError`
    naming the row of its first bad byte."""
    try:
        return pd.read_csv(
            path,
            sep=sep,
            dtype=str,
            keep_default_na=False,
            na_filter=False,
            index_col=False,
            encoding="utf-8-sig",
        )
    except UnicodeDecodeError:
        raise not_utf8_error(path) from None


def _load_csv(path: Path) -> pd.DataFrame:
    file = str(path)
    empty = "empty file: expected a header row and data rows"
    if path.stat().st_size == 0:
        raise DataError(empty, file=file)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            header = [h.strip() for h in next(csv.reader(fh), [])]
    except UnicodeDecodeError:
        raise not_utf8_error(path) from None
    if not any(header):
        raise DataError(empty, file=file)
    check_header_names(file, header)
    try:
        with warnings.catch_warnings():
            # With index_col=False pandas drops the extra fields of a row longer than
            # the header (when the first data row is) with only a ParserWarning.
            warnings.simplefilter("error", pd.errors.ParserWarning)
            frame = read_text_cells(path)
    except (pd.errors.ParserError, pd.errors.ParserWarning) as exc:
        _check_row_lengths(path, len(header))
        raise DataError(
            f"not a readable CSV table: {' '.join(str(exc).split())}", file=file
        ) from None
    frame.columns = header
    return frame


def _load_parquet(path: Path) -> pd.DataFrame:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        parquet = pq.ParquetFile(path)
    except (pa.ArrowException, OSError) as exc:
        raise DataError(
            f"not a readable Parquet file: {' '.join(str(exc).split())}", file=str(path)
        ) from None
    check_header_names(str(path), [str(n).strip() for n in parquet.schema_arrow.names])
    frame = parquet.read().to_pandas()
    frame.columns = [str(c).strip() for c in frame.columns]
    return frame


def _check_row_lengths(path: Path, width: int) -> None:
    """Fail at the first data row with more fields than the header's ``width``, naming
    its first field without a column."""
    found = first_long_row(path, width)
    if found is not None:
        row, fields, _ = found
        raise DataError(
            f"{len(fields)} fields where the header has {width}: "
            f"field {width + 1} ({fields[width]!r}) has no column name "
            "(check the separator and the header)",
            file=str(path),
            row=row,
            column=f"field {width + 1}",
        )


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
    if suffix not in CSV_SUFFIXES and suffix not in PARQUET_SUFFIXES:
        raise DataError(_UNSUPPORTED.format(path.suffix), file=str(path))
    with replacing(path) as tmp:
        if suffix in CSV_SUFFIXES:
            frame.to_csv(tmp, index=False)  # float64 -> repr: exact on re-read
        else:
            frame.to_parquet(tmp, index=False)
    return path

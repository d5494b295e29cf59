"""The cells of an export read through a column map, converted to table units.

The first half of :func:`hybrid_pk.data.mapping.read_mapped`: the text cells as the
map's separator, skipped lines and header say, the source column of every target, and
the numbers (or date-times) in table units with every unreadable cell recorded.
"""

from __future__ import annotations

import difflib
import os
import re
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from hybrid_pk.data.cells import (
    RowProblems,
    cell_problem,
    check_header_names,
    first_long_row,
    to_float,
)
from hybrid_pk.data.column_map import ColumnMap
from hybrid_pk.data.units import Source
from hybrid_pk.errors import DataError

__all__ = ["convert_cells", "read_cells", "resolve_column", "source_columns"]


def read_cells(path: Path, cmap: ColumnMap) -> pd.DataFrame:
    """The cells of ``path`` as text, read as ``cmap`` says (separator, skipped lines,
    header or ``names``), after header checks.

    Raises:
        DataError: no file, an empty file, a row longer than the header, duplicated
            column names, no data rows.
    """
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
        raise _long_row_error(path, cmap) from None
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
    check_header_names(file, header)
    raw.columns = header
    if len(raw) == 0:
        raise DataError("no data rows below the header", file=file)
    return raw


def _long_row_error(path: Path, cmap: ColumnMap) -> DataError:
    """The error for a data row with more fields than the header, by row where it can."""
    hint = (
        f"check the separator ({cmap.separator!r}), the decimal mark and skip_lines "
        f"({cmap.skip_lines})"
    )
    found = None  # the csv module reads single-character separators only
    if len(cmap.separator) == 1:
        found = first_long_row(
            path,
            len(cmap.names) if cmap.names else None,
            delimiter=cmap.separator,
            encoding=cmap.encoding,
            skip_lines=cmap.skip_lines,
        )
    if found is None:
        return DataError(f"a data row has more fields than the header; {hint}", file=str(path))
    row, fields, width = found
    return DataError(
        f"{len(fields)} fields where the header has {width}: a data row has more "
        f"fields than the header; {hint}",
        file=str(path),
        row=row,
        column=f"field {width + 1}",
    )


def source_columns(path: str | os.PathLike, cmap: ColumnMap) -> list[str]:
    """Header of ``path`` as ``cmap`` reads it (separator, skipped lines, names)."""
    return list(read_cells(Path(path), cmap).columns)


def resolve_column(src: Source, header: list[str], file: str, target: str) -> str:
    """The header column ``src`` names (``"X [mm]"`` may be written ``X[mm]``)."""
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


def convert_cells(
    raw: pd.DataFrame, cmap: ColumnMap, resolved: Mapping[str, str], problems: RowProblems
) -> dict[str, np.ndarray]:
    """Every mapped column in table units; unreadable cells are recorded in ``problems``."""
    values: dict[str, np.ndarray] = {}
    for target, src in cmap.columns.items():
        col = resolved[target]
        cells = raw[col].str.strip()
        if target == "t" and cmap.time_format == "datetime":
            v, bad = _parse_datetime(cells)
            for k in np.flatnonzero(bad):
                problems.add(k, col, f"cannot read {cells.iloc[k][:40]!r} as a date-time")
            values[target] = v * src.scale
            continue
        if cmap.decimal != ".":
            cells = cells.str.replace(cmap.decimal, ".", regex=False)
        v, unparsable = to_float(cells)
        for k in np.flatnonzero(unparsable | ~np.isfinite(v)):
            reason = cell_problem(raw[col].iloc[k], v[k], unparsable[k])
            if unparsable[k] and cmap.decimal == "." and "," in str(raw[col].iloc[k]):
                reason += " (',' decimal? give decimal ',')"
            problems.add(k, col, reason)
        values[target] = src.scale * v + src.offset
    return values

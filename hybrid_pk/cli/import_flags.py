"""Checks of ``import``'s flags that argparse cannot make alone: values that need another
flag (``--decimal`` against ``--sep``, ``--format`` against ``--out``, ``--offset``
against ``--max-offset``) or the streams read (``--max-offset`` against their times).
Each failure is a usage error naming the flag: one line, exit code 2. Also where the
tables go (``--out``: one table, or a folder of them) and their writing, all or none."""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import numpy as np

from hybrid_pk.cli.options import finite_number
from hybrid_pk.data.files import CSV_SUFFIXES, PARQUET_SUFFIXES
from hybrid_pk.errors import DataError, HybridPKError
from hybrid_pk.output_file import replacing

__all__ = [
    "DEFAULT_MAX_OFFSET_S",
    "MAP_OPTIONS",
    "add_map_options",
    "check_decimal",
    "check_max_offset",
    "check_offset_flags",
    "check_table_format",
    "column_map",
    "destinations",
    "finite_seconds",
    "map_overrides",
    "positive_seconds",
    "write_tables",
]

# [s] Largest |offset| searched by default: a controller and a tracker PC whose clocks
# are set by NTP, or started by hand together, differ by well under a second.
DEFAULT_MAX_OFFSET_S = 1.0

# The extensions of each --format's tables: the table writer picks the type by them.
_SUFFIXES = {"csv": CSV_SUFFIXES, "parquet": PARQUET_SUFFIXES}


def finite_seconds(text: str) -> float:
    """``argparse`` type of ``--offset``: a finite number of seconds (any sign)."""
    return finite_number(text, "a finite time [s]")


def positive_seconds(text: str) -> float:
    """``argparse`` type of ``--max-offset``: a finite time > 0 s (a search half-width)."""
    value = finite_seconds(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite time > 0 s, got {text!r}")
    return value


def check_offset_flags(offset: float | None, max_offset: float | None) -> None:
    """``--max-offset`` bounds the estimation that a given ``--offset`` skips: both given
    means one of them is not what the user thinks."""
    if offset is not None and max_offset is not None:
        raise HybridPKError(
            f"--max-offset {max_offset:g} bounds the search for the offset, which --offset "
            f"{offset:g} skips; give one of them"
        )


def check_max_offset(max_offset: float, t_robot: np.ndarray, t_tracker: np.ndarray) -> None:
    """Refuse a ``--max-offset`` [s] beyond every offset at which the streams overlap
    (tracker time = robot time + offset): the search there finds no sample pair, and
    its grid grows with the bound (1e9 s asked for terabytes)."""
    lo = float(t_tracker[0] - t_robot[-1])
    hi = float(t_tracker[-1] - t_robot[0])
    reach = max(abs(lo), abs(hi))
    if max_offset > reach:
        raise HybridPKError(
            f"--max-offset {max_offset:g} s reaches beyond every offset at which the streams "
            f"overlap: robot t {_span(t_robot)}, tracker t {_span(t_tracker)} overlap at "
            f"offsets {lo:.3f}..{hi:.3f} s; give at most {math.floor(1e3 * reach) / 1e3:.3f} s"
        )


def _span(t: np.ndarray) -> str:
    """A stream's first and last time stamp and its length, for messages."""
    return f"{t[0]:.3f}..{t[-1]:.3f} s ({t[-1] - t[0]:.3g} s long)"


def check_table_format(table_format: str | None, out: Path, n_sources: int) -> None:
    """``--format`` is the type of the tables written into a DST directory; a DST table's
    type is its extension, so a ``--format`` that disagrees with it is refused (it was
    ignored: ``--format parquet --out x.csv`` wrote a CSV)."""
    if table_format is None or n_sources > 1 or out.is_dir():
        return
    suffix = out.suffix.lower()
    if suffix in (*CSV_SUFFIXES, *PARQUET_SUFFIXES) and suffix not in _SUFFIXES[table_format]:
        raise HybridPKError(
            f"--format {table_format} disagrees with --out {out}, a {suffix} table: a table's "
            "type is its extension (--format is the type of the tables written into a DST "
            f"directory); drop --format or name the file *{_SUFFIXES[table_format][0]}"
        )


def check_decimal(args: argparse.Namespace, prefix: str = "") -> None:
    """``--{prefix}decimal``: one character, other than ``--{prefix}sep`` (a number's
    decimal mark that is also the separator splits every number in two)."""
    dest = prefix.replace("-", "_")
    decimal = getattr(args, f"{dest}decimal", None)
    if decimal is None:
        return
    if len(decimal) != 1:
        raise HybridPKError(
            f"--{prefix}decimal {decimal!r}: give the decimal mark, one character (. or ,)"
        )
    if getattr(args, f"{dest}separator", None) == decimal:
        raise HybridPKError(
            f"--{prefix}decimal {decimal!r} is also the field separator (--{prefix}sep); "
            "the two must differ"
        )


def destinations(sources: list[Path], out: Path, table_format: str | None) -> list[Path]:
    """The table each of ``sources`` is written to: ``out`` itself for one source, else
    one table per source in the folder ``out``; refused where one would replace a
    source or another (a usage error naming --out)."""
    check_table_format(table_format, out, len(sources))
    if len(sources) == 1 and not out.is_dir():
        return [out]
    if out.suffix.lower() in (*CSV_SUFFIXES, *PARQUET_SUFFIXES):
        raise DataError(
            f"--out {out} is a table but {len(sources)} sources were given; give a directory "
            "(one table per series: they were measured with different tracker set-ups)"
        )
    dests = [out / f"{src.stem}.{table_format or 'csv'}" for src in sources]
    if len(set(dests)) < len(dests):
        raise DataError("several sources have the same file name; convert them one by one")
    for src, dst in zip(sources, dests, strict=True):
        if dst.exists() and src.exists() and os.path.samefile(src, dst):
            raise DataError(
                f"--out {out}: its table {dst.name} would replace this source; give another "
                "folder or --format parquet",
                file=str(src),
            )
    out.mkdir(parents=True, exist_ok=True)
    return dests


def write_tables(sources: list[Path], dests: list[Path], convert: Callable, robot=None):
    """``convert(source, table)`` of every source to its table, all or none: each into
    a temporary file beside its table, renamed in once every one is converted (and, with
    ``robot``, read back for it). Returns what each ``convert`` returned, its
    ``destination`` the table, and the rows read for ``robot`` (None without)."""
    with ExitStack() as stack:
        temps = [stack.enter_context(replacing(dst)) for dst in dests]
        done = [
            replace(convert(src, tmp), destination=str(dst))
            for src, dst, tmp in zip(sources, dests, temps, strict=True)
        ]
        data = None if robot is None else _validated(temps, dests, robot)
    return done, data


def _validated(temps: list[Path], dests: list[Path], robot):
    """The written tables read for ``robot`` from their temporary files, a problem named
    by the table it will be."""
    from hybrid_pk.cli.common import read_data

    try:
        return read_data(temps, robot)
    except DataError as exc:
        message = str(exc)
        for tmp, dst in zip(temps, dests, strict=True):
            message = message.replace(str(tmp), str(dst))
        raise DataError(message) from None


# File-format options of a column map: (flag, dest, metavar, help); type int for N.
MAP_OPTIONS = (
    ("sep", "separator", "SEP", "field separator: ',' ';' tab whitespace ... (default: the "
     "map's, else ',')"),
    ("decimal", "decimal", "CHAR", "decimal mark"),
    ("skip-lines", "skip_lines", "N", "lines before the header row"),
    ("euler", "euler", "SEQ", "scipy Euler sequence of e1 e2 e3 (XYZ intrinsic, xyz "
     "extrinsic, ZYX, ...)"),
    ("length-unit", "length", "UNIT", "default length unit"),
    ("angle-unit", "angle", "UNIT", "default angle unit"),
)  # fmt: skip


def add_map_options(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """File-format options of a column map; ``prefix`` names them per stream."""
    dest = prefix.replace("-", "_")
    for flag, name, metavar, text in MAP_OPTIONS:
        kind = int if metavar == "N" else str
        parser.add_argument(
            f"--{prefix}{flag}", dest=f"{dest}{name}", type=kind, metavar=metavar, help=text
        )
    parser.add_argument(
        f"--{prefix}time-format",
        dest=f"{dest}time_format",
        choices=("number", "datetime"),
        help="t as numbers (default) or date-time text (seconds since the first row)",
    )


def map_overrides(args: argparse.Namespace, prefix: str = "") -> dict:
    get = lambda name: getattr(args, prefix + name, None)  # noqa: E731
    units = {k: get(k) for k in ("length", "angle") if get(k) is not None}
    out = {k: get(k) for k in ("separator", "decimal", "skip_lines", "euler", "time_format")}
    if units:
        out["units"] = units
    return out


def column_map(spec: str, args: argparse.Namespace, prefix: str = ""):
    from hybrid_pk.data.mapping import load_column_map

    overrides = map_overrides(args, prefix)
    if "units" in overrides and Path(spec).suffix.lower() in (".json", ".yaml", ".yml"):
        # merge with the file's defaults instead of replacing them
        base = load_column_map(spec)
        overrides["units"] = {**base.defaults, **overrides["units"]}
    return load_column_map(spec, **overrides)

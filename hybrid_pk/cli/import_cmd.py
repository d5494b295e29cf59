"""``hybrid-pk import FORMAT SRC... --out DST``: convert other formats to the pose table."""

from __future__ import annotations

import argparse
from pathlib import Path

from hybrid_pk.data.ipa import EULER_SEQUENCES, MEASUREMENT_CONVENTION, convert_ipa
from hybrid_pk.errors import DataError

_TABLE_SUFFIXES = (".csv", ".parquet", ".pq")

_IPA_HELP = """\
Convert files of the published UR10 laser-tracker data set (IPA, Landgraf et al.
2021: ';' separator, ',' decimal) to the measured pose table:

  shoulder_pan_joint ... wrist_3_joint  [rad]   copied
  measurement_x, _y, _z                 [mm]  -> x, y, z [m]
  measurement_rx, _ry, _rz              [deg] -> qw, qx, qy, qz (unit, w >= 0)
  measurement_temperature               [°C]  -> temperature [°C]
  measurement_std_x .. _rz          [mm, deg] -> std_x_mm .. std_rz_deg (extra columns)

The spreadsheet-mangled Timestamp is not written (no t); row order is kept.
One SRC: DST is the output table (.csv, .parquet or .pq). Several SRC (series
measured with the tracker set up anew): DST is a directory that gets one table
per source, named after it; read them together to keep one file index per series.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``import`` command and its formats."""
    parser = subparsers.add_parser(
        "import",
        help="convert measurement files of other formats to the pose table",
        description="Convert measurement files of other formats to the pose table "
        "(joints [rad], x, y, z [m], qw, qx, qy, qz).",
    )
    formats = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    ipa = formats.add_parser(
        "ipa",
        help="UR10 laser-tracker files of the IPA data set",
        description=_IPA_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ipa.add_argument("sources", nargs="+", metavar="SRC", help="IPA measurements_*.csv file(s)")
    ipa.add_argument(
        "--out", required=True, metavar="DST", help="output table, or directory for several SRC"
    )
    ipa.add_argument(
        "--format",
        choices=("csv", "parquet"),
        default="csv",
        dest="table_format",
        help="table type written into a DST directory (default: csv)",
    )
    ipa.add_argument(
        "--convention",
        choices=(*EULER_SEQUENCES, "auto"),
        default=MEASUREMENT_CONVENTION,
        metavar="SEQ",
        help="Euler sequence of measurement_rx,ry,rz [deg] in scipy notation (upper case "
        f"intrinsic, lower case extrinsic), or 'auto' to detect it per file from the "
        f"joint angles (default: {MEASUREMENT_CONVENTION}, verified on the published data)",
    )
    ipa.set_defaults(func=_run_ipa)


def _destinations(sources: list[Path], out: Path, table_format: str) -> list[Path]:
    if len(sources) == 1 and not out.is_dir():
        return [out]
    if out.suffix.lower() in _TABLE_SUFFIXES:
        raise DataError(
            f"--out {out} is a table but {len(sources)} sources were given; give a directory "
            "(one table per series: they were measured with different tracker set-ups)"
        )
    dests = [out / f"{src.stem}.{table_format}" for src in sources]
    if len(set(dests)) < len(dests):
        raise DataError("several sources have the same file name; convert them one by one")
    out.mkdir(parents=True, exist_ok=True)
    return dests


def _run_ipa(args: argparse.Namespace) -> int:
    sources = [Path(s) for s in args.sources]
    for src in sources:
        if not src.is_file():
            raise DataError("no such file", file=str(src))
    for src, dst in zip(
        sources, _destinations(sources, Path(args.out), args.table_format), strict=True
    ):
        print(convert_ipa(src, dst, convention=args.convention).summary())
    return 0

"""``hybrid-pk import FORMAT SRC... --out DST``: convert other formats to the pose table.

Formats: ``ipa`` (the published UR10 laser-tracker files), ``columns`` (any export, by
a column map: :mod:`hybrid_pk.data.mapping`), ``streams`` (a robot joint stream and
a tracker stream with an unknown time offset: :mod:`hybrid_pk.data.streams`) and ``dh``
(a robot's DH table -> URDF: :mod:`hybrid_pk.cli.import_dh`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hybrid_pk.cli import import_dh
from hybrid_pk.cli import import_flags as flags
from hybrid_pk.cli.options import add_out, add_robot, command_parser
from hybrid_pk.data.ipa import EULER_SEQUENCES, MEASUREMENT_CONVENTION, convert_ipa
from hybrid_pk.errors import DataError

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


def register(subparsers: argparse._SubParsersAction, name: str, help: str) -> None:
    """Add the ``import`` command (``name``, ``help`` in the command list) and its formats."""
    parser = subparsers.add_parser(
        name,
        help=help,
        description="Convert measurement files of other formats to the pose table "
        "(joints [rad], x, y, z [m], qw, qx, qy, qz).",
    )
    formats = parser.add_subparsers(dest="format", metavar="FORMAT", required=True)
    for fmt, text, description, add_options in (
        ("ipa", "UR10 laser-tracker files of the IPA data set", _IPA_HELP, _ipa_options),
        (
            "columns",
            "any export, by a column map (units, separators, Euler conventions)",
            _COLUMNS_HELP,
            _columns_options,
        ),
        (
            "streams",
            "dynamic campaign: robot joint stream + tracker stream with a time offset",
            _STREAMS_HELP,
            _streams_options,
        ),
        ("dh", import_dh.TEXT, import_dh.HELP, import_dh.add_options),
    ):
        add_options(command_parser(formats, fmt, help=text, description=description))


def _ipa_options(ipa: argparse.ArgumentParser) -> None:
    _add_sources_and_out(ipa, "IPA measurements_*.csv file(s)")
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


def _add_sources_and_out(parser: argparse.ArgumentParser, sources_help: str) -> None:
    """``SRC...``, ``--out DST`` and ``--format`` of a conversion of files."""
    parser.add_argument("sources", nargs="+", metavar="SRC", help=sources_help)
    add_out(parser, metavar="DST", help="output table, or directory for several SRC", kind="either")
    parser.add_argument(
        "--format",
        choices=("csv", "parquet"),
        dest="table_format",
        help="table type written into a DST directory (default: csv); a DST table's is "
        "its extension",
    )


def _run_ipa(args: argparse.Namespace) -> int:
    sources = [Path(s) for s in args.sources]
    for src in sources:
        if src.is_dir():
            found = sorted(str(p) for p in src.rglob("measurements_*.csv"))
            raise DataError(
                "is a folder; give its IPA measurement files: "
                + (" ".join(found) if found else "none found (measurements_*.csv)"),
                file=str(src),
            )
        if not src.is_file():
            raise DataError("no such file", file=str(src))
    dests = flags.destinations(sources, Path(args.out), args.table_format)
    done, _ = flags.write_tables(
        sources, dests, lambda src, tmp: convert_ipa(src, tmp, convention=args.convention)
    )
    print("\n".join(d.summary() for d in done))
    return 0


# ----------------------------------------------------------------------------- columns

_COLUMNS_HELP = """\
Convert any tracker/robot export to the measured pose table with a column map: which
source column holds which table column, in which unit, and how the file is written.

MAP is a .json/.yaml file or inline TARGET=SOURCE items separated by commas:

  hybrid-pk import columns export.csv --sep ';' --decimal , --skip-lines 2 \\
      --euler XYZ --map "x=X[mm],y=Y[mm],z=Z[mm],e1=Rx[deg],e2=Ry[deg],e3=Rz[deg],\\
      shoulder_pan_joint=J1[deg],shoulder_lift_joint=J2[deg],elbow_joint=J3[deg],\\
      wrist_1_joint=J4[deg],wrist_2_joint=J5[deg],wrist_3_joint=J6[deg],\\
      t=Time[ms],temperature=Temp[C]" --out table.csv

TARGETS  joint names (renames), x y z, e1 e2 e3 (Euler angles of --euler SEQ, in
         sequence order; upper case intrinsic, lower case extrinsic: XYZ means
         Rx(e1) Ry(e2) Rz(e3)), or qw qx qy qz (quaternion from any columns, in any
         order), t, temperature, payload
SOURCE   COLUMN | COLUMN[unit] | COLUMN*FACTOR | COLUMN/FACTOR   (e.g. X_mm*0.001)
         A header with its unit, "X [mm]", may be written X [mm].
UNITS    length m mm cm um in; angle rad deg mrad urad; time s ms us ns min h;
         temperature C K F; mass kg g lb.  Without a unit the table unit (m, rad,
         s, C, kg) or the --length-unit/--angle-unit default is used.

A JSON map holds the same items under "columns" plus the file options:
  {"separator": ";", "decimal": ",", "skip_lines": 2, "units": {"length": "mm"},
   "euler": "XYZ", "columns": {"x": "X", ...},
   "quaternion": {"columns": ["Q1", "Q2", "Q3", "Q4"], "order": "xyzw"},
   "time_format": "datetime", "keep": ["Std X"]}
Options given on the command line replace those of a map file.
"""


def _columns_options(cols: argparse.ArgumentParser) -> None:
    _add_sources_and_out(cols, "export file(s) to convert")
    cols.add_argument(
        "--map", required=True, metavar="MAP", help="column map: .json/.yaml file or inline"
    )
    flags.add_map_options(cols)
    cols.add_argument(
        "--skip-bad-rows",
        action="store_true",
        help="leave out rows with unreadable cells (each reported) instead of stopping",
    )
    add_robot(cols, help="also validate the written table for this robot (joint limits, degrees)")
    cols.set_defaults(func=_run_columns)


def _run_columns(args: argparse.Namespace) -> int:
    from hybrid_pk.data.mapping import convert_columns

    flags.check_decimal(args)
    cmap = flags.column_map(args.map, args)
    sources = [Path(s) for s in args.sources]
    for src in sources:
        if not src.is_file():
            raise DataError("no such file", file=str(src))
    dests = flags.destinations(sources, Path(args.out), args.table_format)
    robot = None
    if args.robot:
        from hybrid_pk.cli.common import load_robot

        robot = load_robot(args.robot)
    done, data = flags.write_tables(
        sources,
        dests,
        lambda src, tmp: convert_columns(src, tmp, cmap, skip_bad_rows=args.skip_bad_rows),
        robot,
    )
    print("\n".join(d.summary() for d in done))
    if data is not None:
        print(f"validated for {robot.name}: {data.n} rows, joints {', '.join(data.joint_names)}")
    return 0


# ----------------------------------------------------------------------------- streams

_STREAMS_HELP = """\
Build the measured pose table of a dynamic campaign (Ojer et al. 2024, section 4.3):
a joint stream from the robot controller (about 110 Hz) and a pose stream from the
laser tracker (about 3 kHz), recorded on two clocks:

    tracker time = robot time + offset

The offset is estimated (speed-profile cross-correlation, then the offset that
minimises the closed-form frame registration residual, scanned over all of
--max-offset) unless --offset is given; a residual over 100 times the noise the
streams show is a warning naming both files. The summary gives the offsets the noise
allows (likelihood ratio 100:1); where they reach beyond one robot sample, or another
offset fits as well (a short or nearly straight path), a warning says the streams do
not determine the offset: record a longer path that turns and changes speed, or give
--offset. A drift of the clocks is fitted at the offset; where it moves the offset by
more than a robot sample across the streams and explains most of the residual, the
table is synchronised with the fitted rate and a note says so (--clock-drift none:
one offset, and a warning with the length of the parts to split the streams into).
The tracker poses are then interpolated at the robot times (positions linearly,
orientations by SLERP); robot rows outside the tracker stream or in a tracker gap
(beam break) are left out and reported. The table keeps t (robot clock, s).
A clock jump inside the streams (the offset stepping between two rows) is a
warning naming the robot stream's row and the offsets before and after it
(significance: two-sided z, Bonferroni over the rows tried, alpha 0.001); the
table keeps one offset: split the streams there.

ROBOT_STREAM: t [s] and one column per joint (names as in the URDF) [rad];
TRACKER_STREAM: t [s], x y z [m], optional qw qx qy qz; a temperature column [°C] of
either stream is carried. Other layouts: give a column map per stream (--robot-map,
--tracker-map; see 'hybrid-pk import columns -h').
"""


def _streams_options(st: argparse.ArgumentParser) -> None:
    st.add_argument("robot_stream", metavar="ROBOT_STREAM", help="joint stream file")
    st.add_argument("tracker_stream", metavar="TRACKER_STREAM", help="tracker stream file")
    add_robot(st, required=True)
    add_out(st, metavar="DST", help="output table (.csv/.parquet)")
    st.add_argument("--robot-map", metavar="MAP", help="column map of the robot stream")
    st.add_argument("--tracker-map", metavar="MAP", help="column map of the tracker stream")
    st.add_argument(
        "--offset",
        type=flags.finite_seconds,
        metavar="S",
        help="known offset [s]; skips the estimation",
    )
    st.add_argument(
        "--max-offset",
        type=flags.positive_seconds,
        metavar="S",
        help=f"largest |offset| searched [s] (default: {flags.DEFAULT_MAX_OFFSET_S:g}; "
        "at most the offsets at which the streams overlap)",
    )
    st.add_argument(
        "--clock-drift",
        choices=("auto", "none"),
        default="auto",
        help="auto: where the clocks drift apart by more than a robot sample across the "
        "streams (and the drift explains most of the residual), synchronise with the "
        "fitted rate; none: keep one offset and warn (default: %(default)s)",
    )
    st.add_argument(
        "--every",
        type=int,
        default=1,
        metavar="K",
        help="keep every K-th robot row of the table (default: 1, all)",
    )
    flags.add_map_options(st, "robot-")
    flags.add_map_options(st, "tracker-")
    st.set_defaults(func=_run_streams)


def _stream_map(spec: str | None, args, prefix: str, default_columns: list[str]):
    from hybrid_pk.data.mapping import parse_inline_map

    if spec is not None:
        return flags.column_map(spec, args, prefix)
    inline = ",".join(f"{c}={c}" for c in default_columns)
    overrides = {k: v for k, v in flags.map_overrides(args, prefix).items() if v is not None}
    return parse_inline_map(inline, **overrides)


def _read_streams(args: argparse.Namespace, names: list[str]):
    """The robot and tracker streams as mapped tables, each checked for its columns."""
    from hybrid_pk.data.cells import check_conditions
    from hybrid_pk.data.mapping import read_mapped

    robot_cols = ["t", *names]
    if args.robot_map is None:  # a temperature column is carried, as from the tracker
        robot_cols += _present(args, "robot_", args.robot_stream, ["temperature"], robot_cols)
    rmap = _stream_map(args.robot_map, args, "robot_", robot_cols)
    rs = read_mapped(args.robot_stream, rmap)
    tracker_cols = ["t", "x", "y", "z"]
    if args.tracker_map is None:
        quat = ["qw", "qx", "qy", "qz"]
        extra = _present(
            args, "tracker_", args.tracker_stream, ["qw", "temperature"], tracker_cols + quat
        )
        tracker_cols += (quat if "qw" in extra else []) + [c for c in extra if c != "qw"]
    tmap = _stream_map(args.tracker_map, args, "tracker_", tracker_cols)
    ts = read_mapped(args.tracker_stream, tmap)
    for label, table, path, needed in (
        ("robot", rs, args.robot_stream, ["t", *names]),
        ("tracker", ts, args.tracker_stream, ["t", "x", "y", "z"]),
    ):
        missing = [c for c in needed if c not in table.frame]
        if missing:
            raise DataError(f"the {label} stream map gives no {', '.join(missing)}", file=str(path))
        _stamps_increase(table, path)
        if "temperature" in table.frame:  # kelvin or °F: one line naming file and row
            temperature = table.frame["temperature"].to_numpy()
            check_conditions(str(path), {"temperature": temperature}, table.rows)
    return rs, ts


def _present(args, prefix: str, path, wanted: list[str], used: list[str]) -> list[str]:
    """Those of ``wanted`` that the stream file's header has; its columns that are
    neither ``used`` nor wanted are named once as not carried."""
    from hybrid_pk.data.mapping import source_columns

    header = source_columns(path, _stream_map(None, args, prefix, ["t"]))
    left = [c for c in header if c not in used and c not in wanted]
    if left:
        print(f"note: {path}: column(s) {', '.join(left)} not carried into the table")
    return [c for c in wanted if c in header]


def _stamps_increase(table, path) -> None:
    """A stream's time stamps strictly increase: a repeated one (a sample logged twice)
    would pair one time with two poses; the error names the file's row."""
    t = table.frame["t"].to_numpy()
    same = (t[1:] <= t[:-1]).nonzero()[0]
    if same.size:
        k = int(same[0]) + 1
        rows = table.rows
        raise DataError(
            f"time stamp {t[k]:.9g} s repeats that of row {int(rows[k - 1])} (a sample "
            "logged twice?); a stream's time stamps must increase",
            file=str(path),
            row=int(rows[k]),
            column="t",
        )


def _run_streams(args: argparse.Namespace) -> int:
    import numpy as np

    from hybrid_pk.cli.common import load_robot
    from hybrid_pk.cli.progress import progress
    from hybrid_pk.data.streams import check_offset, estimate_time_offset, synchronise
    from hybrid_pk.data.table import write_table

    if args.every < 1:
        raise DataError(f"--every must be >= 1, got {args.every}")
    flags.check_offset_flags(args.offset, args.max_offset)
    for prefix in ("robot-", "tracker-"):
        flags.check_decimal(args, prefix)
    robot = load_robot(args.robot)
    names = list(robot.joint_names)
    rs, ts = _read_streams(args, names)
    q = rs.frame[names].to_numpy()
    t_r = rs.frame["t"].to_numpy()
    t_m = ts.frame["t"].to_numpy()
    pos = ts.frame[["x", "y", "z"]].to_numpy()
    quat = ts.frame[["qw", "qx", "qy", "qz"]].to_numpy() if "qw" in ts.frame else None
    print(f"robot stream: {len(t_r)} samples, {_rate(t_r):.1f} Hz, {t_r[-1] - t_r[0]:.1f} s")
    print(f"tracker stream: {len(t_m)} samples, {_rate(t_m):.1f} Hz, {t_m[-1] - t_m[0]:.1f} s")
    source = f"{args.robot_stream}, {args.tracker_stream}"  # what the warnings name
    if args.offset is None:
        if args.max_offset is not None:
            flags.check_max_offset(args.max_offset, t_r, t_m)
        max_offset = args.max_offset or flags.DEFAULT_MAX_OFFSET_S
        with progress("estimate offset") as bar:
            bar.stage("cross-correlation and registration")
            est = estimate_time_offset(t_r, q, t_m, pos, robot, quat=quat, max_offset=max_offset)
        print(est.summary())
        for warning in (est.residual_warning(source), est.ambiguity_warning(source)):
            if warning:
                print(f"warning: {warning}")
        offset, jumps, drift = est.offset, est.jumps, est.drift
    else:
        offset = args.offset
        jumps, drift = check_offset(t_r, q, t_m, pos, robot, offset, quat=quat)
    for jump in jumps:  # the table keeps one offset: the user splits the streams
        print(f"warning: {jump.summary(str(args.robot_stream), rs.rows)}")
    rate, middle = 0.0, None
    if drift is not None and drift.matters:
        corrected = args.clock_drift == "auto"
        line = drift.warning(source, corrected)
        print(f"{'note' if corrected else 'warning'}: {line}")
        if corrected:  # the offset fitted with the rate, at the stream's middle
            offset, rate, middle = drift.offset, drift.rate, drift.middle
    temperature = rs.frame["temperature"].to_numpy() if "temperature" in rs.frame else None
    tracker_temperature = ts.frame["temperature"].to_numpy() if "temperature" in ts.frame else None
    sync = synchronise(
        t_r,
        q,
        t_m,
        pos,
        offset,
        joint_names=names,
        quat=quat,
        temperature=temperature,
        tracker_temperature=tracker_temperature,
        source=str(args.robot_stream),
        robot_rows=rs.rows,
        rate=rate,
        middle=middle,
    )
    data = sync.data
    if args.every > 1:
        data = data.subset(np.arange(0, data.n, args.every))
    write_table(args.out, data)
    print(sync.summary())
    print(f"wrote {data.n} rows to {args.out}")
    return 0


def _rate(t) -> float:
    import numpy as np

    return 1.0 / float(np.median(np.diff(t)))

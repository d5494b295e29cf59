"""``hybrid-pk import dh TABLE --convention dh|mdh --out ROBOT.urdf``: a robot maker's
DH / modified-DH table as a URDF that ``--robot`` (and pinocchio, yourdfpy) read."""

from __future__ import annotations

import argparse
from pathlib import Path

from hybrid_pk.cli.options import add_out
from hybrid_pk.errors import HybridPKError
from hybrid_pk.output_file import write_text
from hybrid_pk.robot.dh import ROOT_LINK, TIP_LINK, dh_urdf
from hybrid_pk.robot.dh_table import CONVENTIONS, DH_COLUMNS, INERTIA_COLUMNS, read_dh_table
from hybrid_pk.units import UNITS

# What a URDF file is named, as ROBOT arguments and export take it.
_URDF_SUFFIXES = (".urdf", ".xml")

TEXT = "a robot maker's DH / modified-DH table (CSV or YAML) -> URDF"
HELP = f"""\
Write the URDF of a Denavit-Hartenberg table, one row per joint in chain order.

Columns (CSV header, or YAML keys of a 'joints' list): {", ".join(DH_COLUMNS)}
  lengths a, d [m] (beyond 5 m: refused as mm); angles alpha, theta [rad] (theta:
  the joint's zero offset); a datasheet's mm and degrees: --length-unit mm
  --angle-unit deg (or 'units: {{length: mm, angle: deg}}' in the YAML);
  type revolute | continuous | prismatic; lower, upper [rad or m].
Optional: beta [rad] (Hayati's tilt about y for parallel consecutive axes);
  {", ".join(INERTIA_COLUMNS)} [kg, m, kg m^2]: the link's inertial in the
  table's frame i, for the statics and compliance effects.
YAML may also state convention, name, base and flange ({{xyz: [m], rpy: [rad]}}).

Conventions (q the joint value, added to theta, or to d for a prismatic joint):
  dh   A_i = Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)   (standard, distal)
  mdh  A_i = Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d)   (Craig's modified; row i
       holds alpha_(i-1), a_(i-1), theta_i, d_i)
T(q) = base A_1 ... A_n flange: the URDF's root link '{ROOT_LINK}' is the frame the
base is given in (frame 0 by default), its end link '{TIP_LINK}' is frame n followed by
the flange transform (frame n by default).
"""


def add_options(parser: argparse.ArgumentParser) -> None:
    """Flags of ``import dh``."""
    parser.add_argument("table", metavar="TABLE", help="DH table, .csv or .yaml")
    parser.add_argument(
        "--convention",
        choices=CONVENTIONS,
        help="dh (standard) or mdh (modified, Craig); required unless the YAML states it",
    )
    parser.add_argument("--name", help="robot name (default: the file's, else its stem)")
    lengths = [u for u, (q, _, _) in UNITS.items() if q == "length"]
    parser.add_argument(
        "--length-unit",
        choices=lengths,
        help="unit of a, d, the centres of mass, prismatic limits and base / flange xyz "
        "(default m; inertias in kg per its square)",
    )
    parser.add_argument(
        "--angle-unit",
        choices=[u for u, (q, _, _) in UNITS.items() if q == "angle"],
        help="unit of alpha, theta, beta, revolute limits and base / flange rpy (default rad)",
    )
    add_out(parser, metavar="ROBOT.urdf", help="URDF file to write")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if Path(args.out).suffix.lower() not in _URDF_SUFFIXES:  # as export checks its FILE
        raise HybridPKError(
            f"--out {args.out}: import dh writes a URDF (XML); name the file "
            f"{' or '.join(f'*{x}' for x in _URDF_SUFFIXES)}"
        )
    given = {"length": args.length_unit, "angle": args.angle_unit}
    units = {k: v for k, v in given.items() if v is not None} or None
    table = read_dh_table(args.table, args.convention, name=args.name, units=units)
    out = write_text(args.out, dh_urdf(table))
    statics = "from the table" if table.inertial is not None else "none (no masses given)"
    print(
        f"{table.name}: {table.n} joints ({table.convention}) from {args.table}; chain "
        f"{ROOT_LINK} -> {TIP_LINK}; statics {statics}"
    )
    print(f"wrote {out}")
    return 0

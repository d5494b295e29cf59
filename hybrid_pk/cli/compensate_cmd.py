"""``hybrid-pk compensate MODEL PROGRAM --out CORRECTED``: a robot program corrected for
the calibrated (or hybrid) model, for a controller that runs its nominal model."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from hybrid_pk.cli.common import data_notes, load_frozen_model
from hybrid_pk.cli.options import (
    add_approach,
    add_frame_set,
    add_model,
    add_out,
)
from hybrid_pk.cli.progress import progress
from hybrid_pk.errors import HybridPKError
from hybrid_pk.ik import IKOptions
from hybrid_pk.ik.compensation import COMPENSATION_BOX, STATUSES, Compensation
from hybrid_pk.ik.conditions import parse_approach
from hybrid_pk.pipelines.compensation import compensate_program, read_program
from hybrid_pk.robot import Robot

_DESCRIPTION = f"""\
Correct a robot program for the real robot: for each PROGRAM row, the joint values
that put the robot, as MODEL describes it (a calibrated model, or a hybrid model with
residual networks), at the pose the controller's nominal model meant.

PROGRAM (.csv or .parquet), one row per target, in program order:
  joint targets   one column per joint [rad, m], computed with the nominal model; or
  target poses    x y z [m] and qw qx qy qz of the flange in the robot base frame
                  (the branch: the nominal solution nearest the previous row's).
  optional        payload [kg], temperature [degC] for models with such effects.

Each row is solved from its nominal joints within --box of them and within the joint
limits, so it stays on the same branch. A model with backlash takes the approach side
of every joint from the order of the corrected program (first row: mid-play) unless
--approach states it (then every row is solved for that side: the program must
approach its targets so).

CORRECTED has one row per PROGRAM row, in order: the joint columns, a joint program's
other columns as they are (e.g. line numbers, speeds), residual_mm and
residual_deg (the model's predicted error at those joints), status, nominal_mm and
nominal_deg (the same for the uncorrected joints) and note. status is one of
{", ".join(STATUSES)}; a row that is not ok keeps its nominal joints and the note
says why (a joint beyond its limit, or no solution within --box): nothing is bent
into the limits silently.

The robot base frame is the one the calibration identified (MODEL's base frame).
The intended pose of a joint row is where the controller's kinematics put the flange:
MODEL's nominal URDF, or --controller FILE when the controller runs another model, such
as the calibrated geometry of 'hybrid-pk export' (a DH / MDH YAML or a URDF): the
program then moves by what that file cannot carry only. Compensating a program of a
controller that runs the exported geometry without --controller corrects the geometry
twice.
"""


# How a user of this command states each condition the IK would otherwise assume.
_FIXES = {
    "approach": "--approach + / - / JOINT=+,JOINT=- states how the robot approaches",
    "temperature": "a temperature column [degC] in PROGRAM states it",
    "payload": "a payload column [kg] in PROGRAM states it",
}
DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk compensate``."""
    add_model(p, help="model file (calibrate or train output): the real robot")
    p.add_argument(
        "program", metavar="PROGRAM", help="joint targets or flange poses, .csv/.parquet"
    )
    add_out(p, metavar="CORRECTED", help="output table, .csv or .parquet")
    p.add_argument(
        "--box",
        type=float,
        default=COMPENSATION_BOX,
        metavar="RAD",
        help=f"largest correction of a joint [rad, m for prismatic] (default {COMPENSATION_BOX})",
    )
    p.add_argument(
        "--tol-mm", type=float, default=1e-3, metavar="MM",
        help="largest predicted position error of an ok row [mm] (default 0.001)",
    )  # fmt: skip
    p.add_argument(
        "--tol-deg", type=float, default=1e-3, metavar="DEG",
        help="largest predicted orientation error of an ok row [deg] (default 0.001)",
    )  # fmt: skip
    p.add_argument(
        "--controller",
        metavar="FILE",
        help="the kinematics the controller runs and the program was computed with: a URDF "
        "or a DH / MDH YAML table, e.g. from 'hybrid-pk export' (then only what that file "
        "cannot carry is corrected); default: MODEL's nominal URDF",
    )
    p.add_argument(
        "--angle-unit",
        choices=("rad", "deg"),
        default="rad",
        help="unit of a joint program's revolute joints, read and written (default rad; a "
        "controller's program: deg); prismatic joints are metres",
    )
    add_frame_set(p)
    add_approach(p, default="the sides of the corrected program's own moves; first row mid-play")


def _summary(comp: Compensation, args, robot, kind: str) -> list[str]:
    n = len(comp.status)
    counts = Counter(comp.status)
    ok = comp.ok
    lines = [f"compensate {args.model} ({robot.name}) on {n} row(s) of {args.program} ({kind})"]
    if bool(ok.any()):
        before, after = comp.nominal_mm[ok], comp.residual_mm[ok]
        lines.append(
            f"predicted error of the ok rows: program joints mean {float(before.mean()):.4g} mm"
            f" / {float(comp.nominal_deg[ok].mean()):.4g} deg (max {float(before.max()):.4g} "
            f"mm) -> corrected max {float(after.max()):.3g} mm / "
            f"{float(comp.residual_deg[ok].max()):.3g} deg; largest joint correction "
            f"{float((comp.q - comp.q_nominal)[ok].abs().max()):.4g} rad"
        )
    lines.append("rows: " + ", ".join(f"{counts[s]} {s}" for s in STATUSES if counts[s]))
    for status in STATUSES[1:]:
        rows = [i for i, s in enumerate(comp.status) if s == status]
        if rows:
            shown = "; ".join(f"row {i + 1}: {comp.note[i]}" for i in rows[:5])
            more = f" (and {len(rows) - 5} more)" if len(rows) > 5 else ""
            # a pose the nominal model cannot reach has no nominal joints to keep
            kept = "joints left empty" if status == "no_nominal_solution" else "nominal joints kept"
            lines.append(f"warning: {len(rows)} row(s) {status}, {kept}: {shown}{more}")
    return lines


def _controller(path: str, robot: Robot) -> Robot:
    """The controller's kinematics (``--controller``): a URDF, or a DH / MDH table that
    states its convention (YAML), with ``robot``'s joints in the same order."""
    if not Path(path).is_file():
        raise HybridPKError(f"--controller: file not found: {path}")
    suffix = Path(path).suffix.lower()
    if suffix == ".csv":
        raise HybridPKError(
            f"--controller: {path}: a CSV DH table does not state its convention; give a "
            f"URDF ('hybrid-pk import dh {path} --convention dh|mdh --out ROBOT.urdf') or "
            "the YAML table that export writes"
        )
    if suffix in (".yaml", ".yml"):
        controller = Robot.from_dh(path)
    elif suffix in (".urdf", ".xml"):
        controller = Robot.from_urdf(path, end_link=robot.end_link)
    else:  # a model, a diagnosis JSON, a program: no kinematics a controller runs
        raise HybridPKError(
            f"--controller: {path}: expected the controller's kinematics, a URDF (.urdf, "
            ".xml) or a DH / MDH YAML table (.yaml, .yml), as 'hybrid-pk export' writes them"
        )
    if controller.joint_names != robot.joint_names:
        raise HybridPKError(
            f"--controller: {path} has joints {', '.join(controller.joint_names)}; the model's "
            f"{robot.name} has {', '.join(robot.joint_names)}"
        )
    controller.requires_grad_(False)
    return controller


def run(args: argparse.Namespace) -> int:
    if not (args.box > 0 and args.tol_mm > 0 and args.tol_deg > 0):  # NaN included
        raise HybridPKError(
            f"--box, --tol-mm and --tol-deg must be positive, got {args.box:g} rad, "
            f"{args.tol_mm:g} mm, {args.tol_deg:g} deg"
        )
    loaded, _model, robot, k = load_frozen_model(args)
    controller = _controller(args.controller, robot) if args.controller else None
    with data_notes():
        program = read_program(args.program, robot, args.angle_unit)
    for line in program.notes:
        print(line if line.startswith("warning: ") else f"note: {line}")
    options = IKOptions(tol_mm=args.tol_mm, tol_deg=args.tol_deg)
    with progress("compensate", enabled=not args.no_progress) as bar:
        bar.stage(f"solving {program.n} row(s) on the model")
        comp = compensate_program(
            loaded, program, frame_set=k, box=args.box, options=options,
            approach=parse_approach(args.approach), out=args.out, fixes=_FIXES,
            controller=controller,
        )  # fmt: skip
    for line in comp.assumed:
        print(f"note: {line}")
    for line in _summary(comp, args, robot, program.kind):
        print(line)
    print(f"wrote {args.out}")
    return 0

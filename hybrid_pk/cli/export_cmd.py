"""``hybrid-pk export MODEL --format dh|mdh|urdf|ur-calibration --out FILE``: the geometric
part of a calibrated model for controllers and ROS."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from hybrid_pk.cli.common import read_data
from hybrid_pk.cli.options import add_model, add_out
from hybrid_pk.effects import Conditions, conditions_from_data
from hybrid_pk.errors import HybridPKError
from hybrid_pk.io.dh_export import inertial_note, model_dh_table, table_changes, write_dh_yaml
from hybrid_pk.io.export_summary import left_out, summary_lines
from hybrid_pk.io.model_file import LoadedModel, load_model
from hybrid_pk.io.ur_calibration import (
    UR_ROOTS,
    guess_ur_root,
    not_ur_layout,
    write_ur_calibration,
)
from hybrid_pk.io.urdf_export import export_urdf

DESCRIPTION = """\
Write the geometric part of MODEL (link lengths, axis misalignments, base and flange
frames, joint offsets folded into the joint zero: the file reads commanded joint
values) in one of these formats:

  dh              DH table, YAML: rows name a alpha d theta beta type lower upper
                  [m, rad], Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta); base (root ->
                  frame 0) and flange (frame n -> end link) as {xyz [m], rpy [rad]};
                  where the links have mass, each row also holds mass com_x com_y com_z
                  ixx ixy ixz iyy iyz izz [kg, m, kg m^2] in its frame i (import dh's)
  mdh             modified (Craig) DH, same file: Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d)
  urdf            the corrected URDF (joint offsets folded into the joint origins)
  ur-calibration  Universal Robots' kinematics YAML (ur_description): per joint
                  x y z [m] roll pitch yaw [rad] and a hash (--ur-root: the model's root);
                  6 revolute joints; an arm not laid out as a UR is written unturned, warned

beta is Hayati's parameter, non-zero only between consecutive axes within 45 degrees of
parallel (where plain DH is singular). Effects a geometric file cannot carry
(compliance, deflection, backlash, gear ratio, eccentricity, cyclic errors, residual
networks, and a thermal expansion: the file holds the geometry at 20 degC) are listed
with their size [mm, mrad] at the measured points (a thermal expansion at their
temperatures, or per K from 20 degC where they have none): those of --data, else
the data files the model was calibrated on, else 1000 configurations drawn within the
joint limits. No format holds the mounting (gravity other than upright): a line says
which --gravity gives it back. 'hybrid-pk import dh' and Robot.from_dh read the dh / mdh
files back; 'hybrid-pk compensate --controller FILE' corrects a program for what FILE
cannot carry.
"""

_FORMATS = ("dh", "mdh", "urdf", "ur-calibration")
_YAML = ((".yaml", ".yml"), "YAML")
# the file names each format's readers expect: Robot.from_dh and compensate --controller
# take a .yaml as a DH table and anything else as a URDF
_SUFFIXES = {"dh": _YAML, "mdh": _YAML, "ur-calibration": _YAML, "urdf": ((".urdf", ".xml"), "XML")}
_RANDOM_POINTS = 1000  # enough for a stable rms and max of a smooth effect over the workspace


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk export``."""
    add_model(p)
    p.add_argument("--format", required=True, choices=_FORMATS, help="output format")
    add_out(
        p, metavar="FILE", help="output file (.yaml for dh, mdh and ur-calibration, .urdf for urdf)"
    )
    p.add_argument(
        "--ur-root",
        choices=("auto", *UR_ROOTS),
        default="auto",
        help="ur-calibration: what MODEL's root link is in UR's description: "
        "base_link_inertia (the controller's base frame, DH frame 0: a robot imported from "
        "UR's DH table) or base_link (turned by pi about z: ur_description's URDFs, the "
        "shipped ur10); auto: base_link where the flange at zero joints lies along +x of "
        "the root, else base_link_inertia (UR's arms stretch along -x of DH frame 0) "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--data",
        nargs="+",
        metavar="DATA",
        help="measured pose table(s) whose joint values are the points the summary sizes "
        "the left-out effects at (default: the model's calibration data, when found)",
    )


def _points(args: argparse.Namespace, loaded: LoadedModel) -> tuple[torch.Tensor, Conditions, str]:
    """Joint values, conditions and a description of the points to size effects at."""
    robot = loaded.model.robot
    paths = args.data or [p for p in loaded.metadata.get("data") or [] if Path(p).is_file()]
    if paths:
        data = read_data(paths, robot)
        return data.q, conditions_from_data(data), f"the {data.n} measured points"
    q = robot.sample_q(_RANDOM_POINTS, torch.Generator().manual_seed(0))
    # Backlash needs an approach direction: +1 for every joint (half the play each way).
    cond = Conditions(direction=torch.ones_like(q))
    listed = loaded.metadata.get("data") or []
    why = "no data found"
    if listed:  # recorded as given to calibrate: relative to where it ran
        why = f"its calibration data {', '.join(map(str, listed))} not found from here; --data"
        why += " gives measured points"
    return q, cond, f"{_RANDOM_POINTS} configurations within the joint limits ({why})"


def _mounting_line(model) -> list[str]:
    """A line when MODEL's gravity is not the default (upright on the floor): no export
    format holds it, and a robot read back from the file is statically upright."""
    g = model.gravity
    if g.is_default:
        return []
    flag = "level-tracker" if g.levelled else ",".join(f"{v:g}" for v in g.vector)
    return [
        f"mounting not carried: gravity {g.describe()}; a robot read back from this file "
        f"stands upright: give --gravity {flag} again where its statics count (compliance, "
        "deflection)"
    ]


def _ur_root(given: str, model, lines: list[str]) -> str:
    """The root UR's file is written for (``--ur-root``, or taken from the geometry under
    ``auto``); the lines that say how it was chosen go to ``lines``."""
    other = not_ur_layout(model)
    if other:
        turned = ", turned by pi about z as --ur-root base_link asks" * (given == UR_ROOTS[1])
        lines.append(
            f"warning: {model.robot.name} is not laid out as a UR arm ({other}): UR's "
            "description and driver read this format for UR arms; the file holds the chain "
            f"from its root link{turned}"
        )
        return UR_ROOTS[0] if given == "auto" else given
    root, x = guess_ur_root(model)
    seen = f"at zero joints the flange is at x = {x:.4g} m, as UR's arms are in {root}"
    if given == "auto":
        lines.append(f"root: {model.robot.name}'s root link taken as {root}: {seen}")
        return root
    if given != root:
        lines.append(
            f"warning: --ur-root {given}, but {seen}: the written arm may be turned by pi about z"
        )
    return given


def run(args: argparse.Namespace) -> int:
    suffixes, kind = _SUFFIXES[args.format]
    if Path(args.out).suffix.lower() not in suffixes:
        raise HybridPKError(
            f"{args.out}: --format {args.format} writes {kind}; name the file "
            f"{' or '.join(f'*{x}' for x in suffixes)}"
        )
    if args.ur_root != "auto" and args.format != "ur-calibration":
        raise HybridPKError(f"--ur-root is for --format ur-calibration, not {args.format}")
    loaded = load_model(args.model, robot_check=args.robot, end_link=args.end_link)
    model = loaded.model
    model.requires_grad_(False)
    q, cond, where = _points(args, loaded)
    lines = [f"hybrid_pk export of {loaded.source} ({args.format})"]
    lines += summary_lines(left_out(loaded, q, cond), where)
    lines += _mounting_line(model)
    if args.format in ("dh", "mdh"):
        note = inertial_note(model.robot)
        lines += [note] if note else []
        table = model_dh_table(model, args.format)
        lines += table_changes(model, table)
        write_dh_yaml(table, args.out, header=lines)
    elif args.format == "ur-calibration":
        root = _ur_root(args.ur_root, model, lines)
        _, note = write_ur_calibration(model, args.out, header=lines, root=root)
        lines += [note] if note else []
    else:
        export_urdf(model, args.out, fold_joint_offsets=True)
    print("\n".join(lines))
    print(f"wrote {args.out}")
    return 0

"""``hybrid-pk ik MODEL TARGETS --out SOLUTIONS``: every distinct joint solution (contract 6)."""

from __future__ import annotations

import argparse
import sys

import torch
from tqdm import tqdm

from hybrid_pk.cli.common import data_notes
from hybrid_pk.cli.options import add_model, add_out, add_seed
from hybrid_pk.data import read_table_for
from hybrid_pk.data.table import write_frame
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.ik import IKOptions, solve_ik, solve_ik_two_stage
from hybrid_pk.ik.two_stage import DEFAULT_BOX
from hybrid_pk.io.hybrid_file import load_hybrid
from hybrid_pk.io.model_file import load_model, model_robot

_DESCRIPTION = """\
All distinct joint solutions of each target pose, within the URDF joint limits.

TARGETS is a pose table without joint columns: x y z [m] of the target point in the
measurement frame, optional qw qx qy qz (without them the IK is position-only), and
optional payload [kg] / temperature [degC] for models with such effects. If TARGETS
has the joint columns too, each row's joints are used as one more start configuration.

MODEL is a model file (its base/tool frames and effects are used; a model with
residual networks is solved in two stages: all branches on the kinematic model, each
refined on the full model within --box of it) or nominal:ROBOT (the URDF, identity
frames: targets are flange poses in the robot base frame).

SOLUTIONS (.csv or .parquet) has one row per solution: target (0-based row of
TARGETS), solution (0-based index among that target's solutions), one column per
joint [rad, m for prismatic joints], position_error_mm [mm], orientation_error_deg
[deg]. Two solutions are the same when every revolute joint agrees within 1e-3 rad
modulo 2 pi (prismatic: 1e-6 m). A target with no solution within --tol-mm and
--tol-deg has no row and counts as failed.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``ik`` command."""
    p = subparsers.add_parser(
        "ik",
        help="all distinct joint solutions [rad] of target poses (errors in mm / deg)",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_model(p)
    p.add_argument(
        "targets",
        metavar="TARGETS",
        help="target table, .csv or .parquet: x y z [m], optional qw qx qy qz, payload [kg], "
        "temperature [degC]",
    )
    add_out(p, metavar="SOLUTIONS", help="output table, .csv or .parquet")
    p.add_argument(
        "--seeds",
        type=int,
        default=64,
        metavar="N",
        help="quasi-random start configurations per target (default 64)",
    )
    for unit, name in (("mm", "position"), ("deg", "orientation")):
        p.add_argument(
            f"--tol-{unit}",
            type=float,
            default=1e-3,
            metavar=unit.upper(),
            help=f"largest {name} error of a solution [{unit}] (default 0.001)",
        )
    p.add_argument(
        "--max-iterations",
        type=int,
        default=IKOptions.max_iterations,
        metavar="N",
        help=f"iteration budget per start configuration (default {IKOptions.max_iterations})",
    )
    p.add_argument(
        "--box",
        type=float,
        default=DEFAULT_BOX,
        metavar="RAD",
        help="half-width of the refinement box around each branch on a model with "
        f"effects or networks [rad, m for prismatic joints] (default {DEFAULT_BOX})",
    )
    p.add_argument(
        "--frame-set",
        type=int,
        default=None,
        metavar="K",
        help="base/tool frame set of a model calibrated with one set per file (0-based)",
    )
    add_seed(p, what="scrambling seed of the start configurations")
    p.set_defaults(func=_run)


def _frame_set(args: argparse.Namespace, sets: int) -> int:
    if args.frame_set is None:
        if sets > 1:
            raise HybridPKError(
                f"{args.model} has {sets} base/tool frame sets (one per calibration file); "
                f"choose one with --frame-set 0..{sets - 1}"
            )
        return 0
    if not 0 <= args.frame_set < sets:
        raise HybridPKError(f"--frame-set {args.frame_set}: {args.model} has sets 0..{sets - 1}")
    return args.frame_set


def _read_targets(path: str, robot):
    with data_notes():
        return read_table_for([path], robot, n_params=1, require_joints=False)


def _expensive(loaded, model: ExtendedModel):
    """The accurate model when it is more than the kinematics plus frames, else None."""
    if loaded.has_networks:
        return load_hybrid(loaded)
    return model if len(model.effects) else None


def _run(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        raise HybridPKError(f"--seeds must be at least 1, got {args.seeds}")
    if args.tol_mm <= 0 or args.tol_deg <= 0:
        raise HybridPKError("--tol-mm and --tol-deg must be positive")
    loaded = load_model(args.model, robot_check=args.robot, end_link=args.end_link)
    model = loaded.model
    model.requires_grad_(False)
    robot = model_robot(loaded)
    k = _frame_set(args, model.base.sets)
    data = _read_targets(args.targets, robot)
    n = data.n
    targets = data.T_measured() if data.has_orientation else data.position
    group = torch.full((n,), k, dtype=torch.long) if model.base.sets > 1 else None
    cond = Conditions(
        payload=data.payload,
        temperature=data.temperature,
        direction=torch.zeros(n, robot.dof, dtype=torch.float64),  # unknown approach
        group=group,
    )
    extra = data.q[:, None, :] if data.q.shape[1] == robot.dof else None
    with torch.no_grad():
        base, tool = model.base.matrix()[k], model.tool.matrix()[k]
    cheap = ExtendedModel(robot, [], base=base, tool=tool)
    expensive = _expensive(loaded, model)
    options = IKOptions(
        tol_mm=args.tol_mm, tol_deg=args.tol_deg, max_iterations=args.max_iterations, seed=args.seed
    )
    common = {"seeds": args.seeds, "extra_seeds": extra, "options": options}
    stages = "kinematic model" if expensive is None else "kinematic model, refined on full model"
    with tqdm(
        total=n, desc=f"ik ({stages})", unit="target", file=sys.stderr, leave=False, delay=0.5
    ) as bar:
        if expensive is None:
            result = solve_ik(cheap, targets, progress=bar.update, **common)
        else:
            result = solve_ik_two_stage(
                cheap, expensive, targets, box=args.box, cond=cond, robot=robot,
                progress=bar.update, **common,
            )  # fmt: skip
    write_frame(args.out, result.to_frame())

    kind = "nominal URDF" if loaded.source.startswith("nominal:") else "model"
    if expensive is not None:
        kind += " (two stages: kinematics + frames, then the full model)"
    n_sol = int(result.counts.sum())
    print(
        f"ik {args.model} ({robot.name}, {kind}) on {n} target(s) from {args.targets}"
        f"{' (position only)' if not data.has_orientation else ''}: {n_sol} solution(s), "
        f"{n_sol / max(n, 1):.2f} per target, {args.seeds} seeds"
    )
    if n_sol:
        pos = result.position_error_mm[result.valid]
        line = f"largest error: {float(pos.max()):.3g} mm"
        if data.has_orientation:
            line += f", {float(result.orientation_error_deg[result.valid].max()):.3g} deg"
        print(line)
    tol = f"{args.tol_mm:g} mm" + (f" / {args.tol_deg:g} deg" if data.has_orientation else "")
    print(
        f"{result.n_failed} of {n} target(s) failed (no solution within {tol} and the joint limits)"
    )
    print(f"wrote {args.out}")
    return 0

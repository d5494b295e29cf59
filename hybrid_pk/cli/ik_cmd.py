"""``hybrid-pk ik MODEL TARGETS --out SOLUTIONS``: every distinct joint solution (contract 6)."""

from __future__ import annotations

import argparse

import torch

from hybrid_pk.cli.common import data_notes, load_frozen_model
from hybrid_pk.cli.options import add_approach, add_frame_set, add_model, add_out, add_seed
from hybrid_pk.cli.progress import progress
from hybrid_pk.data import read_table_for
from hybrid_pk.data.table import write_frame
from hybrid_pk.errors import HybridPKError
from hybrid_pk.ik import IKOptions, parse_approach
from hybrid_pk.ik.dedup import REVOLUTE_TOL
from hybrid_pk.ik.two_stage import DEFAULT_BOX
from hybrid_pk.io.model_file import NOMINAL_PREFIX
from hybrid_pk.pipelines.solving import solve_targets, target_reach

# The fixes of assumed conditions, as flags and columns.
_FIXES = {
    "approach": "--approach + / - / JOINT=+,JOINT=- states how the robot approaches",
    "temperature": "a temperature column [degC] in TARGETS states it",
    "payload": "a payload column [kg] in TARGETS states it",
}

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
--tol-deg has no row and counts as failed; failed targets farther from the robot's
root than its links, joint travel and tool add up to are named in a note (a table in
another frame than the measurement frame).

A model with backlash needs the side each joint approaches the target from: give it
with --approach (+: moving in the joint's positive direction, -: negative, per joint
as joint_3=+,joint_4=-); without it the target is solved for the mid-play model
(half-way between both approaches, at most half the play from either), and a note
says so. Targets without payload / temperature columns are solved at 0 kg / 20 degC.
"""


DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk ik``."""
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
    add_frame_set(p)
    add_seed(p, what="scrambling seed of the start configurations")
    add_approach(p)


def _read_targets(path: str, robot):
    with data_notes():
        return read_table_for([path], robot, n_params=1, require_joints=False)


def run(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        raise HybridPKError(f"--seeds must be at least 1, got {args.seeds}")
    if not (args.tol_mm > 0 and args.tol_deg > 0):  # NaN included
        raise HybridPKError(
            f"--tol-mm and --tol-deg must be positive, got {args.tol_mm:g} mm, {args.tol_deg:g} deg"
        )
    if args.max_iterations < 1:
        raise HybridPKError(f"--max-iterations must be at least 1, got {args.max_iterations}")
    if not args.box > 0:  # NaN included
        raise HybridPKError(f"--box must be > 0 [rad, m for prismatic joints], got {args.box}")
    loaded, _model, robot, k = load_frozen_model(args)
    data = _read_targets(args.targets, robot)
    options = IKOptions(
        tol_mm=args.tol_mm, tol_deg=args.tol_deg, max_iterations=args.max_iterations, seed=args.seed
    )

    solved = [0]

    def started(n: int, two_stage: bool) -> None:
        full = ", then refined on the full model" if two_stage else ""
        bar.stage(f"solving {n} target(s) on the kinematic model{full}")

    def moved(k: int) -> None:
        solved[0] += k
        bar(f"{solved[0]} of {data.n} target(s) done")

    # the progress of every command: a status line on a terminal, lines in a log
    with progress("ik", enabled=not args.no_progress) as bar:
        job = solve_targets(
            loaded, data, frame_set=k, seeds=args.seeds, options=options, box=args.box,
            approach=parse_approach(args.approach), fixes=_FIXES, progress=moved,
            started=started,
        )  # fmt: skip
    for note in job.notes:
        print(f"note: {note}")
    write_frame(args.out, job.frame)
    _print_summary(args, loaded, robot, data, job)
    return 0


def _print_summary(args, loaded, robot, data, job) -> None:
    n, frame, two_stage = data.n, job.frame, job.two_stage
    kind = "nominal URDF" if loaded.source.startswith(NOMINAL_PREFIX) else "model"
    if two_stage:
        kind += " (two stages: kinematics + frames, then the full model)"
    n_sol = len(frame)
    print(
        f"ik {args.model} ({robot.name}, {kind}) on {n} target(s) from {args.targets}"
        f"{' (position only)' if not data.has_orientation else ''}: {n_sol} solution(s), "
        f"{n_sol / max(n, 1):.2f} per target, {args.seeds} seeds"
    )
    if n_sol:
        line = f"largest error: {float(frame['position_error_mm'].max()):.3g} mm"
        if data.has_orientation:
            line += f", {float(frame['orientation_error_deg'].max()):.3g} deg"
        print(line)
    fixed = 6 if data.has_orientation else 3  # the coordinates a target fixes
    if robot.dof > fixed and n_sol:
        print(
            f"note: a target fixes {fixed} coordinates of {robot.name}'s {robot.dof} joints: "
            f"its solutions form a {robot.dof - fixed}-parameter family, and the ones "
            "listed are samples of it (one per start that converged apart), not distinct "
            "branches" + ("" if data.has_orientation else "; orientation columns fix more")
        )
    if n_sol:
        _singular(robot, job, data.has_orientation)
    tol = f"{args.tol_mm:g} mm" + (f" / {args.tol_deg:g} deg" if data.has_orientation else "")
    failed = n - frame["target"].nunique()
    print(f"{failed} of {n} target(s) failed (no solution within {tol} and the joint limits)")
    if failed:
        _closest(job, data.has_orientation)
        _beyond_reach(loaded, data, frame, args.frame_set or 0)
    print(f"wrote {args.out}")


def _singular(robot, job, has_orientation: bool) -> None:
    """A note on targets solved at or near a singular configuration (stretched elbow,
    wrist_2 = 0, ...): ``IKResult.near_singular``, where the smallest singular value of
    the model's Jacobian (rotation rows weighted like the solver's) times the
    distinctness tolerance (1e-3 rad) is below the position tolerance."""
    fixed = 6 if has_orientation else 3
    if robot.dof > fixed or job.near_singular is None:  # a family anyway: redundancy note
        return
    targets = job.near_singular.nonzero()[:, 0].tolist()
    if not targets:
        return
    sigma = float(job.smallest_singular_value[targets].min())
    rows = ", ".join(map(str, targets[:5])) + (", ..." if len(targets) > 5 else "")
    print(
        f"note: {len(targets)} target(s) (rows {rows}, 0-based) are reached at or near a "
        f"singular configuration (smallest Jacobian singular value {sigma:.2g} m/rad): a "
        f"pose change within the tolerance moves the joints there by more than the "
        f"{REVOLUTE_TOL:g} rad that tells solutions apart; solutions are polished onto "
        "their exact branch, but rows of such a target may be samples of one singular "
        "family instead, and a measured pose's noise moves its branches by more than that"
    )


def _closest(job, has_orientation: bool) -> None:
    """How near the solver came to each failed target (its best start), e.g. a measured
    pose of a stretched arm a few micrometres beyond the model's reach."""
    if job.closest_mm is None:
        return
    failed = torch.ones(job.closest_mm.numel(), dtype=torch.bool)
    failed[torch.as_tensor(job.frame["target"].unique(), dtype=torch.long)] = False
    rows = failed.nonzero()[:, 0]
    parts = []
    for i in rows[:5].tolist():
        part = f"{i}: {float(job.closest_mm[i]):.3g} mm"
        parts.append(part + (f" / {float(job.closest_deg[i]):.3g} deg" if has_orientation else ""))
    more = f", ... (largest {float(job.closest_mm[rows].max()):.3g} mm)" if rows.numel() > 5 else ""
    print(
        f"note: closest the solver came to the failed target(s), row (0-based): "
        f"{', '.join(parts)}{more}; a target that misses by micrometres lies just beyond the "
        "reach (a stretched arm) or a limit: --tol-mm / --tol-deg accept it"
    )


def _beyond_reach(loaded, data, frame, k: int) -> None:
    """A note on the failed targets that no configuration reaches (farther from the
    robot's root than its links, travel and tool add up to): the usual cause is a target
    table in another frame than the model's measurement frame."""
    distance, reach = target_reach(loaded, data, k)
    failed = torch.ones(data.n, dtype=torch.bool)
    failed[torch.as_tensor(frame["target"].unique(), dtype=torch.long)] = False
    far = failed & (distance > reach)
    if not bool(far.any()):
        return
    rows = ", ".join(str(int(i)) for i in far.nonzero()[:5, 0]) + (", ..." if far.sum() > 5 else "")
    span = f"{float(distance[far].min()):.3g}-{float(distance[far].max()):.3g} m"
    if loaded.source.startswith(NOMINAL_PREFIX):  # identity frames: targets in the base frame
        why = "nominal:ROBOT takes flange poses in the robot base frame [m]; measured poses "
        why += "in a tracker's frame go with a calibrated model file"
    else:
        why = "TARGETS are x y z of the measured point in the measurement frame (as the "
        why += "calibration data's); flange poses in the robot base frame go with "
        why += "nominal:ROBOT (or to compensate)"
    print(
        f"note: {int(far.sum())} failed target(s) (rows {rows}, 0-based) lie {span} from the "
        f"origin of the robot's root (the model's base frame), beyond the {reach:.3g} m its "
        f"links, joint travel and tool add up to: {why}"
    )

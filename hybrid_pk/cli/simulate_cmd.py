"""``hybrid-pk simulate ROBOT ...``: a virtual measurement campaign to a table + truth JSON."""

from __future__ import annotations

import argparse

from hybrid_pk.calibration.frames import parse_frame_spec
from hybrid_pk.cli.options import (
    add_end_link,
    add_noise,
    add_out,
    add_robot,
    add_seed,
)
from hybrid_pk.data.joint_table import read_joint_table
from hybrid_pk.effects import parse_gravity
from hybrid_pk.errors import HybridPKError
from hybrid_pk.pipelines.simulation import (
    beyond_credible_lines,
    simulate_to_files,
    table_path,
    truth_path,
    unseen_lines,
)
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import TRAJECTORIES, is_hidden_spec

_DESCRIPTION = """\
Simulate a measurement campaign: the robot with injected error effects, measured
by a laser tracker at an unknown place (unless --known-frames) with Gaussian noise.
Writes the pose table FILE (joints [rad], x, y, z [m], qw..qz, payload [kg],
temperature [°C], t [s] for continuous trajectories) and FILE.truth.json with every
injected effect, the base and tool frames, and the dataset error (true poses vs the
nominal model with the true frames, as in the paper's Table I).

--effects SPEC, items separated by ';':
  kind:joint=value        joint_offset:joint_2=1e-3 (rad), joint_compliance:joint_3=2e-6
                          (rad/Nm), gear_ratio:joint_1=1e-4 (1), backlash:joint_4=2e-4 (rad,
                          full play)
  kind:joint=v1,v2[,v3]   joint_eccentricity:joint_2=3e-4,-2e-4 (a, b [rad]),
                          cyclic_error_17:joint_2=2e-4,1e-4 (a, b [rad], 17 per turn),
                          link_length:joint_3=0,0,5e-4 ([m]), axis_misalignment:joint_5=1e-3,0,0
                          ([rad] rotation vector)
  kind=value              thermal_expansion=1.2e-5 (1/K)
  none                    no effect
  paper                   the paper's generator: compliance of the three most loaded joints
                          (RX160 + 20 kg payload: about 1.8 mm mean error)
  random[:K]              K (default 2) effects drawn from --seed, 0.2-1 mm each; not printed
  FILE.json               the effects of a truth JSON (or a list of {effect, joint, value})

Deflection beyond the joint axis: tilt_compliance:joint_2=1e-6,2e-6 (rad/Nm about the two
axes perpendicular to the joint), column_bending:JOINT=b1,b2 (rad/Nm/m, prismatic joints:
grows with the extension).

--mount floor|ceiling|wall|tilt:DEG[,AZ] or --gravity X,Y,Z [m/s^2, robot root frame]:
how the robot is mounted; compliance and deflection follow that gravity. The tracker
then stands level and the truth base frame carries the mount rotation (what
calibrate/diagnose --gravity level-tracker recover). Without either, the robot stands
upright and the tracker is tilted up to 2 deg.
"""


DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk simulate``."""
    add_robot(p, positional=True)
    p.add_argument("--n", type=int, metavar="N", help="number of measurements")
    p.add_argument(
        "--poses",
        metavar="POSES",
        help="measure at these joints instead of a --trajectory: a table with one column "
        "per joint [rad, m], e.g. the output of `hybrid-pk plan` (--n: its row count)",
    )
    p.add_argument(
        "--effects",
        default="none",
        metavar="SPEC",
        help="injected error effects, values in the units of each effect (see above; "
        "default: none)",
    )
    add_noise(p, mm=0.0, deg=0.0)
    p.add_argument(
        "--trajectory",
        choices=TRAJECTORIES,
        default=None,
        help="random: uniform in the joint limits; continuous: smooth joint path at 10 Hz "
        "(writes t [s]); iso-cube: ISO 9283 poses P1..P5, repeated; zigzag: Cartesian "
        "raster through the ISO cube (default: random)",
    )
    p.add_argument(
        "--payload",
        type=float,
        default=0.0,
        metavar="KG",
        help="mass at the flange [kg], every row (default: 0)",
    )
    p.add_argument(
        "--payload-range",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="measure in blocks of rows at payloads spread over LO..HI [kg] (instead of --payload)",
    )
    temp = p.add_mutually_exclusive_group()
    temp.add_argument(
        "--temperature-range",
        type=float,
        nargs=2,
        default=(20.0, 28.0),
        metavar=("START", "END"),
        help="warm-up drift of the temperature over the campaign [°C] (default: 20 28)",
    )
    temp.add_argument("--no-temperature", action="store_true", help="write no temperature column")
    p.add_argument(
        "--position-only", action="store_true", help="write no orientation (qw, qx, qy, qz)"
    )
    p.add_argument(
        "--known-frames",
        action="store_true",
        help="measure the flange in the robot base frame (identity base and tool frames)",
    )
    mounting = p.add_mutually_exclusive_group()
    mounting.add_argument(
        "--mount",
        metavar="MOUNT",
        help="floor, ceiling, wall or tilt:DEG[,AZ] (base tilted DEG degrees towards "
        "azimuth AZ); the tracker stands level (default: upright, tracker tilted <= 2 deg)",
    )
    mounting.add_argument(
        "--gravity",
        metavar="X,Y,Z",
        help="gravity in the robot's root frame [m/s^2], e.g. 0,0,9.81 for a ceiling "
        "mount (instead of --mount)",
    )
    p.add_argument(
        "--tool",
        metavar="X,Y,Z[,RX,RY,RZ]",
        help="the true tool frame (measured point on the flange) [m, roll-pitch-yaw rad] "
        "instead of a drawn one; without angles its rotation is drawn",
    )
    p.add_argument(
        "--base",
        metavar="X,Y,Z[,RX,RY,RZ]",
        help="the true base frame (robot root in the tracker frame) [m, roll-pitch-yaw "
        "rad] instead of a drawn one; without angles its rotation is drawn",
    )
    add_end_link(p)
    add_seed(p, what="random seed")
    add_out(
        p,
        metavar="FILE",
        help="output table (.csv, .parquet or .pq); the truth goes to FILE.truth.json",
    )
    p.set_defaults(also_writes=lambda args: [("its truth file", truth_path(args.out))])


def _describe(entry: dict) -> str:
    """``kind:joint = value unit`` with 4 significant digits."""
    label = f"{entry['effect']}:{entry['joint']}" if "joint" in entry else entry["effect"]
    value = entry["value"]
    text = (
        f"({', '.join(f'{v:.4g}' for v in value)})" if isinstance(value, list) else f"{value:.4g}"
    )
    return f"{label} = {text} {entry['unit']}"


def _mount(args: argparse.Namespace):
    """``--mount`` text, a root-frame Gravity from ``--gravity``, or None."""
    if args.gravity is not None:
        return parse_gravity(args.gravity)
    return args.mount


def run(args: argparse.Namespace) -> int:
    table_path(args.out)
    robot = Robot.from_urdf(args.robot, end_link=args.end_link)
    frames = {
        name: None
        if getattr(args, name) is None
        else parse_frame_spec(getattr(args, name), f"--{name}")
        for name in ("base", "tool")
    }
    poses = None
    if args.poses is not None and args.trajectory is not None:
        raise HybridPKError(
            f"--poses {args.poses} and --trajectory {args.trajectory}: give one of them"
        )
    args.trajectory = args.trajectory or "random"
    if args.poses is not None:
        poses, _ = read_joint_table(args.poses, robot)
    elif args.n is None:
        raise HybridPKError("give --n N (rows of a --trajectory) or --poses POSES")
    sim = simulate_to_files(
        robot, args.out, args.n, args.effects, poses=poses, noise_mm=args.noise_mm,
        noise_deg=args.noise_deg, trajectory=args.trajectory, payload=args.payload,
        payload_range=None if args.payload_range is None else tuple(args.payload_range),
        temperature_range=None if args.no_temperature else tuple(args.temperature_range),
        position_only=args.position_only, known_frames=args.known_frames, mount=_mount(args),
        seed=args.seed, progress=True, **frames,
    )  # fmt: skip
    data, truth, out, truth_file = sim.data, sim.truth, sim.table, sim.truth_file

    where = f"poses of {args.poses}" if poses is not None else f"trajectory {args.trajectory}"
    load = (
        f"payload {args.payload:g} kg"
        if args.payload_range is None
        else f"payload {args.payload_range[0]:g}-{args.payload_range[1]:g} kg"
    )
    pos, rot = truth["dataset_error"]["position_mm"], truth["dataset_error"]["orientation_deg"]
    print(
        f"simulated {data.n} rows of {robot.name}: {where}, {load}, "
        f"noise {args.noise_mm:g} mm / {args.noise_deg:g} deg, seed {args.seed}"
    )
    print(f"wrote {out} and {truth_file}")
    if truth["mount"] is not None:
        g = ", ".join(f"{v:.4g}" for v in truth["gravity"])
        print(
            f"mounted {truth['mount']['spec']} ({truth['mount']['tilt_deg']:.1f} deg from "
            f"upright): gravity ({g}) m/s^2 in the robot root frame; tracker level"
        )
    print(
        f"dataset error vs nominal (true frames): position mean {pos['mean']:.3f} mm, "
        f"max {pos['max']:.3f} mm; orientation mean {rot['mean']:.4f} deg, "
        f"max {rot['max']:.4f} deg"
    )
    for line in sim.frame_lines:
        print(line)
    if is_hidden_spec(args.effects):
        print(f"effects hidden; see {truth_file}")
    elif not truth["effects"]:
        print("effects: none (nominal robot)")
    else:
        print(f"effects: {'; '.join(_describe(e) for e in truth['effects'])}")
        for line in beyond_credible_lines(robot, truth) + unseen_lines(robot, data, truth):
            print(line)
    return 0

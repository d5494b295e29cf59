"""``hybrid-pk plan ROBOT --n N --out POSES``: the joint configurations to measure."""

from __future__ import annotations

import argparse
import math

from hybrid_pk.calibration.planning import CRITERIA, Plan, box_bounds
from hybrid_pk.cli.common import flag_values, load_robot, read_json
from hybrid_pk.cli.effect_lists import effect_labels
from hybrid_pk.cli.options import (
    add_end_link,
    add_json,
    add_noise,
    add_out,
    add_robot,
    add_seed,
)
from hybrid_pk.cli.progress import progress
from hybrid_pk.errors import HybridPKError
from hybrid_pk.pipelines.planning import parameter_units, plan_to_file

_DESCRIPTION = """\
Choose N joint configurations to measure so that a calibration identifies the base and
tool frames and the named effects best: a D-optimal design (largest determinant of the
fit's information J^T J) chosen from --candidates random configurations within the
joint limits (2 % margin) and the --joint-box, by a greedy pass and exchange passes.

Prints the predicted 1-sigma of every parameter and the condition number of the
identification Jacobian, next to the same for N random configurations. Writes POSES
(one column per joint [rad, m], in a measuring order that keeps joint moves short, or
shuffled when backlash is named: its approach side comes from the order),
which `hybrid-pk simulate ROBOT --poses POSES` or a real campaign measures.

--effects LIST|DIAG.json: comma-separated effects (joint_offset:joint_2,
joint_compliance:joint_3, ...) or the causes of a `diagnose --json` file; default none
(frames only). The prediction assumes the stated noise; the fit estimates its own.
--joint-box FILE: JSON {"joint_2": [lower, upper], ...} [rad, m]: stay within it.
"""

_UNITS = {"m": ("mm", 1e3), "rad": ("mrad", 1e3), "rad/Nm": ("urad/Nm", 1e6)}
_UNITS.update({"1": ("ppm", 1e6), "1/K": ("ppm/K", 1e6)})


# Flags that are plan_poses() keywords of the same name.
_PLAN_FLAGS = (
    "candidates",
    "position_only",
    "seed",
    "noise_mm",
    "noise_deg",
    "payload",
    "criterion",
)

DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk plan``."""
    add_robot(p, positional=True)
    p.add_argument("--n", type=int, required=True, metavar="N", help="number of poses to measure")
    p.add_argument(
        "--effects",
        default="none",
        metavar="LIST|DIAG.json",
        help="effects to identify besides the frames (default: none)",
    )
    p.add_argument(
        "--candidates",
        type=int,
        default=2000,
        metavar="M",
        help="random candidate configurations to choose from (default: %(default)s)",
    )
    p.add_argument(
        "--criterion",
        choices=tuple(CRITERIA),
        default="d",
        help="; ".join(f"{k}: {v}" for k, v in CRITERIA.items()) + " (default: d)",
    )
    p.add_argument(
        "--position-only",
        action="store_true",
        help="the instrument measures points only (no orientation)",
    )
    p.add_argument("--joint-box", metavar="FILE", help="JSON {joint: [lower, upper]} [rad, m]")
    add_noise(p, mm=0.02, deg=0.002)
    p.add_argument(
        "--payload",
        type=float,
        default=0.0,
        metavar="KG",
        help="mass at the flange during the campaign [kg] (compliance; default: 0)",
    )
    add_end_link(p)
    add_seed(p, what="seed of the random candidates and of the random comparison poses")
    add_out(p, metavar="POSES", help="output joint table, .csv or .parquet")
    add_json(p, help="also write the prediction (std per parameter, condition) as JSON")


def read_joint_box(path: str) -> dict[str, tuple[float, float]]:
    """``{joint: (lower, upper)}`` of a ``--joint-box`` JSON file."""
    doc = read_json(path, "--joint-box")
    if not isinstance(doc, dict) or not doc:
        raise HybridPKError(f'--joint-box: {path} must hold {{"joint_2": [lower, upper], ...}}')
    box = {}
    for joint, value in doc.items():
        ok = isinstance(value, list) and len(value) == 2
        if not ok or not all(isinstance(v, int | float) for v in value):
            raise HybridPKError(
                f"--joint-box: {path}: {joint!r} must be [lower, upper] in rad (m), got {value!r}"
            )
        box[joint] = (float(value[0]), float(value[1]))
    return box


def _row(name: str, unit: str, planned: float, random: float) -> str:
    shown, factor = _UNITS.get(unit, (unit, 1.0))
    finite = math.isfinite(planned) and math.isfinite(random) and random > 0
    ratio = f"{planned / random:.2f}" if finite else "-"
    cells = [
        f"{v * factor:.4g}" if math.isfinite(v) else "not identifiable" for v in (planned, random)
    ]
    return f"  {name:<32} {shown:<8} {cells[0]:>16} {cells[1]:>16} {ratio:>9}"


def _summary(plan: Plan, args: argparse.Namespace, labels: list[str]) -> list[str]:
    n = plan.q.shape[0]
    design = CRITERIA[args.criterion].split(":")[0]
    left = {e for e, _ in plan.left_out}
    kept = [label for label in labels if label not in left]
    named = f" + {', '.join(kept)}" if kept else " (no effects)"
    lines = [
        f"plan {args.robot}: {n} poses from {plan.candidates} random candidates "
        f"({design}, {plan.exchanges} exchange(s)), seed {args.seed}",
        f"identifies: base and tool frames{named}",
    ]
    for label, why in plan.left_out:
        lines.append(f"note: {label} is not planned for: {why}")
    noise = f"{args.noise_mm:g} mm" + ("" if args.position_only else f" / {args.noise_deg:g} deg")
    lines.append(f"predicted 1-sigma at noise {noise} per coordinate:")
    header = f"{'planned':>16} {f'{n} random':>16} {'ratio':>9}"
    lines.append(f"  {'parameter':<32} {'unit':<8} {header}")
    for name, unit, a, b in zip(
        plan.names,
        parameter_units(plan),
        plan.planned.std.tolist(),
        plan.random.std.tolist(),
        strict=True,
    ):
        lines.append(_row(name, unit, a, b))
    c1, c2 = plan.planned.condition, plan.random.condition
    lines.append(f"  {'condition number':<41} {c1:>16.4g} {c2:>16.4g} {c1 / c2:>9.2f}")
    e1, e2 = plan.planned.position_rms_mm, plan.random.position_rms_mm
    if math.isfinite(e1) and math.isfinite(e2):
        lines.append(
            f"  {'position error over the box, RMS':<32} {'mm':<8} {e1:>16.4g} {e2:>16.4g} "
            f"{e1 / e2:>9.2f}"
        )
        lines.append(
            "  (predicted test error of the calibrated model from the fit's own uncertainty)"
        )
    lost = [n for n, v in zip(plan.names, plan.planned.std.tolist(), strict=True) if math.isinf(v)]
    if lost:
        lines.append(
            f"warning: no poses separate {', '.join(lost)} (they trade off exactly); plan "
            "without the effect that duplicates a frame (diagnose lists such pairs as ambiguous)"
        )
    if args.n < len(plan.names):  # calibrate refuses fewer rows than parameters
        lines.append(
            f"warning: {args.n} poses for {len(plan.names)} parameters: calibrate needs at "
            f"least one row per parameter; plan --n {len(plan.names)} or more"
        )
    return lines


def run(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot, args.end_link)
    spec = args.effects.strip()
    labels = [] if spec == "none" else effect_labels(spec)
    box = read_joint_box(args.joint_box) if args.joint_box else None
    if box:
        box_bounds(robot, box, where=f"--joint-box {args.joint_box}")  # names the file
    with progress("plan", total=2, enabled=not args.no_progress) as bar:
        res = plan_to_file(
            robot, args.n, labels, args.out, box=box, progress=bar.report,
            json_out=None if args.json is None else (args.json, args.robot),
            **flag_values(args, *_PLAN_FLAGS),
        )  # fmt: skip
    for line in _summary(res.plan, args, labels):
        print(line)
    print(f"wrote {args.out}" + (f" and {args.json}" if args.json else ""))
    end = f" --end-link {args.end_link}" if args.end_link else ""  # a URDF of several leaves
    hint = f"hybrid-pk simulate {args.robot}{end} --poses {args.out} ..."
    print(f"measure them: {hint} (or on the robot)")
    return 0

"""``hybrid-pk demo``: the whole pipeline on the shipped default robot (RX160).

The pipeline itself is :func:`hybrid_pk.pipelines.demo.run_demo`; this module adds its
flags, the progress display and the printed summary.
"""

from __future__ import annotations

import argparse

from hybrid_pk.cli.options import add_epochs, add_noise, add_out, add_robot, add_seed, count
from hybrid_pk.cli.progress import progress
from hybrid_pk.pipelines.demo import (
    DEFAULT_ROBOT,
    STAGES,
    UNMODELLED_DEFLECTION,
    UNMODELLED_KNEE,
    DemoResult,
    run_demo,
)
from hybrid_pk.pipelines.demo_report import NOT_INJECTED, found_table, injected_text

_DESCRIPTION = """\
The whole pipeline on a simulated laser-tracker campaign: simulate hidden effects ->
diagnose (name the causes, show the evidence) -> calibrate -> train the residual
networks -> evaluate on rows no fit saw -> IK with every solution -> report. The
injected effects are revealed only at the end.

Units: positions in m (errors in mm), angles in rad (errors in deg), payload in kg.
Writes DIR/report.md (start there), campaign.csv with its truth JSON, diagnosis.json,
model.pt (calibrated), hybrid.pt (+ networks), ik_targets.csv / ik_solutions.csv and
TensorBoard logs in DIR/tensorboard. Progress (stage, inner step, elapsed time) goes
to stderr; the report's run-time line gives the time of each stage.
"""


DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk demo``."""
    add_out(p, metavar="DIR", help="output folder", default="hybrid_pk_demo", kind="folder")
    add_robot(p, default=DEFAULT_ROBOT)
    p.add_argument("--n", type=count, default=3000, help="measured poses (default: %(default)s)")
    p.add_argument(
        "--effects",
        default="random:3",
        help="hidden effects of the vocabulary (simulate's --effects syntax; default: "
        "%(default)s, drawn from --seed)",
    )
    p.add_argument(
        "--unmodelled",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="add a hardening spring to joint 2 or 3 (drawn from --seed): extra "
        f"deflection up to {UNMODELLED_DEFLECTION * 1e3:g} mrad, knee at "
        f"{UNMODELLED_KNEE:g} x the joint's RMS gravity torque; outside the vocabulary, "
        "left to the networks (default: on)",
    )
    add_noise(p, mm=0.02, deg=0.002)
    p.add_argument(
        "--payload", type=float, default=20.0, help="payload at the flange [kg] (default: 20)"
    )
    add_epochs(p, default=100)
    add_seed(p, default=7, what="seed of the campaign, the diagnosis split and the training")


def run(args: argparse.Namespace) -> int:
    with progress("demo", total=len(STAGES), delay=0.0, enabled=not args.no_progress) as bar:
        result = run_demo(
            args.out,
            robot=args.robot,
            n=args.n,
            effects=args.effects,
            unmodelled=args.unmodelled,
            noise_mm=args.noise_mm,
            noise_deg=args.noise_deg,
            payload=args.payload,
            epochs=args.epochs,
            seed=args.seed,
            progress=bar.report,
        )
    print_summary(result)
    return 0


def print_summary(result: DemoResult) -> None:
    """The demo's printed summary: held-out errors, injected vs found, IK, run time."""
    print(f"demo: {result.n_rows} simulated poses of {result.robot}, results in {result.out}/")
    print(f"  held-out test rows: {result.n_test}")
    for name, res in result.evaluation.items():
        p, o = res["position_mm"], res["orientation_deg"]
        print(
            f"  {name:28s} position mean {p['mean']:.4f} mm (max {p['max']:.4f}), "
            f"orientation mean {o['mean']:.5f} deg"
        )
    print("  injected (hidden until now) vs found:")
    found = {(c.effect, c.joint): c for c in result.diagnosis.causes}
    for e in result.truth["effects"]:
        c = found.get((e["effect"], e.get("joint")))
        unit = "" if e["unit"] == "1" else f" {e['unit']}"  # a ratio: no unit
        got = "NOT FOUND" if c is None else f"found {injected_text(c.value)}{unit}"
        if e.get("unseen"):
            got += f" ({e['unseen']['words']})"
        shown = injected_text(e["value"], None if c is None else c.value)
        print(f"    {e['effect']}:{e.get('joint')} = {shown}{unit}  ->  {got}")
    for e in result.truth["unmodelled"]:
        value = f"{injected_text(e['value'])} {e['unit']}"
        print(
            f"    {e['effect']}:{e['joint']} = {value} "
            "(outside the vocabulary: left to the networks)"
        )
    # named but not injected, as the report's table says them (not hidden from the console)
    for label, unit, injected, value, why in found_table(result.truth, result.diagnosis):
        if injected == NOT_INJECTED:
            unit = "" if unit == "1" else f" {unit}"
            print(f"    also named: {label} = {injected_text(value)}{unit}: {why}")
    ik = result.ik
    print(
        f"  IK on the hybrid model: {ik['solutions']} solutions for {ik['targets']} targets, "
        f"largest error {ik['max_position_mm']:.2g} mm / {ik['max_orientation_deg']:.2g} deg"
    )
    stages = ", ".join(f"{k} {v:.0f} s" for k, v in result.stage_seconds.items())
    print(f"  report: {result.report}  ({result.seconds:.0f} s: {stages})")

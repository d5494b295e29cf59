"""``hybrid-pk demo``: the whole pipeline on the shipped default robot (RX160).

simulate a laser-tracker campaign with hidden effects -> diagnose (name the causes,
show the evidence) -> calibrate -> train the residual networks -> evaluate on rows no
fit saw -> IK with every solution -> report. The injected effects are revealed only
at the end, next to what the diagnosis found, so the run shows that the tool finds
them by itself.

Besides effects of the vocabulary, the campaign carries by default one effect that no
calibration can fit: a hardening joint spring (softer near zero torque, as harmonic
drives are) on a gravity-loaded joint. The physics explains what it can of it; the
residual networks learn the rest.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.cli.common import progress
from hybrid_pk.data import MeasuredData, write_table
from hybrid_pk.data.table import write_frame
from hybrid_pk.effects import Conditions, Effect, ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.ik import solve_ik_two_stage
from hybrid_pk.io.hybrid_file import save_hybrid
from hybrid_pk.io.model_file import save_model
from hybrid_pk.report.diagnosis_report import write_diagnosis_report
from hybrid_pk.report.evaluation_report import write_evaluation_report
from hybrid_pk.report.markdown import fmt, image, markdown_table, stats_table
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.effect_specs import effect_entry, parse_effects
from hybrid_pk.simulate.unmodelled import HardeningCompliance, rms_gravity_torques

DEFAULT_ROBOT = "rx160"
UNMODELLED_DEFLECTION = 2e-4  # [rad] of the hardening spring's saturated extra deflection
UNMODELLED_KNEE = 0.4  # knee torque tau0, share of the joint's RMS gravity torque
IK_TARGETS = 4
STEPS = 7


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the whole pipeline on a simulated RX160 campaign and write a report",
        description=__doc__.split("\n\n")[0]
        + " Units: positions in m (errors in mm), angles in rad (errors in deg), "
        "payload in kg. Writes DIR/report.md (start there), campaign.csv with its "
        "truth JSON, diagnosis.json, model.pt (calibrated), hybrid.pt (+ networks), "
        "ik_targets.csv / ik_solutions.csv and TensorBoard logs in DIR/tensorboard.",
    )
    p.add_argument("--out", default="hybrid_pk_demo", help="output folder (default: %(default)s)")
    p.add_argument("--robot", default=DEFAULT_ROBOT, help="shipped robot or URDF (default: rx160)")
    p.add_argument("--n", type=int, default=3000, help="measured poses (default: %(default)s)")
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
    p.add_argument("--noise-mm", type=float, default=0.02, help="position noise std [mm]")
    p.add_argument("--noise-deg", type=float, default=0.002, help="orientation noise std [deg]")
    p.add_argument("--payload", type=float, default=20.0, help="payload at the flange [kg]")
    p.add_argument(
        "--epochs", type=int, default=100, help="training epochs of the networks (default: 100)"
    )
    p.add_argument("--seed", type=int, default=7, help="seed of the campaign (default: 7)")
    p.set_defaults(func=run)


def _hidden_effects(robot: Robot, args) -> tuple[list[Effect], list[Effect]]:
    """The vocabulary effects of ``--effects`` and the unmodelled one (if any)."""
    effects = parse_effects(robot, args.effects, seed=args.seed, payload=args.payload)
    unmodelled: list[Effect] = []
    if args.unmodelled:
        gen = torch.Generator().manual_seed(args.seed + 1)
        index = 1 + int(torch.randint(2, (1,), generator=gen))  # joint 2 or 3
        tau0 = UNMODELLED_KNEE * float(rms_gravity_torques(robot, args.payload, gen)[index])
        unmodelled.append(
            HardeningCompliance(robot, robot.joint_names[index], UNMODELLED_DEFLECTION / tau0, tau0)
        )
    return effects, unmodelled


def run(args) -> int:
    started = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    robot = Robot.from_urdf(args.robot)
    robot.requires_grad_(False)
    with progress("demo", total=STEPS) as step:
        step("simulating the measurement campaign")
        vocabulary, unmodelled = _hidden_effects(robot, args)
        data, truth = simulate_campaign(
            robot,
            args.n,
            vocabulary + unmodelled,
            noise_mm=args.noise_mm,
            noise_deg=args.noise_deg,
            payload=args.payload,
            seed=args.seed,
        )
        truth["effects"] = [effect_entry(e) for e in vocabulary]
        truth["unmodelled"] = [{**effect_entry(e), "tau0_Nm": e.tau0} for e in unmodelled]
        write_table(out / "campaign.csv", data)
        (out / "campaign.csv.truth.json").write_text(json.dumps(truth, indent=2))
        # Last quarter of the campaign: never seen by diagnosis, calibration or training.
        n_test = data.n // 4
        calib = data.subset(torch.arange(0, data.n - n_test))
        test = data.subset(torch.arange(data.n - n_test, data.n))
        cond_all = conditions_from_data(data)
        cond = cond_all.subset(torch.arange(0, data.n - n_test))
        test_cond = cond_all.subset(torch.arange(data.n - n_test, data.n))

        step("diagnosing: which effects explain the errors?")
        diag = diagnose(robot, calib, seed=args.seed)
        (out / "diagnosis.json").write_text(json.dumps(diag.to_json(), indent=2, default=str))
        diag_report = write_diagnosis_report(diag, calib, robot, out / "diagnosis")

        step("calibrating frames + named effects on the calibration rows")
        effects = [
            make_effect(robot, c.effect if c.joint is None else f"{c.effect}:{c.joint}")
            for c in diag.causes
        ]
        model = ExtendedModel(robot, effects)
        initialise_frames(model, calib, cond)
        fit(model, calib, cond=cond)
        model.requires_grad_(False)
        save_model(out / "model.pt", model, metadata={"source": "hybrid-pk demo"})
        nominal = ExtendedModel(robot)
        initialise_frames(nominal, calib, cond)
        fit(nominal, calib, cond=cond)
        nominal.requires_grad_(False)

        step("training the residual networks (Lightning)")
        from hybrid_pk.training import train_hybrid  # Lightning: imported when needed

        trained = train_hybrid(
            calib,
            model,
            cond,
            max_epochs=args.epochs,
            seed=args.seed,
            datamodule={"batch_size": 128},  # more steps on a small campaign
            logdir=out / "tensorboard",
            progress=False,
        )
        hybrid = trained.hybrid
        save_hybrid(out / "hybrid.pt", hybrid, metadata={"source": "hybrid-pk demo"})

        step("evaluating on held-out rows")
        with torch.no_grad():
            predictions = {
                "nominal + frames": nominal(test.q, test_cond),
                "extended (physics)": model(test.q, test_cond),
                "hybrid (physics + networks)": hybrid(test.q, test_cond),
            }
        evaluation_report, results = write_evaluation_report(
            out / "evaluation",
            test,
            predictions,
            title="Held-out evaluation",
            intro=f"{test.n} rows of the campaign that no diagnosis, calibration or "
            "training step saw.",
        )
        (out / "evaluation.json").write_text(json.dumps(results, indent=2))

        step("inverse kinematics on the hybrid model: every solution")
        ik = _ik(out, robot, model, hybrid, test, test_cond)

        step("writing the report")
        seconds = time.perf_counter() - started
        report = _report(
            out, truth, diag, results, ik, diag_report, evaluation_report, trained, seconds
        )
    print(f"demo: {data.n} simulated poses of {robot.name}, results in {out}/")
    print(f"  held-out test rows: {n_test}")
    for name, res in results.items():
        p, o = res["position_mm"], res["orientation_deg"]
        print(
            f"  {name:28s} position mean {p['mean']:.4f} mm (max {p['max']:.4f}), "
            f"orientation mean {o['mean']:.5f} deg"
        )
    print("  injected (hidden until now) vs found:")
    found = {(c.effect, c.joint): c for c in diag.causes}
    for e in truth["effects"]:
        c = found.get((e["effect"], e.get("joint")))
        got = "NOT FOUND" if c is None else f"found {c.value}"
        print(f"    {e['effect']}:{e.get('joint')} = {e['value']}  ->  {got}")
    for e in truth["unmodelled"]:
        print(
            f"    {e['effect']}:{e['joint']} = {e['value']} (outside the vocabulary: left to "
            "the networks)"
        )
    n_sol = ik["solutions"]
    print(
        f"  IK on the hybrid model: {n_sol} solutions for {ik['targets']} targets, largest "
        f"error {ik['max_position_mm']:.2g} mm / {ik['max_orientation_deg']:.2g} deg"
    )
    print(f"  report: {report}  ({time.perf_counter() - started:.0f} s)")
    return 0


def _ik(
    out: Path,
    robot: Robot,
    model: ExtendedModel,
    hybrid,
    test: MeasuredData,
    cond: Conditions,
) -> dict:
    """All IK solutions on the hybrid model for the first held-out measured poses."""
    rows = torch.arange(min(IK_TARGETS, test.n))
    targets = test.T_measured()[rows]
    write_table(out / "ik_targets.csv", test.subset(rows))
    cheap = ExtendedModel(robot, [], base=model.base.matrix()[0], tool=model.tool.matrix()[0])
    cheap.requires_grad_(False)
    started = time.perf_counter()
    result = solve_ik_two_stage(
        cheap, hybrid, targets, seeds=64, cond=cond.subset(rows), robot=robot
    )
    seconds = time.perf_counter() - started
    frame = result.to_frame()
    write_frame(out / "ik_solutions.csv", frame)
    valid = result.valid
    return {
        "targets": int(rows.numel()),
        "solutions": int(valid.sum()),
        "per_target": [int(c) for c in result.counts.reshape(-1)],
        "failed": int(result.n_failed),
        "max_position_mm": float(result.position_error_mm[valid].max()) if valid.any() else 0.0,
        "max_orientation_deg": (
            float(result.orientation_error_deg[valid].max()) if valid.any() else 0.0
        ),
        "seconds": seconds,
        "frame": frame,
    }


def _found_table(truth: dict, diag) -> list[list[object]]:
    found = {(c.effect, c.joint): c for c in diag.causes}
    rows = []
    for e in truth["effects"]:
        c = found.pop((e["effect"], e.get("joint")), None)
        named = "yes" if c else "no"
        rows.append(
            [f"{e['effect']}:{e.get('joint')}", e["value"], "-" if c is None else c.value, named]
        )
    unmodelled_joints = {e["joint"] for e in truth["unmodelled"]}
    for e in truth["unmodelled"]:
        rows.append(
            [
                f"{e['effect']}:{e['joint']} (knee {e['tau0_Nm']:.0f} Nm)",
                e["value"],
                "-",
                "outside the vocabulary",
            ]
        )
    for (effect, joint), c in found.items():
        why = (
            "stands in for part of the unmodelled spring (same joint)"
            if joint in unmodelled_joints
            else "false positive"
        )
        rows.append([f"{effect}:{joint}", "(not injected)", c.value, why])
    return rows


def _report(out, truth, diag, results, ik, diag_report, evaluation_report, trained, seconds):
    hist = sorted((out / "evaluation").glob("histogram_*.png"))
    evidence = sorted((out / "diagnosis").glob("evidence_*.png"))
    notes = [f"- ambiguous: {' / '.join(a['effects'])}: {a['why']}" for a in diag.ambiguous]
    notes += [f"- warning, {w['cause']}: {w['why']}" for w in diag.warnings]
    joints = list(diag.model.robot.joint_names)
    ik_rows = [
        [int(r["target"]), int(r["solution"]), *(fmt(r[j], 4) for j in joints),
         r["position_error_mm"], r["orientation_error_deg"]]
        for _, r in ik["frame"].iterrows()
    ]  # fmt: skip
    lines = [
        "# hybrid-pk demo",
        "",
        f"Simulated laser-tracker campaign of the {truth['robot']}: {truth['n']} poses, "
        f"{truth['payload']:g} kg payload, noise {truth['noise_mm']} mm / "
        f"{truth['noise_deg']} deg, unknown tracker and tool frames, hidden effects. The "
        f"last quarter of the rows is held out of every step. Run time {seconds:.0f} s.",
        "",
        "## Errors on held-out rows: nominal -> extended -> hybrid",
        "",
        stats_table(results),
        "",
        *[image(h, h.stem.replace("_", " "), out) + "\n" for h in hist],
        f"More plots (error along each joint): [evaluation report]"
        f"({evaluation_report.relative_to(out).as_posix()})",
        "",
        "## Hidden effects vs what the diagnosis found",
        "",
        markdown_table(_found_table(truth, diag), ["effect", "injected", "found", "named"]),
        "",
        "Each plot below shows the residual a cause leaves when it is taken out of the "
        "model, against that cause's signature (e.g. the error against the gravity torque "
        "of the joint for a compliance): the evidence, in the data, for the named cause.",
        "",
        *[image(p, p.stem.replace("_", " "), out) + "\n" for p in evidence],
        "Identifiability and warnings:",
        "",
        *(notes or ["- none: every named cause is separable from the frames and the others"]),
        "",
        "The full diagnosis (statistics, selection log, what is left): [diagnosis report]"
        f"({diag_report.relative_to(out).as_posix()})",
        "",
        "## Residual networks",
        "",
        f"Two networks (position, orientation) trained with Lightning for {trained.epochs} "
        f"epochs in {trained.seconds:.0f} s on the calibration rows, on top of the "
        f"extended model. Validation mean error: base model "
        f"{trained.base['position_mm']:.4f} mm / {trained.base['orientation_deg']:.5f} deg, "
        f"with the networks {trained.best['position_mm']:.4f} mm / "
        f"{trained.best['orientation_deg']:.5f} deg. Curves: `tensorboard --logdir "
        f"{(out / 'tensorboard').as_posix()}`.",
        "",
        "## Inverse kinematics on the hybrid model",
        "",
        f"{ik['targets']} held-out measured poses as targets, 64 seeds: {ik['solutions']} "
        f"distinct solutions ({', '.join(map(str, ik['per_target']))} per target), "
        f"{ik['failed']} target(s) without a solution, in {ik['seconds']:.1f} s. Errors "
        "are with respect to the hybrid forward model (`ik_solutions.csv`).",
        "",
        markdown_table(
            ik_rows,
            ["target", "solution", *joints, "position error [mm]", "orientation error [deg]"],
        ),
        "",
    ]
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path

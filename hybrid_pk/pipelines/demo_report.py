"""The demo's ``report.md``: what was hidden, what the diagnosis found, what each model
gets wrong on held-out rows, the IK solutions, and how long each stage took."""

from __future__ import annotations

import math
from pathlib import Path

from hybrid_pk.calibration.diagnosis.unseen import seen_error
from hybrid_pk.output_file import write_text
from hybrid_pk.report.markdown import fmt, image, markdown_table, stats_table

__all__ = ["NOT_INJECTED", "found_table", "injected_text", "run_time_line", "write_demo_report"]


def run_time_line(stage_seconds: dict[str, float], seconds: float) -> str:
    """``Run time 33 s: simulate 0.4 s, diagnose 12 s, ...`` (stages over 0.05 s)."""
    parts = [
        f"{name} {s:.2g} s" if s < 10 else f"{name} {s:.0f} s"
        for name, s in stage_seconds.items()
        if s >= 0.05
    ]
    return f"Run time {seconds:.0f} s" + (f" ({', '.join(parts)})." if parts else ".")


NOT_INJECTED = "(not injected)"  # the injected cell of a cause named but not injected


def injected_text(value, found=None) -> str:
    """An injected value as the summary shows it (4 digits); a sinusoid's ``(a, b)``
    with its amplitude √(a² + b²) when the diagnosis gives an amplitude (``found`` a
    number), so the two can be compared as printed."""
    if not isinstance(value, list | tuple):
        return f"{float(value):.4g}"
    text = "(" + ", ".join(f"{float(v):.4g}" for v in value) + ")"
    if len(value) == 2 and found is not None and not isinstance(found, list | tuple):
        text += f", amplitude {math.hypot(*map(float, value)):.4g}"
    return text


def found_table(truth: dict, diag) -> list[list[object]]:
    """Rows ``effect, unit, injected, found, named`` of the injected effects, the
    unmodelled spring and every named cause that was not injected."""
    from hybrid_pk.effects import EFFECTS

    found = {(c.effect, c.joint): c for c in diag.causes}
    rows = []
    for e in truth["effects"]:
        c = found.pop((e["effect"], e.get("joint")), None)
        named = "yes" if c else "no"
        unseen = e.get("unseen")
        if unseen is not None:  # only the part the data see is compared
            err = None if c is None else seen_error(e, c.value)
            within = "" if err is None else f", the part the data see within {100 * err:.2g} %"
            named = f"{named}{within} ({unseen['words']})"
        value = "-" if c is None else c.value
        injected = injected_text(e["value"], None if c is None else c.value)
        rows.append([f"{e['effect']}:{e.get('joint')}", EFFECTS[e["effect"]].unit, injected,
                     value, named])  # fmt: skip
    unmodelled_joints = {e["joint"] for e in truth["unmodelled"]}
    for e in truth["unmodelled"]:
        rows.append(
            [
                f"{e['effect']}:{e['joint']} (knee {e['tau0_Nm']:.0f} Nm)",
                e["unit"],
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
        rows.append([f"{effect}:{joint}", c.unit, NOT_INJECTED, c.value, why])
    return rows


def write_demo_report(
    out: Path,
    truth: dict,
    diag,
    results: dict,
    ik: dict,
    diag_report: Path,
    evaluation_report: Path,
    trained,
    stage_seconds: dict[str, float],
    seconds: float,
) -> Path:
    """Write ``out/report.md``: held-out errors, hidden vs found effects with their
    evidence plots, the networks, the IK solutions, and the time of each stage.

    Returns:
        Path of ``report.md``.
    """
    intro = (
        f"Simulated laser-tracker campaign of the {truth['robot']}: {truth['n']} poses, "
        f"{truth['payload']:g} kg payload, noise {truth['noise_mm']} mm / "
        f"{truth['noise_deg']} deg, unknown tracker and tool frames, hidden effects. The "
        "last quarter of the rows is held out of every step. "
        + run_time_line(stage_seconds, seconds)
    )
    lines = [
        "# hybrid-pk demo",
        "",
        intro,
        "",
        *_errors_section(out, results, evaluation_report),
        *_causes_section(out, truth, diag, diag_report),
        *_networks_section(out, trained),
        *_ik_section(ik, diag.model.robot.joint_names, diag.model.robot.joint_types),
    ]
    path = out / "report.md"
    write_text(path, "\n".join(lines))
    return path


def _errors_section(out: Path, results: dict, evaluation_report: Path) -> list[str]:
    hist = sorted((out / "evaluation").glob("histogram_*.png"))
    return [
        "## Errors on held-out rows: nominal -> extended -> hybrid",
        "",
        stats_table(results),
        "",
        *[image(h, h.stem.replace("_", " "), out) + "\n" for h in hist],
        f"More plots (error along each joint): [evaluation report]"
        f"({evaluation_report.relative_to(out).as_posix()})",
        "",
    ]


def _causes_section(out: Path, truth: dict, diag, diag_report: Path) -> list[str]:
    evidence = sorted((out / "diagnosis").glob("evidence_*.png"))
    notes = [f"- ambiguous: {' / '.join(a['effects'])}: {a['why']}" for a in diag.ambiguous]
    notes += [f"- warning, {w['cause']}: {w['why']}" for w in diag.warnings]
    return [
        "## Hidden effects vs what the diagnosis found",
        "",
        markdown_table(found_table(truth, diag), ["effect", "unit", "injected", "found", "named"]),
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
    ]


def _networks_section(out: Path, trained) -> list[str]:
    return [
        "## Residual networks",
        "",
        f"Two networks (position, orientation) trained with Lightning for {trained.epochs} "
        f"epochs in {trained.seconds:.0f} s on the calibration rows, on top of the "
        f"extended model. Validation mean error: base model "
        f"{trained.base['position_mm']:.4f} mm / {trained.base['orientation_deg']:.5f} deg, "
        f"with the networks {trained.final['position_mm']:.4f} mm / "
        f"{trained.final['orientation_deg']:.5f} deg. Curves: `tensorboard --logdir "
        f"{(out / 'tensorboard').as_posix()}`.",
        "",
    ]


def _ik_section(ik: dict, joints: list[str], types: list[str]) -> list[str]:
    """The IK solutions, one row each; joint columns in rad (m for a prismatic joint)."""
    units = [
        f"{j} [{'m' if t == 'prismatic' else 'rad'}]" for j, t in zip(joints, types, strict=True)
    ]
    rows = [
        [int(r["target"]), int(r["solution"]), *(fmt(r[j], 4) for j in joints),
         r["position_error_mm"], r["orientation_error_deg"]]
        for _, r in ik["frame"].iterrows()
    ]  # fmt: skip
    return [
        "## Inverse kinematics on the hybrid model",
        "",
        f"{ik['targets']} held-out measured poses as targets, 64 seeds: {ik['solutions']} "
        f"distinct solutions ({', '.join(map(str, ik['per_target']))} per target), "
        f"{ik['failed']} target(s) without a solution, in {ik['seconds']:.1f} s. Errors "
        "are with respect to the hybrid forward model (`ik_solutions.csv`).",
        "",
        markdown_table(
            rows,
            ["target", "solution", *units, "position error [mm]", "orientation error [deg]"],
        ),
        "",
    ]

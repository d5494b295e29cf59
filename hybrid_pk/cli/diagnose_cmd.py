"""``hybrid-pk diagnose DATA... --robot ROBOT --json OUT``: what the nominal model gets wrong."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from hybrid_pk.calibration.diagnosis.leftovers import structured_text
from hybrid_pk.calibration.diagnosis.rivals import rival_lines
from hybrid_pk.calibration.diagnosis.settle import order_groups
from hybrid_pk.calibration.diagnosis.statistics import along_joints_text
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.cli.common import load_robot, mounting_lines, read_data
from hybrid_pk.cli.fit_settings import diagnosis_notes, print_settings, settings_of
from hybrid_pk.cli.options import add_data, add_end_link, add_json, add_report, add_robot
from hybrid_pk.cli.progress import Progress
from hybrid_pk.cli.settings_flags import add_config_flags, add_settings_flags
from hybrid_pk.cli.transfer_check import append_to_report, transfer_check, transfer_lines
from hybrid_pk.errors import DataError, HybridPKError, missing_file
from hybrid_pk.output_file import write_text

_DESCRIPTION = """\
Diagnose a robot from measured poses: fit base and tool frames to the nominal URDF,
then name the physical effects (joint offsets, compliance, gear ratios, eccentricity,
backlash, link lengths, axis misalignments, thermal expansion, bearing tilt and link or
column bending under the static load) that explain its errors, with their values,
uncertainties and gains, tested on hold-out rows. A robot on a ceiling, a wall or a
tilted base: --gravity X,Y,Z or --gravity level-tracker.

Units: DATA tables have joints [rad, m for prismatic], x y z [m], optional
qw qx qy qz (unit quaternion), payload [kg], temperature [°C]. Errors are reported in
mm (position: point distance) and deg (orientation: rotation angle); each cause in the
unit of its effect (rad, rad/Nm, 1, m, 1/K, rad/Nm/m). --holdout is a fraction of the rows.
"""

# Width of the label column of the printed error table.
_LABEL_WIDTH = 26


DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk diagnose``."""
    add_data(p)
    add_robot(p, required=True)
    add_end_link(p)
    add_settings_flags(p, DiagnosisSettings)
    add_config_flags(p, DiagnosisSettings)
    add_json(p, required=True, help="write the diagnosis JSON here")
    add_report(p, help="write DIR/report.md with plots (PNG) of the evidence for each cause")


def _finite(obj):
    """JSON-safe copy: non-finite floats become null (JSON has no NaN or inf)."""
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, int | str):
        return obj
    if hasattr(obj, "item"):  # numpy / torch scalars
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    return obj


def _num(x, digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def _value(value, std, unit: str, undetermined: list[dict] | None = None) -> str:
    """``value ± std unit``; a component the data do not determine (``undetermined``)
    shows ``*`` for its std and is named after it."""
    if isinstance(value, list):
        free = {u["component"]: u["with"] for u in undetermined or []}
        vals = ", ".join(f"{v:.3g}" for v in value)
        stds = ", ".join("*" if k in free else f"{s:.2g}" for k, s in enumerate(std))
        note = "".join(
            f"; * [{k}]: only its combination with {', '.join(w)} is determined"
            for k, w in free.items()
        )
        return f"({vals}) ± ({stds}) {unit}{note}"
    return f"{value:.4g} ± {std:.2g} {unit}"


def summary_lines(diagnosis, seconds: float | None = None, runs: int = 1) -> list[str]:
    """The short human summary ``diagnose`` prints (errors, causes, ambiguities, rest);
    ``runs``: diagnoses the ``seconds`` cover (``--stability``)."""
    took = "" if seconds is None else f" in {seconds:.1f} s"
    if seconds is not None and runs > 1:
        took += f" ({runs} diagnoses, --stability)"
    lines = [
        f"diagnosed {diagnosis.robot}: {diagnosis.n_samples} rows, "
        f"{diagnosis.n_holdout} hold-out{took}",
        f"{'hold-out error':<{_LABEL_WIDTH}}{'mean':>10}{'rms':>10}{'p95':>10}{'max':>10}",
    ]
    detectable = getattr(diagnosis, "detectable", None) or {}
    if detectable.get("little_power"):  # said before any result
        lines[1:1] = [
            f"warning: {detectable['little_power']}",
            f"detection limits (80 % power): {detectable['summary']}",
        ]
    for key, name in (("position_mm", "position [mm]"), ("orientation_deg", "orientation [deg]")):
        for model in ("nominal", "extended"):
            stats = getattr(diagnosis, model).get(key)
            if stats is None:
                continue
            cells = "".join(f"{_num(stats[s]):>10}" for s in ("mean", "rms", "p95", "max"))
            lines.append(f"{model + ' ' + name:<{_LABEL_WIDTH}}{cells}")
    if diagnosis.causes:
        lines.append(f"causes ({len(diagnosis.causes)}, largest gain first):")
        for c in diagnosis.causes:
            where = f" {c.joint}" if c.joint else ""
            gain = f"gain {c.position_gain_mm:.4g} mm"
            if c.orientation_gain_deg is not None:
                gain += f", {c.orientation_gain_deg:.3g} deg"
            if c.blocked_holdout_gain_mm is not None:
                gain += f"; blocked hold-out {c.blocked_holdout_gain_mm:.3g}"
                if getattr(c, "blocked_holdout_gain_se_mm", None) is not None:
                    gain += f" ± {c.blocked_holdout_gain_se_mm:.2g}"
                gain += " mm"
                if c.blocked_blocks is not None:
                    gain += f" ({c.blocked_blocks['gained']} of {c.blocked_blocks['of']} blocks)"
            if getattr(c, "own_range_gain_mm", None) is not None:
                gain += f"; own-range hold-out {c.own_range_gain_mm:.3g} mm"
            value = _value(c.value, c.std, c.unit, c.undetermined)
            lines.append(f"  {c.effect}{where} = {value}  ({gain})")
        if detectable:
            lines.append(f"other candidates (80 % power): {detectable['summary']}")
    elif getattr(diagnosis, "structural", None) and diagnosis.structural["structurally_wrong"]:
        lines.append("causes: withheld, the URDF looks structurally wrong (see structural)")
    else:
        none = "causes: none beyond measurement noise"
        if detectable:
            none = f"causes: none detected (80 % power): {detectable['summary']}"
        lines.append(none)
    from hybrid_pk.calibration.diagnosis.carryover import margin_text

    margin = margin_text(getattr(diagnosis, "carry_over", None))
    lines += [margin] if margin else []
    lines += ambiguous_lines(diagnosis.ambiguous)
    if diagnosis.rival_stories:
        margin = (diagnosis.carry_over or {}).get("min_gain_mm")
        lines.append("rival stories (the rows cannot choose; named / rival):")
        stories = rival_lines(diagnosis.rival_stories, margin, diagnosis.ambiguous)
        lines += [f"  {x}" for x in stories]
    for w in diagnosis.warnings:
        lines.append(f"warning: {w['cause']}: {w['why']}")
    lines += mounting_lines(diagnosis.model)
    un = diagnosis.unexplained
    rest = f"unexplained: RMS {_num(un.get('position_mm_rms'))} mm"
    if un.get("orientation_deg_rms") is not None:
        rest += f", {_num(un['orientation_deg_rms'])} deg"
    rest += "; structured: " + structured_text(un)
    lines.append(rest)
    along = along_joints_text(un.get("along_joints"))
    if along is not None:
        lines.append(f"  left error along the joints: {along}")
    return lines + diagnosis_notes(diagnosis)


def run(args: argparse.Namespace) -> int:
    from hybrid_pk.calibration.diagnosis import diagnose
    from hybrid_pk.calibration.diagnosis.result import cause_labels
    from hybrid_pk.calibration.diagnosis.stability import seed_stability, stability_lines
    from hybrid_pk.effects import make_effect, unloaded_reason

    settings = settings_of(args, DiagnosisSettings)
    if print_settings(args, settings):
        return 0
    for path in args.data:
        if not Path(path).is_file():
            raise DataError(missing_file(path), file=str(path))  # as every table reader
    if settings.candidates is not None and not settings.candidates:
        raise HybridPKError(
            "--candidates: no effect given; list some (joint_offset:joint_2,...) or leave "
            "the option out for every effect the data could reveal"
        )
    robot = load_robot(args.robot, args.end_link)
    for c in settings.candidates or []:
        make_effect(robot, c)  # unknown effect or joint: a clear error now
    gravity = settings.mounting()
    data = read_data(args.data, robot, skip_bad_rows=args.skip_bad_rows, args=args)

    progress = Progress("diagnose", delay=0.0)
    try:
        keywords = settings.keywords() | {"gravity": gravity}
        result = diagnose(
            robot, data, frames_per_file=args.frames_per_file, progress=progress.stage,
            **keywords,
        )  # fmt: skip
        labels = cause_labels(result)
        stability = None
        if settings.stability > 1:
            stability = seed_stability(
                robot, data, result, settings.stability,
                keywords | {"frames_per_file": args.frames_per_file}, progress.stage,
            )  # fmt: skip
        transfer = transfer_check(
            settings, args.frames_per_file, robot, data, labels, gravity=gravity,
            start=result.model, progress=progress.stage,
        )  # fmt: skip
        if args.report:
            progress.stage("writing the report")
            from hybrid_pk.report import write_diagnosis_report

            report = write_diagnosis_report(result, data, robot, args.report, progress)
            if transfer is not None:
                append_to_report(report, "Transfer: leave one file out", transfer.lines())
            if stability is not None:
                append_to_report(report, "Stability over seeds", stability_lines(stability))
    finally:
        progress.close()
    seconds = progress.elapsed()

    doc = result.to_json() | {"transfer": None if transfer is None else transfer.to_json()}
    doc["stability"] = stability
    out = write_text(args.json, json.dumps(_finite(doc), indent=2) + "\n")
    lines = summary_lines(result, seconds, settings.stability)
    unloaded = unloaded_reason(robot, data.payload, "move nothing and were not tested")
    if unloaded:
        lines.append(f"note: {unloaded}")
    lines += transfer_lines(transfer, settings, data)
    lines += [] if stability is None else stability_lines(stability)
    print("\n".join(lines))
    print(f"wrote {out}" + (f" and {report}" if args.report else ""))
    return 0


def ambiguous_lines(ambiguous: list[dict]) -> list[str]:
    """The printed ambiguity entries; the cyclic orders not resolved gathered per joint."""
    orders, others = order_groups(ambiguous)
    lines = []
    if others:
        lines.append(f"ambiguous ({len(others)}):")
        lines += [_ambiguous_line(a) for a in others]
    if orders:
        lines.append(
            "periodic errors whose order these rows do not resolve (each order predicts "
            "the blocked hold-out within the margin of another, or worse; none is named):"
        )
        lines += [f"  {j}: {', '.join(map(str, o))} per turn" for j, o in orders.items()]
    return lines


def _ambiguous_line(entry: dict) -> str:
    """One ambiguity entry: the effects, or a periodic cause not resolved over its
    joint's range with its own-range gain, or a candidate named causes stand in for
    (or that was named in place of one of them)."""
    if entry.get("stood_in_by"):
        return f"  {entry['effects'][0]} ~ {' + '.join(entry['stood_in_by'])} (together)"
    if entry.get("named_in_place_of"):
        label, group = entry["effects"][0], " + ".join(entry["group"])
        return f"  {label} ~ {group} (together; named in place of {entry['named_in_place_of']})"
    if not entry.get("not_resolved_over_range"):
        return f"  {' ~ '.join(entry['effects'])}"
    own = entry["own_range"]
    low, high = own["ends_mm"]
    return (
        f"  {entry['effects'][0]}: not resolved over its joint's range (own-range hold-out "
        f"gain {own['gain_mm']:.3g} mm: low end {low:.3g}, high end {high:.3g} mm)"
    )

"""``hybrid-pk calibrate``: fit frames + physical effects to DATA, write one MODEL file.

Two forms (contract section 3)::

    hybrid-pk calibrate DATA... --robot ROBOT [--effects auto|none|LIST] --out MODEL
    hybrid-pk calibrate DATA... --model MODEL --refit tool|base|frames --out MODEL2
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch

from hybrid_pk.calibration.diagnosis.search import _report_value, diagnose
from hybrid_pk.calibration.fit import FitResult, fit, initialise_frames
from hybrid_pk.cli.common import (
    FRAME_LABELS,
    add_data_arguments,
    add_gravity_argument,
    fit_frames,
    frame_parameter_count,
    load_robot,
    mounting_lines,
    progress,
    read_data,
    stats_line,
    with_frame_sets,
)
from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import (
    Conditions,
    Effect,
    ExtendedModel,
    conditions_from_data,
    make_effect,
    parse_gravity,
)
from hybrid_pk.errors import HybridPKError, ModelFileError
from hybrid_pk.evaluation.metrics import error_stats, row_errors
from hybrid_pk.geometry import matrix_to_rpy
from hybrid_pk.io.hybrid_file import predict_poses
from hybrid_pk.io.model_file import LoadedModel, load_model, model_robot, save_model
from hybrid_pk.io.urdf_export import export_urdf

# Above this condition number of the scaled identification Jacobian a fit is not
# identifiable from the data (well-posed calibrations here stay below 1e5).
MAX_CONDITION = 1e8

_DESCRIPTION = """\
Fit base/tool frames and physical error effects to measured poses; write one MODEL file
(robot URDF, effects, frames; read by evaluate, train and ik) and a corrected URDF.

  --robot ROBOT --effects auto   diagnose which effects the data shows, then fit them
  --robot ROBOT --effects LIST   fit the listed effects, e.g.
                                 joint_offset:joint_2,joint_compliance:joint_3
  --robot ROBOT --effects none   fit only the base and tool frames
  --robot ROBOT --effects D.json fit the causes named in a diagnose --json file
  --model MODEL --refit WHICH    keep everything of MODEL (effects, networks) and re-fit
                                 only the tool frame, the base frame, or both (after a
                                 tool was re-mounted or the tracker moved)

Effects and units: joint_offset [rad], joint_compliance [rad/Nm], gear_ratio [1],
joint_eccentricity [rad], backlash [rad, full play], link_length [m, vector],
axis_misalignment [rad, rotation vector], thermal_expansion [1/K, not per joint],
tilt_compliance [rad/Nm about the two axes perpendicular to the joint], column_bending
[rad/Nm/m, prismatic joints]. Compliance and deflection use --gravity (the mounting).
The frames are always estimated: base = measurement frame <- robot root, tool =
flange -> measured point. Errors are reported in mm (position) and deg (orientation).
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``calibrate`` command."""
    p = subparsers.add_parser(
        "calibrate",
        help="fit frames + physical effects to measured poses; write a MODEL file",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_data_arguments(p)
    p.add_argument(
        "--robot",
        metavar="ROBOT",
        help="URDF path or shipped robot name (rx160, ur10); with --model: only checked "
        "against the model's robot",
    )
    p.add_argument("--end-link", metavar="NAME", help="end link (default: the URDF's leaf)")
    p.add_argument(
        "--effects",
        default=None,
        metavar="auto|none|LIST|DIAGNOSIS.json",
        help="effects to fit: auto (diagnose them; default), none (frames only), a "
        "comma-separated list of kind:joint labels, values fitted in each kind's unit "
        "(rad, rad/Nm, 1, m, 1/K), or the causes of a diagnose --json file",
    )
    p.add_argument(
        "--model",
        metavar="MODEL",
        help="existing model file whose frame(s) --refit re-fits (effects and networks kept)",
    )
    p.add_argument(
        "--refit",
        choices=tuple(FRAME_LABELS),
        help="with --model: re-fit only the tool frame, the base frame, or both [m, rad]",
    )
    add_gravity_argument(p)
    p.add_argument("--out", required=True, metavar="MODEL", help="output model file (e.g. .pt)")
    p.add_argument(
        "--holdout",
        type=float,
        default=0.2,
        metavar="F",
        help="fraction of rows (0 < F < 1) the diagnosis of --effects auto holds out to "
        "compare models; the final fit uses all rows (default: 0.2)",
    )
    p.add_argument(
        "--urdf",
        metavar="OUT.urdf",
        help="corrected URDF of the geometric part, lengths [m], angles [rad] (default: "
        "MODEL.urdf next to MODEL; with --refit only when given)",
    )
    p.add_argument("--no-urdf", action="store_true", help="write no corrected URDF")
    p.add_argument(
        "--urdf-frames",
        action="store_true",
        help="put the fitted base frame (root link 'measurement_frame') and tool frame "
        "(leaf link 'measured_point') into the URDF as fixed joints",
    )
    p.add_argument(
        "--urdf-fold-offsets",
        action="store_true",
        help="fold joint offsets [rad] into the URDF joint origins (the URDF then reads "
        "commanded joint values) instead of listing them as comments",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="K",
        help="seed of the diagnosis hold-out split (default: 0)",
    )
    p.set_defaults(func=_run)


# ----------------------------------------------------------------------------- helpers


def _effect_labels(text: str) -> list[str]:
    if text.lower().endswith(".json"):
        return _diagnosis_labels(text)
    labels = [s.strip() for s in text.split(",") if s.strip()]
    if not labels:
        raise HybridPKError("--effects: give auto, none, or a comma-separated list of effects")
    seen = set()
    for label in labels:
        if label in seen:
            raise HybridPKError(f"--effects: {label} is listed twice")
        seen.add(label)
    return labels


def _diagnosis_labels(path: str) -> list[str]:
    """The causes of a ``diagnose --json`` file as effect labels."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise HybridPKError(f"--effects: diagnosis file not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise HybridPKError(f"--effects: {path} is not a diagnosis JSON file: {exc}") from None
    causes = doc.get("causes") if isinstance(doc, dict) else None
    if not isinstance(causes, list) or not all(
        isinstance(c, dict) and isinstance(c.get("effect"), str) for c in causes
    ):
        raise HybridPKError(f"--effects: {path} has no 'causes' list of a diagnosis JSON file")
    return [c["effect"] + (f":{c['joint']}" if c.get("joint") else "") for c in causes]


def _effect_rows(model: ExtendedModel, res: FitResult) -> list[dict]:
    """Value, 1-sigma std and unit of every effect of a fit (reporting convention)."""
    rows = []
    for e in model.effects:
        value, std, components = _report_value(e, res.std[res.block_slice(e.label)])
        row = {"effect": e.label, "value": value, "std": std, "unit": e.unit}
        if components is not None:
            row["components"] = components
        rows.append(row)
    return rows


def _fmt(v) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"
    return f"{v:.6g}"


def _fixed(x) -> str:
    return f"{round(float(x), 5) + 0.0:.5f}"  # + 0.0: no "-0.00000"


def _frame_lines(model: ExtendedModel) -> list[str]:
    lines = []
    for name, frame in (("base frame", model.base), ("tool frame", model.tool)):
        T = frame.matrix().detach()
        for g in range(frame.sets):
            tag = f" [{g}]" if frame.sets > 1 else ""
            xyz = ", ".join(_fixed(x) for x in T[g, :3, 3])
            rpy = ", ".join(_fixed(x) for x in matrix_to_rpy(T[g, :3, :3]))
            lines.append(f"  {name}{tag:<6} xyz [m] ({xyz})  rpy [rad] ({rpy})")
    return lines


def _error_summary(res: FitResult) -> dict:
    out = {"position_mm": error_stats(res.position_mm).to_dict()}
    out["orientation_deg"] = (
        None if res.orientation_deg is None else error_stats(res.orientation_deg).to_dict()
    )
    return out


def _urdf_target(args: argparse.Namespace, refit: bool) -> Path | None:
    if args.no_urdf:
        return None
    if args.urdf:
        return Path(args.urdf)
    return None if refit else Path(f"{args.out}.urdf")


def _export(model: ExtendedModel, args: argparse.Namespace, target: Path | None) -> None:
    if target is None:
        return
    export_urdf(
        model,
        target,
        include_base=args.urdf_frames,
        include_tool=args.urdf_frames,
        fold_joint_offsets=args.urdf_fold_offsets,
    )


# ----------------------------------------------------------------------------- commands


def _run(args: argparse.Namespace) -> int:
    if args.model is not None or args.refit is not None:
        return _run_refit(args)
    if args.robot is None:
        raise HybridPKError("give --robot ROBOT (new calibration) or --model MODEL --refit ...")
    return _run_new(args)


def _start_effects(robot, labels: list[str], diag_model: ExtendedModel | None) -> list[Effect]:
    effects = []
    for label in labels:
        value = None
        if diag_model is not None:
            value = diag_model.effect(label).value.detach().clone()
        effects.append(make_effect(robot, label, value))
    return effects


def _run_new(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot, args.end_link)
    gravity = parse_gravity(args.gravity)
    spec = (args.effects or "auto").strip()
    auto = spec == "auto"
    labels = [] if auto or spec == "none" else _effect_labels(spec)
    if not labels and spec.lower().endswith(".json"):
        spec = "none"  # the diagnosis named no cause: frames only
    for label in labels:  # unknown kinds / joints fail before any data is read
        make_effect(robot, label)
    sets = len(args.data) if args.frames_per_file else 1

    diag = None
    with progress("calibrate", total=None if auto else 4) as step:
        step("reading data")
        n_effect_params = sum(make_effect(robot, lb).value.numel() for lb in labels)
        data = read_data(
            args.data,
            robot,
            n_params=frame_parameter_count(sets, False) + n_effect_params,
            skip_bad_rows=args.skip_bad_rows,
        )
        cond = conditions_from_data(data, args.frames_per_file)
        if auto:
            step("diagnosing effects")
            diag = diagnose(
                robot,
                data,
                holdout=args.holdout,
                seed=args.seed,
                frames_per_file=args.frames_per_file,
                progress=step,
                gravity=gravity,
            )
            labels = [c.effect if c.joint is None else f"{c.effect}:{c.joint}" for c in diag.causes]
        step("fitting frames to the nominal robot")
        nominal = ExtendedModel(robot, frame_sets=sets, gravity=gravity)
        res0 = fit_frames(nominal, data, cond)
        step("fitting frames and effects")
        model = ExtendedModel(
            robot,
            _start_effects(robot, labels, diag.model if diag else None),
            frame_sets=sets,
            gravity=gravity,
        )
        initialise_frames(model, data, cond)
        res = fit(model, data, cond=cond)
        step("writing")
        effects = _effect_rows(model, res)
        metadata = {
            "command": "calibrate",
            "data": list(data.sources),
            "n_rows": data.n,
            "frames_per_file": bool(args.frames_per_file),
            "orientation_fitted": data.quat is not None,
            "effects_requested": spec,
            "gravity": gravity.describe(),
            "effects": effects,
            "nominal": _error_summary(res0),
            "calibrated": _error_summary(res),
            "noise_estimate": {
                "position_mm": res.sigma_pos_mm,
                "orientation_rad": res.sigma_rot_rad,
            },
            "condition_number": res.condition,
            "diagnosis": None if diag is None else diag.to_json(),
        }
        save_model(args.out, model, metadata=metadata)
        urdf = _urdf_target(args, refit=False)
        _export(model, args, urdf)

    _print_new_summary(robot, data, args, diag, labels, effects, model, res0, res, urdf)
    return 0


def _print_new_summary(robot, data, args, diag, labels, effects, model, res0, res, urdf) -> None:
    files = len(data.sources)
    what = "position + orientation" if data.quat is not None else "position only"
    print(
        f"calibrated {robot.name} on {data.n} rows from {files} file(s) ({what}); "
        f"{model.base.sets} base/tool frame set(s)"
    )
    if diag is not None:
        print(
            f"diagnosis (hold-out {diag.n_holdout} rows): {len(diag.causes)} cause(s); "
            f"mean position error {diag.nominal['position_mm']['mean']:.4g} mm nominal -> "
            f"{diag.extended['position_mm']['mean']:.4g} mm extended"
        )
        for amb in diag.ambiguous:
            print(f"  ambiguous: {' / '.join(amb['effects'])}")
    if effects:
        print(f"  {'effect':<34} {'value':>22}   {'+- std (1 sigma)':<24} unit")
        for row in effects:
            print(
                f"  {row['effect']:<34} {_fmt(row['value']):>22}   "
                f"+- {_fmt(row['std']):<21} {row['unit']}"
            )
    else:
        print("  no effects: frames only" + (" (the diagnosis named none)" if diag else ""))
    for line in _frame_lines(model) + mounting_lines(model):
        print(line)
    p0, p1 = error_stats(res0.position_mm), error_stats(res.position_mm)
    print(
        f"position error rms {p0.rms:.4g} mm (nominal, frames fitted) -> {p1.rms:.4g} mm "
        f"(calibrated); mean {p0.mean:.4g} -> {p1.mean:.4g} mm, max {p0.max:.4g} -> "
        f"{p1.max:.4g} mm"
    )
    if res.orientation_deg is not None:
        o0, o1 = error_stats(res0.orientation_deg), error_stats(res.orientation_deg)
        print(f"orientation error rms {o0.rms:.4g} deg -> {o1.rms:.4g} deg")
    if not res.condition < MAX_CONDITION:
        pairs = _inseparable_pairs(res)
        which = (
            "these trade off exactly: " + "; ".join(pairs)
            if pairs
            else "some parameter combination is not determined"
        )
        print(
            f"warning: condition number {res.condition:.3g}: the rows cannot separate some "
            f"parameters ({which}); their individual values and std are unreliable, their "
            "sum is fine for prediction. Poses whose flange orientation never changes (only "
            "ISO 9283 cube poses) cannot separate base and tool translation; components of "
            "link lengths along parallel joint axes never separate"
        )
    print(f"wrote {args.out}" + (f" and {urdf}" if urdf else ""))


def _inseparable_pairs(res: FitResult, limit: int = 3) -> list[str]:
    """Up to ``limit`` parameter pairs whose estimates are correlated at |r| >= 0.999."""
    pairs = res.correlated_pairs(0.999)
    return [f"{a} ~ {b} (r = {r:+.4f})" for _, a, _, b, r in pairs[:limit]]


def _run_refit(args: argparse.Namespace) -> int:
    if args.model is None or args.refit is None:
        raise HybridPKError("re-fitting needs both --model MODEL and --refit tool|base|frames")
    if args.effects is not None:
        raise HybridPKError(
            "--effects cannot be combined with --refit: the model keeps its effects"
        )
    if args.gravity is not None:
        raise HybridPKError(
            "--gravity cannot be combined with --refit: the model keeps its mounting"
        )
    loaded = load_model(args.model, robot_check=args.robot, end_link=args.end_link)
    robot = model_robot(loaded)
    robot.requires_grad_(False)
    sets = len(args.data) if args.frames_per_file else 1
    which = args.refit

    with progress("calibrate --refit", total=3) as step:
        step("reading data")
        data = read_data(
            args.data,
            robot,
            n_params=frame_parameter_count(sets, False) // (1 if which == "frames" else 2),
            skip_bad_rows=args.skip_bad_rows,
        )
        cond = conditions_from_data(data, sets > 1)
        before = _errors(loaded, data, cond) if loaded.model.base.sets == sets else None
        keep = {"base": "tool", "tool": "base", "frames": None}[which]
        model = with_frame_sets(loaded.model, sets, keep=keep)
        step(f"re-fitting the {which} frame(s)")
        res = fit_frames(model, data, cond, which)
        step("writing")
        history = list(loaded.metadata.get("refits", []))
        history.append(
            {
                "refit": which,
                "data": list(data.sources),
                "n_rows": data.n,
                "frames_per_file": bool(args.frames_per_file),
                "fitted": _error_summary(res),
            }
        )
        metadata = {k: v for k, v in loaded.metadata.items() if k != "created"}
        metadata["refits"] = history
        if which != "base":  # the tool's orientation is known only from orientation data
            metadata["orientation_fitted"] = data.quat is not None
        save_model(args.out, model, networks=loaded.networks, metadata=metadata)
        urdf = _urdf_target(args, refit=True)
        _export(model, args, urdf)

    print(
        f"re-fitted the {which} frame(s) of {args.model} ({robot.name}, "
        f"{len(model.effects)} effect(s) kept"
        + (", residual networks kept" if loaded.has_networks else "")
        + f") on {data.n} rows from {len(data.sources)} file(s)"
    )
    for line in _frame_lines(model):
        print(line)
    after = _errors(dataclasses.replace(loaded, model=model, frames_fitted=True), data, cond)
    for i, (name, unit) in enumerate((("position", "mm"), ("orientation", "deg"))):
        if after[i] is None:
            continue
        if before is not None:
            print(stats_line(f"{name} before [{unit}]", before[i]))
        print(stats_line(f"{name} after [{unit}]", after[i]))
    if after[2]:
        print(after[2])
    print(f"wrote {args.out}" + (f" and {urdf}" if urdf else ""))
    return 0


def _errors(loaded: LoadedModel, data: MeasuredData, cond: Conditions):
    """Position [mm] and orientation [deg] errors per row, and a note if the residual
    networks could not be evaluated by this installation (extended model alone)."""
    try:
        T, note = predict_poses(loaded, data, cond), ""
    except ModelFileError as exc:
        with torch.no_grad():
            T = loaded.model(data.q, cond)
        note = f"note: errors of the extended model only: {exc}"
    return (*row_errors(T, data), note)

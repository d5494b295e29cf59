"""``hybrid-pk calibrate``: fit frames + physical effects to DATA, write one MODEL file.

Two forms (contract section 3)::

    hybrid-pk calibrate DATA... --robot ROBOT [--effects auto|none|LIST] --out MODEL
    hybrid-pk calibrate DATA... --model MODEL --refit tool|base|frames --out MODEL2
"""

from __future__ import annotations

import argparse
import textwrap

from hybrid_pk.calibration.diagnosis.setup_moves import setup_move_text
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.cli.calibrate_output import (
    add_urdf_options,
    condition_warning,
    effect_rows,
    error_summary,
    format_value,
    frame_lines,
    save_with_urdf,
    urdf_target,
    wrote_line,
)
from hybrid_pk.cli.calibrate_refit import run_refit
from hybrid_pk.cli.common import (
    FRAME_LABELS,
    data_files,
    frame_parameter_count,
    load_robot,
    mounting_lines,
    read_data,
)
from hybrid_pk.cli.effect_lists import effect_labels
from hybrid_pk.cli.fit_settings import (
    fit_lines,
    implausible_effect_lines,
    print_settings,
    robust_summary,
    settings_of,
)
from hybrid_pk.cli.options import ROBOT_HELP, add_data, add_end_link, add_out, add_robot
from hybrid_pk.cli.progress import progress
from hybrid_pk.cli.settings_flags import add_config_flags, add_settings_flags
from hybrid_pk.cli.transfer_check import transfer_check, transfer_lines
from hybrid_pk.effects import make_effect, unloaded_reason
from hybrid_pk.effects.vocabulary import vocabulary_units
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.metrics import error_stats
from hybrid_pk.io.model_file import save_model
from hybrid_pk.pipelines.calibration import calibrate

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
                                 tool was re-mounted or the tracker moved); MODEL's
                                 networks stay in use only if they beat the physics on
                                 DATA, each row predicted with frames fitted without it

{units}
The frames are always estimated: base = measurement frame <- robot root, tool =
flange -> measured point. Errors are reported in mm (position) and deg (orientation).
"""


# The diagnosis' own flags (diagnose's); calibrate --effects auto takes them from
# --config (a YAML diagnose reads too), else their defaults.
_DIAGNOSE_ONLY = ("candidates", "alpha", "max_causes", "stability")

_UNITS = f"Effects and units: {vocabulary_units()}. Compliance and deflection use --gravity."
DESCRIPTION = _DESCRIPTION.replace("{units}", textwrap.fill(_UNITS, 88))


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk calibrate``."""
    add_data(p)
    add_robot(
        p,
        help=f"{ROBOT_HELP}; with --model: only checked against the model's robot",
    )
    add_end_link(p)
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
    add_out(p, metavar="MODEL", help="output model file (e.g. .pt)")
    add_settings_flags(
        p, DiagnosisSettings, skip=_DIAGNOSE_ONLY,
        helps={
            "holdout": "fraction of rows (0 < F < 1) the diagnosis of --effects auto holds "
            "out to compare models; the final fit uses all rows (default: 0.2)",
            "seed": "seed of the diagnosis' hold-out split and blocks and of the "
            "--refit-rows rows (default: 0)",
        },
    )  # fmt: skip
    add_config_flags(p, DiagnosisSettings)
    add_urdf_options(p)


def run(args: argparse.Namespace) -> int:
    settings = settings_of(args, DiagnosisSettings)
    if print_settings(args, settings):
        return 0
    if args.model is not None or args.refit is not None:
        return run_refit(args, settings)
    if args.robot is None:
        raise HybridPKError("give --robot ROBOT (new calibration) or --model MODEL --refit ...")
    return _run_new(args, settings)


def _requested_labels(robot, spec: str) -> tuple[str, list[str]]:
    """``--effects`` as (spec, labels): auto and none give no labels; a diagnosis JSON
    that named no cause is ``none``. Unknown kinds or joints fail here, before any data
    is read."""
    labels = [] if spec in ("auto", "none") else effect_labels(spec, others="auto, none, ")
    if not labels and spec.lower().endswith(".json"):
        spec = "none"  # the diagnosis named no cause: frames only
    for label in labels:
        make_effect(robot, label)
    return spec, labels


def _run_new(args: argparse.Namespace, settings: DiagnosisSettings) -> int:
    robot = load_robot(args.robot, args.end_link)
    gravity = settings.mounting()
    spec, labels = _requested_labels(robot, (args.effects or "auto").strip())
    auto = spec == "auto"
    sets = data_files(args) if args.frames_per_file else 1
    settings.priors()  # a bad --tool or --base fails before the data are read

    with progress("calibrate", total=6 if auto else 5) as bar:
        bar.stage("reading data")
        n_effect_params = sum(make_effect(robot, lb).value.numel() for lb in labels)
        data = read_data(
            args.data,
            robot,
            n_params=frame_parameter_count(sets, False) + n_effect_params,
            skip_bad_rows=args.skip_bad_rows,
            args=args,
        )
        result = calibrate(
            robot, data, None if auto else labels, frames_per_file=args.frames_per_file,
            settings=settings, stage=bar.stage, progress=bar,
        )  # fmt: skip
        model, res, res0, diag = result.model, result.fit, result.nominal_fit, result.diagnosis
        bar.stage("leave one file out")
        transfer = transfer_check(
            settings, args.frames_per_file, robot, data, result.labels, gravity=gravity,
            start=model, progress=bar,
        )  # fmt: skip
        bar.stage("writing")
        effects = effect_rows(model, res)
        metadata = {
            "command": "calibrate",
            "data": list(data.sources),
            "n_rows": data.n,
            "frames_per_file": bool(args.frames_per_file),
            "orientation_fitted": data.quat is not None,
            "effects_requested": spec,
            "gravity": gravity.describe(),
            "effects": effects,
            "nominal": error_summary(res0),
            "calibrated": error_summary(res),
            "noise_estimate": {
                "position_mm": res.sigma_pos_mm,
                "orientation_rad": res.sigma_rot_rad,
            },
            "condition_number": res.condition,
            "frames": None if res.frame_report is None else res.frame_report.to_json(),
            "robust": robust_summary(data, res),
            "diagnosis": None if diag is None else diag.to_json(),
            "transfer": None if transfer is None else transfer.to_json(),
        }
        urdf = urdf_target(args, refit=False)
        save_with_urdf(lambda: save_model(args.out, model, metadata=metadata), model, args, urdf)

    _print_summary(robot, data, diag, effects, model, res0, res)
    for line in transfer_lines(transfer, settings, data):
        print(line)
    print(wrote_line(args.out, model, args, urdf))
    return 0


def _print_summary(robot, data, diag, effects, model, res0, res) -> None:
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
        for move in diag.setup_moves:  # the causes may carry part of it
            print(f"warning: set-up: {setup_move_text(move)}")
        unloaded = unloaded_reason(robot, data.payload, "move nothing and were not tested")
        if unloaded:
            print(f"note: {unloaded}")
    if effects:
        print(f"  {'effect':<34} {'value':>22}   {'+- std (1 sigma)':<24} unit")
        for row in effects:
            print(
                f"  {row['effect']:<34} {format_value(row['value']):>22}   "
                f"+- {format_value(row['std']):<21} {row['unit']}"
            )
    else:
        print("  no effects: frames only" + (" (the diagnosis named none)" if diag else ""))
    lines = frame_lines(model) + mounting_lines(model) + fit_lines(data, res)
    for line in lines + implausible_effect_lines(model, data, res):
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
    warning = condition_warning(res)
    if warning:
        print(warning)

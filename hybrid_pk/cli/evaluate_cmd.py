"""``hybrid-pk evaluate MODEL DATA... --json OUT.json``: errors of a model (contract 5)."""

from __future__ import annotations

import argparse

from hybrid_pk.calibration.settings import FitSettings
from hybrid_pk.cli.common import (
    frame_parameter_count,
    frame_sets_for,
    mounting_lines,
    read_data,
    stats_line,
    tilt_note,
    write_json,
)
from hybrid_pk.cli.fit_settings import fit_lines, settings_of
from hybrid_pk.cli.gross import fitted_on_note, gross_warning
from hybrid_pk.cli.options import (
    add_data,
    add_fit_frames,
    add_json,
    add_model,
    add_report,
)
from hybrid_pk.cli.progress import progress
from hybrid_pk.cli.settings_flags import add_settings_flags
from hybrid_pk.errors import HybridPKError
from hybrid_pk.io.hybrid_file import networks_used
from hybrid_pk.io.model_file import NOMINAL_PREFIX, load_model, model_robot
from hybrid_pk.pipelines.evaluation import evaluate_model
from hybrid_pk.pipelines.network_rule import verdict_line

_DESCRIPTION = """\
Errors of MODEL on DATA: position error = distance of measured and predicted point
[mm], orientation error = angle of R_measured R_model^T [deg] (null for position-only
data); mean, rms, p95 and max. MODEL is a model file or nominal:ROBOT (the URDF as it
is, identity base and tool frames). The model's own base/tool frames are used unless
--fit-frames fits them (only them) to DATA first; nominal:ROBOT needs --fit-frames
unless DATA is the flange measured in the robot base frame.
JSON: {"n", "position_mm": {mean, rms, p95, max}, "orientation_deg": {...} | null};
a model with residual networks adds "networks": {"used", "rule", ...}: a frame re-fit
on a new set-up (calibrate --refit) keeps them only if they beat the physics on its
rows, held out; else the extended model is evaluated.
"""


DESCRIPTION = _DESCRIPTION


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``hybrid-pk evaluate``."""
    add_model(p)
    add_data(p)
    add_json(
        p,
        help="write the errors: n, position_mm and orientation_deg (mean, rms, p95, max "
        "in mm and deg)",
    )
    add_report(
        p,
        help="write DIR/report.md with PNGs: the error table [mm, deg] of MODEL beside the "
        "nominal URDF with frames fitted to DATA, error histograms (like the paper's Fig. "
        "4), the error along each joint, and ISO 9283 AP/RP [mm, deg] of repeated poses",
    )
    add_fit_frames(
        p,
        help="first fit only the base and tool frames [m, rad] to DATA (effects and networks kept)",
    )
    add_settings_flags(p, FitSettings, skip=("gravity",))  # the model keeps its mounting


def run(args: argparse.Namespace) -> int:
    settings = settings_of(args, FitSettings)
    loaded = load_model(args.model, robot_check=args.robot, end_link=args.end_link)
    robot = model_robot(loaded)
    robot.requires_grad_(False)
    sets = frame_sets_for(args, loaded.model.base.sets)
    if not args.fit_frames and (args.tool or args.base or args.robust != "none"):
        raise HybridPKError(
            "--tool, --base and --robust set how frames are fitted: add --fit-frames"
        )

    total = 2 + bool(args.fit_frames) + bool(args.report)
    with progress("evaluate", total=total) as bar:
        bar.stage("reading data")
        n_params = frame_parameter_count(sets, False) if args.fit_frames else None
        data = read_data(
            args.data, robot, n_params=n_params, skip_bad_rows=args.skip_bad_rows, args=args
        )
        up = loaded.model.base.matrix()[0, :3, 2].detach().clone()  # the fit moves it
        res = evaluate_model(
            loaded, data, model_label=args.model, sets=sets, fit_frames=args.fit_frames,
            priors=settings.priors(loaded.model if loaded.frames_fitted else None)
            if args.fit_frames else None,
            robust=settings.loss(), report=args.report, stage=bar.stage,
        )  # fmt: skip
        if args.json:
            write_json(args.json, res.summary)

    _print_summary(args, res.loaded, robot, data, res)
    if res.frame_fit is not None:  # as calibrate --refit: the mounting the fitted base implies
        lines = mounting_lines(res.loaded.model, check=False) + fit_lines(data, res.frame_fit)
        if loaded.frames_fitted:
            lines.append(tilt_note(up, res.loaded.model, "the frames fitted to DATA tilt"))
        for line in filter(None, lines):
            print(line)
    if args.json:
        print(f"wrote {args.json}")
    if res.report:
        print(f"wrote {res.report}")
    return 0


def _print_summary(args, loaded, robot, data, res) -> None:
    """The summary lines of ``res`` (:class:`~hybrid_pk.pipelines.evaluation.EvaluationResult`)."""
    position, orientation = res.position, res.orientation
    nominal = args.model.startswith(NOMINAL_PREFIX)
    kind = "nominal URDF" if nominal else f"{len(loaded.model.effects)} effect(s)"
    if loaded.has_networks:
        kind += " + residual networks" + ("" if networks_used(loaded) else " (not used)")
    if args.fit_frames:
        frames = "frames fitted to DATA"
    elif loaded.frames_fitted:
        frames = "frames of the model"
    else:
        frames = "identity frames"
    print(
        f"evaluated {args.model} ({robot.name}, {kind}, {frames}) on {data.n} rows from "
        f"{len(data.sources)} file(s)"
    )
    if not args.fit_frames and not loaded.frames_fitted:
        print(
            "warning: base and tool frames are identity: the errors are only meaningful if "
            "DATA is the flange measured in the robot base frame; otherwise add --fit-frames"
        )
    if (
        orientation is not None
        and not args.fit_frames
        and loaded.metadata.get("orientation_fitted") is False
    ):
        print(
            "warning: the model was calibrated on position-only data, so its tool "
            "orientation is unknown and part of the orientation errors; add --fit-frames"
        )
    mean_mm = float(position.mean())
    for line in (
        gross_warning(args.model, mean_mm, bool(args.fit_frames), cause=res.gross_cause),
        *(f"warning: {text}" for text in res.warnings),
        fitted_on_note(args.model, loaded.metadata, data.sources),
    ):
        if line:
            print(line)
    verdict = loaded.networks.get("transfer") if loaded.has_networks else None
    if verdict:
        print(verdict_line(verdict))
    print(stats_line("position error [mm]", position))
    if orientation is not None:
        print(stats_line("orientation error [deg]", orientation))
    else:
        print("orientation error [deg]: none (position-only data)")

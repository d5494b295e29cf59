"""``hybrid-pk calibrate DATA... --model MODEL --refit tool|base|frames --out MODEL2``:
keep everything of MODEL (effects, networks) and re-fit only its frame(s)."""

from __future__ import annotations

import argparse
import math

from hybrid_pk.calibration.settings import FitSettings
from hybrid_pk.cli.calibrate_output import (
    error_summary,
    frame_lines,
    save_with_urdf,
    urdf_target,
    wrote_line,
)
from hybrid_pk.cli.common import (
    data_files,
    frame_parameter_count,
    mounting_lines,
    read_data,
    stats_line,
    tilt_note,
)
from hybrid_pk.cli.fit_settings import fit_lines, robust_summary
from hybrid_pk.cli.gross import gross_warning
from hybrid_pk.cli.progress import progress
from hybrid_pk.data import MeasuredData
from hybrid_pk.errors import HybridPKError
from hybrid_pk.io.model_file import LoadedModel, load_model, model_robot, save_model
from hybrid_pk.pipelines.refit import refit

__all__ = ["run_refit", "spread_line"]


def run_refit(args: argparse.Namespace, settings: FitSettings) -> int:
    """Re-fit the ``--refit`` frame(s) of ``--model`` on DATA with the frames, loss and
    tool limit of ``settings`` (flags over ``--config``) and write ``--out``."""
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
    sets = data_files(args) if args.frames_per_file else 1
    which = args.refit

    with progress("calibrate --refit", total=3) as bar:
        bar.stage("reading data")
        data = read_data(
            args.data,
            robot,
            n_params=frame_parameter_count(sets, False) // (1 if which == "frames" else 2),
            skip_bad_rows=args.skip_bad_rows,
            args=args,
        )
        bar.stage(f"re-fitting the {which} frame(s)")
        priors = settings.priors(loaded.model if loaded.frames_fitted else None)
        up = loaded.model.base.matrix()[0, :3, 2].detach().clone()  # the re-fit moves it
        result = refit(
            loaded, data, which, frames_per_file=args.frames_per_file, priors=priors,
            robust=settings.loss(),
        )  # fmt: skip
        model, res, before, after = result.model, result.fit, result.before, result.after
        bar.stage("writing")
        urdf = urdf_target(args, refit=True)
        save_with_urdf(
            lambda: save_model(
                args.out, model, networks=result.networks if loaded.has_networks else None,
                metadata=_metadata(args, loaded, data, res),
            ), model, args, urdf,
        )  # fmt: skip

    frames = {"frames": "base and tool frames"}.get(which, f"{which} frame")
    per_file = " (one set per file)" if args.frames_per_file else ""
    print(
        f"re-fitted the {frames}{per_file} of {args.model} ({robot.name}, "
        f"{len(model.effects)} effect(s) kept"
        + (", residual networks kept" if loaded.has_networks else "")
        + f") on {data.n} rows from {len(data.sources)} file(s)"
    )
    # the mounting the re-fitted base implies (level-tracker: the new set-up's tilt); the
    # note on a fixed mounting is tilt_note's, against the model's own base
    print(spread_line(frames, res, data.n))
    for line in frame_lines(model) + mounting_lines(model, check=False) + fit_lines(data, res):
        print(line)
    if result.verdict is not None:
        print(result.verdict.line())
    for note in (tilt_note(up, model, "the re-fitted base tilts"), _gross_warning(which, after[0])):
        if note:
            print(note)
    for i, (name, unit) in enumerate((("position", "mm"), ("orientation", "deg"))):
        if after[i] is None:
            continue
        if before is not None:
            print(stats_line(f"{name} before [{unit}]", before[i]))
        print(stats_line(f"{name} after [{unit}]", after[i]))
    if after[2]:
        print(after[2])
    print(wrote_line(args.out, model, args, urdf))
    return 0


def spread_line(frames: str, res, rows: int) -> str:
    """How well ``rows`` rows fix the re-fitted frame(s): a least-squares fit of p
    parameters spends p of its residuals' variance on them (the trace of its hat
    matrix), so over the rows it moves a point by σ√(p/rows) RMS, σ the fit's noise per
    coordinate (at most: orientation residuals, where measured, take a share)."""
    p, sigma = res.n_params, res.sigma_pos_mm
    added = sigma * math.sqrt(p / rows)
    return (
        f"  the {frames} ({p} parameters) from {rows} rows: the re-fit adds about "
        f"{added:.3g} mm RMS at these rows, more beyond their spread (the fit's noise "
        f"{sigma:.3g} mm per coordinate x sqrt({p}/{rows})); four times the rows halve it"
    )


def _gross_warning(which: str, position_mm) -> str | None:
    """A warning when the re-fitted model still misses the rows by more than small
    corrections explain (the diagnosis' ``gross_error_mm``): more moved than the
    re-fitted frame, or the rows are not this robot's."""
    refitted = (
        "the base and tool frames"
        if which == "frames"
        else f"the {which} frame (--refit frames re-fits both frames)"
    )
    return gross_warning(
        "after the re-fit the model still",
        float(position_mm.mean()),
        True,
        cause=f"more changed than {refitted}, or the rows are not this robot's",
    )


def _metadata(args, loaded: LoadedModel, data: MeasuredData, res) -> dict:
    """MODEL's metadata with this re-fit appended to its history."""
    history = list(loaded.metadata.get("refits", []))
    history.append(
        {
            "refit": args.refit,
            "data": list(data.sources),
            "n_rows": data.n,
            "frames_per_file": bool(args.frames_per_file),
            "fitted": error_summary(res),
            "frames": None if res.frame_report is None else res.frame_report.to_json(),
            "robust": robust_summary(data, res),
        }
    )
    metadata = {k: v for k, v in loaded.metadata.items() if k != "created"}
    metadata["refits"] = history
    if args.refit != "base":  # the tool's orientation is known only from orientation data
        metadata["orientation_fitted"] = data.quat is not None
    return metadata

"""What ``hybrid-pk calibrate`` writes and prints: effect rows, frames, error summaries,
the corrected URDF, the identifiability warning."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from hybrid_pk.calibration.covariance import MAX_CONDITION
from hybrid_pk.calibration.diagnosis import report_value
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.effects.joint import JointOffset
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.metrics import error_stats
from hybrid_pk.geometry import matrix_to_rpy
from hybrid_pk.io.urdf_export import export_urdf
from hybrid_pk.output_file import replacing

__all__ = [
    "MAX_CONDITION",
    "add_urdf_options",
    "condition_warning",
    "effect_rows",
    "error_summary",
    "format_value",
    "frame_lines",
    "save_with_urdf",
    "urdf_beside",
    "urdf_target",
    "wrote_line",
]


def effect_rows(model: ExtendedModel, res: FitResult) -> list[dict]:
    """Value, 1-sigma std and unit of every effect of a fit (reporting convention)."""
    rows = []
    for e in model.effects:
        value, std, components = report_value(e, res.std[res.block_slice(e.label)])
        row = {"effect": e.label, "value": value, "std": std, "unit": e.unit}
        if components is not None:
            row["components"] = components
        rows.append(row)
    return rows


def format_value(v) -> str:
    """A scalar with 6 significant digits, a vector as ``(a, b, c)`` with 4."""
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"
    return f"{v:.6g}"


def _fixed(x) -> str:
    return f"{round(float(x), 5) + 0.0:.5f}"  # + 0.0: no "-0.00000"


def frame_lines(model: ExtendedModel) -> list[str]:
    """One line per base and tool frame set: xyz [m] and rpy [rad]."""
    lines = []
    for name, frame in (("base frame", model.base), ("tool frame", model.tool)):
        T = frame.matrix().detach()
        for g in range(frame.sets):
            tag = f" [{g}]" if frame.sets > 1 else ""
            xyz = ", ".join(_fixed(x) for x in T[g, :3, 3])
            rpy = ", ".join(_fixed(x) for x in matrix_to_rpy(T[g, :3, :3]))
            lines.append(f"  {name}{tag:<6} xyz [m] ({xyz})  rpy [rad] ({rpy})")
    return lines


def error_summary(res: FitResult) -> dict:
    """Error statistics of a fit for the model file's metadata."""
    out = {"position_mm": error_stats(res.position_mm).to_dict()}
    out["orientation_deg"] = (
        None if res.orientation_deg is None else error_stats(res.orientation_deg).to_dict()
    )
    return out


def condition_warning(res: FitResult, limit: int = 3) -> str | None:
    """The identifiability warning of an ill-conditioned fit, naming up to ``limit``
    groups of parameters the data cannot separate (:meth:`FitResult.undetermined`) and
    pairs whose estimates are correlated at |r| >= 0.999; None if well posed."""
    if res.condition < MAX_CONDITION:
        return None
    groups = ["{" + ", ".join(g) + "}" for g in res.undetermined(MAX_CONDITION)]
    pairs = [f"{a} ~ {b} (r = {r:+.4f})" for _, a, _, b, r in res.correlated_pairs(0.999)]
    which = "; ".join(
        part
        for part in (
            f"cannot separate: {'; '.join(groups[:limit])}" if groups else "",
            f"these trade off exactly: {'; '.join(pairs[:limit])}" if pairs else "",
        )
        if part
    )
    return (
        f"warning: condition number {res.condition:.3g}: the rows cannot separate some "
        f"parameters ({which or 'some parameter combination is not determined'}); their "
        "individual values and std are unreliable, their sum is fine for prediction. "
        "Poses whose flange orientation never changes (only ISO 9283 cube poses) cannot "
        "separate base and tool translation; components of link lengths along parallel "
        "joint axes never separate"
    )


# ----------------------------------------------------------------------------- URDF


def add_urdf_options(parser: argparse.ArgumentParser) -> None:
    """``--urdf``, ``--no-urdf``, ``--urdf-frames``, ``--urdf-fold-offsets``."""
    parser.add_argument(
        "--urdf",
        metavar="OUT.urdf",
        help="corrected URDF of the geometric part, lengths [m], angles [rad] (default: "
        "MODEL.urdf next to MODEL; with --refit only when given)",
    )
    parser.add_argument("--no-urdf", action="store_true", help="write no corrected URDF")
    parser.set_defaults(also_writes=urdf_beside)
    parser.add_argument(
        "--urdf-frames",
        action="store_true",
        help="put the fitted base frame (root link 'measurement_frame') and tool frame "
        "(leaf link 'measured_point') into the URDF as fixed joints",
    )
    parser.add_argument(
        "--urdf-fold-offsets",
        action="store_true",
        help="fold joint offsets [rad] into the URDF joint origins (the URDF then reads "
        "commanded joint values) instead of listing them as comments",
    )


def urdf_target(args: argparse.Namespace, refit: bool) -> Path | None:
    """Where the corrected URDF goes: ``--urdf``, ``MODEL.urdf`` (not for a re-fit), or
    nowhere (``--no-urdf``)."""
    if args.no_urdf:
        return None
    if args.urdf:
        return Path(args.urdf)
    return None if refit else Path(f"{args.out}.urdf")


def urdf_beside(args: argparse.Namespace) -> list[tuple[str, Path]]:
    """The URDF written beside ``--out`` unless ``--urdf`` names it (for the check of
    the outputs before the command runs, :mod:`hybrid_pk.cli.outputs`)."""
    if args.no_urdf and args.urdf:
        raise HybridPKError(f"--urdf {args.urdf} and --no-urdf: give one of them")
    target = urdf_target(args, refit=args.model is not None or args.refit is not None)
    return [] if target is None or args.urdf else [("its URDF", target)]


def save_with_urdf(save: Callable[[], object], model: ExtendedModel, args, target) -> None:
    """The model file (``save()`` writes it) and the corrected URDF of ``model`` at
    ``target`` (none if None), both or neither where a write fails: the URDF is written
    in full first, then the model file replaced, then the URDF renamed in."""
    if target is None:
        save()
        return
    with replacing(target) as tmp:
        export_urdf(
            model,
            tmp,
            include_base=args.urdf_frames,
            include_tool=args.urdf_frames,
            fold_joint_offsets=args.urdf_fold_offsets,
        )
        save()


def wrote_line(out, model: ExtendedModel, args: argparse.Namespace, urdf: Path | None) -> str:
    """``wrote MODEL and MODEL.urdf``; where the URDF lists joint offsets as comments
    (not folded into the joint origins), it reads true joint values, not the commanded
    ones a controller sends, and the line says so with the two ways to fold them."""
    line = f"wrote {out}" + (f" and {urdf}" if urdf else "")
    offsets = [e.joint for e in model.effects if isinstance(e, JointOffset)]
    if urdf is None or not offsets or args.urdf_fold_offsets:
        return line
    return (
        f"{line} (its joint offsets of {', '.join(offsets)} are comments, not in the joint "
        "origins: it reads true joint values, not a controller's commanded ones; "
        "--urdf-fold-offsets or 'hybrid-pk export MODEL --format urdf' folds them in)"
    )

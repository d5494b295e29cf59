"""``--tool``, ``--base``, ``--max-tool-offset`` and ``--robust``: the options of every
command that fits frames (calibrate, diagnose, evaluate --fit-frames), worded alike."""

from __future__ import annotations

import argparse
from pathlib import Path

from hybrid_pk.calibration.frames import (
    DEFAULT_TOOL_STD_M,
    MAX_TOOL_TRANSLATION_M,
    FramePriors,
    FrameSpec,
    parse_frame_spec,
)
from hybrid_pk.calibration.robust import CUT_WEIGHT, OUTLIER_K, ROBUST_LOSSES, check_robust
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import HybridPKError

__all__ = [
    "add_frame_options",
    "add_robust",
    "diagnosis_notes",
    "frame_priors",
    "frame_report_lines",
    "robust_lines",
    "robust_loss",
]

_FRAME_HELP = (
    "{what} known from outside the data, X,Y,Z[,RX,RY,RZ] in metres and roll-pitch-yaw "
    "radians ({frame}): fixed as given (only the translation with three values), or "
    "after 'seed:' a start and prior that the data refine where they determine it"
)


def add_frame_options(parser: argparse.ArgumentParser) -> None:
    """``--tool``, ``--base`` and ``--max-tool-offset``."""
    parser.add_argument(
        "--tool",
        metavar="X,Y,Z[,RX,RY,RZ]",
        help=_FRAME_HELP.format(
            what="tool frame (the measured point on the flange, e.g. from the target's "
            "mount drawing)",
            frame="flange frame",
        ),
    )
    parser.add_argument(
        "--base",
        metavar="X,Y,Z[,RX,RY,RZ]",
        help=_FRAME_HELP.format(
            what="base frame (the robot root in the measurement frame)",
            frame="measurement frame",
        ),
    )
    parser.add_argument(
        "--max-tool-offset",
        type=float,
        default=MAX_TOOL_TRANSLATION_M,
        metavar="M",
        help="a fitted tool translation beyond M metres from the flange is reported as "
        f"implausible (default: {MAX_TOOL_TRANSLATION_M:g})",
    )


def add_robust(parser: argparse.ArgumentParser) -> None:
    """``--robust none|huber|cauchy``."""
    parser.add_argument(
        "--robust",
        choices=("none", *ROBUST_LOSSES),
        default="none",
        help="down-weight rows with gross errors (a broken beam, a bad visit): huber "
        "(bounded influence) or cauchy (a wild row has no pull); every down-weighted row "
        "is reported (default: none, plain least squares)",
    )


def frame_priors(args: argparse.Namespace, previous: ExtendedModel | None = None) -> FramePriors:
    """The known frames of ``--tool``/``--base``; without ``--tool``, the tool of a
    ``previous`` model (one frame set) is the centre of the tool's prior."""
    tool = None if getattr(args, "tool", None) is None else parse_frame_spec(args.tool, "--tool")
    base = None if getattr(args, "base", None) is None else parse_frame_spec(args.base, "--base")
    if tool is None and previous is not None and previous.tool.sets == 1:
        T = previous.tool.matrix()[0].detach()
        tool = FrameSpec(
            T[:3, 3].clone(), None, fixed=False, std_m=DEFAULT_TOOL_STD_M,
            source="the model's tool frame",
        )  # fmt: skip
    limit = getattr(args, "max_tool_offset", MAX_TOOL_TRANSLATION_M)
    if not limit > 0:
        raise HybridPKError(f"--max-tool-offset must be a positive length [m], got {limit:g}")
    priors = FramePriors(tool=tool, base=base, max_tool_m=limit)
    if tool is not None and tool.fixed and float(tool.translation.norm()) > limit:
        raise HybridPKError(
            f"--tool {args.tool}: a tool {float(tool.translation.norm()):.3g} m from the "
            f"flange is beyond --max-tool-offset ({limit:g} m); check the units (metres)"
        )
    return priors


def robust_loss(args: argparse.Namespace) -> str | None:
    """The ``--robust`` loss, or None for least squares."""
    return check_robust(getattr(args, "robust", None))


def frame_report_lines(result) -> list[str]:
    """The frame report of a fit as ``note:`` / ``warning:`` lines."""
    report = getattr(result, "frame_report", None)
    if report is None:
        return []
    lines = [f"warning: {d['text']}" for d in report.directions]
    return lines + [f"warning: {w}" for w in report.warnings]


def _rows_text(rows: list[dict], what: str, limit: int = 8) -> str:
    listed = ", ".join(f"{Path(r['file']).name}:{r['row']} ({r[what]:.3g})" for r in rows[:limit])
    return listed + (f" and {len(rows) - limit} more" if len(rows) > limit else "")


def robust_lines(outliers: list[dict], robust: dict | None) -> list[str]:
    """Down-weighted rows of a robust fit and outlier rows, one line each."""
    lines = []
    if robust is not None and robust.get("down_weighted"):
        rows = robust["down_weighted"]
        cut = [r for r in rows if r["weight"] < CUT_WEIGHT]
        text = f"robust fit ({robust['loss']}): {len(rows)} row(s) down-weighted to under half "
        text += f"their weight, {len(cut)} of them under {CUT_WEIGHT:g}"
        if cut:
            text += f" (file:row (weight)): {_rows_text(cut, 'weight')}"
        lines.append(text + "; all listed in the JSON")
    if outliers:
        active = robust is not None and robust.get("loss")
        hint = "" if active else "; --robust cauchy down-weights them"
        lines.append(
            f"warning: {len(outliers)} outlier row(s) beyond {OUTLIER_K:g} sigma (file:row "
            f"(position error mm)): {_rows_text(outliers, 'position_mm')}{hint}"
        )
    return lines


def diagnosis_notes(diagnosis) -> list[str]:
    """Frames, structural findings, outliers and down-weighted rows of a diagnosis."""
    lines = []
    structural = getattr(diagnosis, "structural", None)
    if structural is not None:
        lines.append(f"structural: {structural['message']}")
        for f in structural["findings"]:
            lines.append(f"  not a plain cause: {f['cause']}: {f['why']}")
    frames = getattr(diagnosis, "frames", None) or {}
    lines += [f"warning: {d['text']}" for d in frames.get("directions", [])]
    lines += [f"warning: {w}" for w in frames.get("warnings", [])]
    return lines + robust_lines(
        getattr(diagnosis, "outliers", []), getattr(diagnosis, "robust", None)
    )

"""Helpers shared by the sub-commands: robot, data and model loading with clear errors,
progress on stderr, frame (re-)fitting, summaries and JSON output."""

from __future__ import annotations

import json
import math
import os
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import torch
from tqdm import tqdm

from hybrid_pk.calibration.fit import FitResult, fit, initialise_frames
from hybrid_pk.data import DataWarning, MeasuredData, read_table_for
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.metrics import ErrorStats, error_stats
from hybrid_pk.robot import Robot

__all__ = [
    "FRAME_LABELS",
    "add_data_arguments",
    "add_gravity_argument",
    "fit_frames",
    "frame_parameter_count",
    "load_robot",
    "mounting_lines",
    "progress",
    "read_data",
    "stats_line",
    "with_frame_sets",
    "write_json",
]

# Parameter blocks of the frames, by --refit choice (labels of calibration.fit).
FRAME_LABELS = {
    "base": ("base_frame.translation", "base_frame.rotation"),
    "tool": ("tool_frame.translation", "tool_frame.rotation"),
}
FRAME_LABELS["frames"] = FRAME_LABELS["base"] + FRAME_LABELS["tool"]


def add_data_arguments(parser) -> None:
    """``DATA...``, ``--frames-per-file`` and ``--skip-bad-rows``, worded alike everywhere."""
    parser.add_argument(
        "data",
        nargs="+",
        metavar="DATA",
        help="measured pose table(s), .csv or .parquet: one column per joint [rad, m for "
        "prismatic], x y z [m], optional qw qx qy qz, temperature [degC], payload [kg]; "
        "several files are one campaign measured in series",
    )
    parser.add_argument(
        "--frames-per-file",
        action="store_true",
        help="give each DATA file its own base and tool frame (tracker moved, tool "
        "re-mounted); effects are shared",
    )
    parser.add_argument(
        "--skip-bad-rows",
        action="store_true",
        help="leave out rows with NaN/inf, text, out-of-limit joints or non-unit "
        "quaternions (each reported by file and row) instead of stopping at the first",
    )


def add_gravity_argument(parser) -> None:
    """``--gravity X,Y,Z|level-tracker``, worded alike in calibrate and diagnose."""
    parser.add_argument(
        "--gravity",
        metavar="X,Y,Z|level-tracker",
        help="how the robot is mounted, for compliance and deflection: gravity in the "
        "robot's root frame [m/s^2] (ceiling: 0,0,9.81), or level-tracker: the "
        "measurement frame is levelled (laser tracker, total station), so gravity is -z "
        "there and its direction in the robot frame follows from the fitted base frame "
        "(default: upright, 0,0,-9.81)",
    )


def mounting_lines(model: ExtendedModel) -> list[str]:
    """One line per base frame set on the gravity the model's statics use (none when
    the robot is the default upright one)."""
    if model.gravity.is_default:
        return []
    lines = []
    with torch.no_grad():
        T = model.base.matrix()
        for g in range(model.base.sets):
            vec = model.gravity.vector
            if model.gravity.levelled:
                vec = (T[g, :3, :3].T @ torch.tensor(vec, dtype=T.dtype)).tolist()
            norm = max(sum(v * v for v in vec) ** 0.5, 1e-12)
            tilt = math.degrees(math.acos(max(-1.0, min(1.0, -vec[2] / norm))))
            tag = f" [{g}]" if model.base.sets > 1 else ""
            text = ", ".join(f"{v:.4g}" for v in vec)
            lines.append(
                f"  gravity{tag} ({text}) m/s^2 in the robot root frame: root z axis "
                f"{tilt:.1f} deg from upright ({model.gravity.describe()})"
            )
    return lines


def load_robot(name: str, end_link: str | None = None) -> Robot:
    """Robot from a shipped name or URDF path, parameters frozen (fits only move effects)."""
    robot = Robot.from_urdf(name, end_link=end_link)
    robot.requires_grad_(False)
    return robot


def read_data(
    paths: Sequence[str | os.PathLike],
    robot: Robot,
    *,
    n_params: int | None = None,
    skip_bad_rows: bool = False,
) -> MeasuredData:
    """Read and validate DATA for ``robot``; data warnings become ``note:`` lines.

    Args:
        paths: table files.
        robot: gives joint names, limits and types.
        n_params: parameters that will be fitted (fewer rows is an error); None: 1.
        skip_bad_rows: leave out (and report) bad rows instead of failing.
    """
    with data_notes():
        return read_table_for(
            [str(p) for p in paths],
            robot,
            n_params=n_params or 1,
            on_bad_row="skip" if skip_bad_rows else "error",
        )


@contextmanager
def data_notes() -> Iterator[None]:
    """Print the data warnings raised inside the block as ``note:`` lines (after it);
    other warnings go on as warnings."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        yield
    for w in caught:
        if issubclass(w.category, DataWarning):
            print(f"note: {w.message}")
        else:  # not ours to swallow
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def frame_parameter_count(sets: int, position_only: bool) -> int:
    """Number of base + tool frame parameters that a fit estimates."""
    return sets * (9 if position_only else 12)


@contextmanager
def progress(desc: str, total: int | None = None) -> Iterator:
    """Progress bar on stderr; yields ``step(text)`` that starts the next named stage.

    The bar is removed when done, so a quick command leaves only its summary.
    """
    bar = tqdm(total=total, desc=desc, file=sys.stderr, leave=False, unit="step", delay=0.5)

    def step(text: str) -> None:
        bar.set_postfix_str(text, refresh=False)
        bar.update(1)

    try:
        yield step
    finally:
        bar.close()


def with_frame_sets(model: ExtendedModel, sets: int, keep: str | None = None) -> ExtendedModel:
    """``model`` with ``sets`` base/tool frame sets (same robot and effect modules).

    Args:
        model: source model (returned unchanged if it already has ``sets`` sets).
        sets: frame sets wanted (1, or one per DATA file).
        keep: ``"base"`` or ``"tool"``: that frame keeps its values (a single set is
            repeated); the other starts at identity. None: both start at identity.

    Raises:
        HybridPKError: if a kept frame has several sets that cannot map to ``sets``.
    """
    if model.base.sets == sets:
        return model
    kept = {}
    if keep is not None:
        frame = getattr(model, keep)
        if frame.sets != 1:
            raise HybridPKError(
                f"the model has {frame.sets} {keep} frames (one per file of its "
                f"calibration) but this re-fit has {sets} frame set(s); give as many DATA "
                f"files with --frames-per-file, or --refit frames"
            )
        kept[keep] = frame.matrix().detach()
    return ExtendedModel(
        model.robot, list(model.effects), frame_sets=sets, gravity=model.gravity, **kept
    )


def fit_frames(
    model: ExtendedModel, data: MeasuredData, cond: Conditions, which: str = "frames"
) -> FitResult:
    """Register then least-squares fit only the ``which`` frame(s); effects stay fixed.

    Args:
        which: ``"base"``, ``"tool"`` or ``"frames"`` (both).
    """
    initialise_frames(model, data, cond, which=which)
    return fit(model, data, free=list(FRAME_LABELS[which]), cond=cond)


def stats_line(label: str, stats: ErrorStats | torch.Tensor, digits: int = 4) -> str:
    """``label  mean .. rms .. p95 .. max ..`` on one line."""
    s = stats if isinstance(stats, ErrorStats) else error_stats(stats)
    return (
        f"{label:<24} mean {s.mean:.{digits}g}  rms {s.rms:.{digits}g}  "
        f"p95 {s.p95:.{digits}g}  max {s.max:.{digits}g}"
    )


def write_json(path: str | os.PathLike, obj: dict) -> Path:
    """Write ``obj`` as indented JSON (NaN/inf refused: they are not JSON)."""
    path = Path(path)
    if path.parent and not path.parent.is_dir():
        path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path

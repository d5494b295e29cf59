"""Helpers shared by the sub-commands: robot and data loading with clear errors, frame
sets and (re-)fitting, summaries and JSON output. The shared
flags are in :mod:`hybrid_pk.cli.options`, the progress display in
:mod:`hybrid_pk.cli.progress`."""

from __future__ import annotations

import argparse
import json
import math
import os
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import torch

from hybrid_pk.data import DataWarning, MeasuredData, read_table_for
from hybrid_pk.data.parts import split_all
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import DataError, HybridPKError
from hybrid_pk.evaluation.metrics import ErrorStats, error_stats
from hybrid_pk.output_file import json_text, write_text
from hybrid_pk.pipelines.calibration import FRAME_LABELS as FRAME_LABELS
from hybrid_pk.pipelines.calibration import refit_frames as fit_frames
from hybrid_pk.pipelines.refit import with_frame_sets as with_frame_sets
from hybrid_pk.robot import Robot

__all__ = [
    "FRAME_LABELS",
    "TILT_NOTE_DEG",
    "data_files",
    "data_notes",
    "fit_frames",
    "flag_values",
    "frame_parameter_count",
    "frame_set_index",
    "frame_sets_for",
    "gravity_note",
    "load_frozen_model",
    "load_robot",
    "mounting_lines",
    "read_data",
    "read_json",
    "stats_line",
    "tilt_note",
    "with_frame_sets",
    "write_json",
]


# [deg] a gravity effect whose gravity is off by this much points 1.7 % of its size
# astray (sin 1°), about the relative std a compliance is fitted to in a campaign of a
# few hundred poses: beyond it the mounting matters to the model
TILT_NOTE_DEG = 1.0


def mounting_lines(model: ExtendedModel, check: bool = True) -> list[str]:
    """One line per base frame set on the gravity the model's statics use (none when
    the robot is the default upright one), and with ``check`` the note of
    :func:`gravity_note` where the stated gravity and the fitted base disagree."""
    note = gravity_note(model) if check else None
    lines = [] if note is None else [note]
    if model.gravity.is_default:
        return lines
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
    return lines + ([] if note is None else [note])


def gravity_note(model: ExtendedModel) -> str | None:
    """A note when the model's gravity effects take gravity fixed in the robot frame
    (the default upright, or ``--gravity X,Y,Z``) and its fitted base frame turns that
    gravity more than ``TILT_NOTE_DEG`` from the measurement frame's vertical: with a
    levelled instrument (a total station, a levelled tracker) the mounting is then
    stated wrongly, and the effects fitted under it stand in for the difference."""
    loaded = [e.label for e in model.loaded_effects()]
    if model.gravity.levelled or not loaded:
        return None
    with torch.no_grad():
        R = model.base.matrix()[:, :3, :3]
        g = torch.tensor(model.gravity.vector, dtype=R.dtype)
        down = -(R @ g)[:, 2] / g.norm()  # cosine to the measurement frame's -z
        angle = math.degrees(math.acos(float(down.clamp(-1.0, 1.0).min())))
    if angle <= TILT_NOTE_DEG:
        return None
    stated = "upright, the default" if model.gravity.is_default else "--gravity"
    return (
        f"note: the gravity effects ({', '.join(loaded)}) take gravity as "
        f"{model.gravity.describe()} ({stated}), which the fitted base frame turns "
        f"{angle:.1f} deg from the measurement frame's vertical; if the instrument is "
        "levelled (a total station, a levelled laser tracker), the mounting is stated "
        "wrongly and the named causes may stand in for it: --gravity level-tracker "
        "takes the mounting from the data"
    )


def tilt_note(up, after: ExtendedModel, subject: str) -> str | None:
    """A note when ``subject`` (with its verb: "the re-fitted base tilts") tilts the
    robot (its z axis, was ``up`` in the measurement frame) by more than
    ``TILT_NOTE_DEG`` while its gravity effects assume a fixed mounting (``--gravity``
    in the root frame)."""
    gravity_effects = [e.label for e in after.loaded_effects()]
    if after.gravity.levelled or not gravity_effects:
        return None
    z1 = after.base.matrix()[0, :3, 2].detach()
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(up.to(z1.dtype) @ z1)))))
    if tilt <= TILT_NOTE_DEG:
        return None
    return (
        f"note: {subject} the robot by {tilt:.1f} deg against the model's, "
        f"but its gravity effects ({', '.join(gravity_effects)}) keep the mounting they were "
        "calibrated with (gravity fixed in the robot frame); if the instrument is levelled, "
        "calibrate with --gravity level-tracker and they follow the tilt"
    )


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
    args: argparse.Namespace | None = None,
) -> MeasuredData:
    """Read and validate DATA for ``robot``; data warnings become ``note:`` lines.

    Args:
        paths: table files.
        robot: gives joint names, limits and types.
        n_params: parameters that will be fitted (fewer rows is an error); None: 1.
        skip_bad_rows: leave out (and report) bad rows instead of failing.
        args: the command's arguments: their ``--split-at FILE:ROW`` cut the files
            (:mod:`hybrid_pk.data.parts`), which needs ``--frames-per-file``.
    """
    splits = getattr(args, "split_at", None)
    if splits and not getattr(args, "frames_per_file", False):
        raise DataError(
            "--split-at gives the rows from a row on frames of their own: it needs "
            "--frames-per-file"
        )
    with data_notes():
        data = read_table_for(
            [str(p) for p in paths],
            robot,
            n_params=n_params or 1,
            on_bad_row="skip" if skip_bad_rows else "error",
        )
    return split_all(data, splits)


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


def load_frozen_model(args: argparse.Namespace):
    """``args.model`` loaded for solving (ik, compensate): ``(loaded, model, robot, k)``
    with parameters frozen and ``k`` the ``--frame-set`` to use (checked)."""
    from hybrid_pk.io.model_file import load_model, model_robot

    loaded = load_model(args.model, robot_check=args.robot, end_link=args.end_link)
    model = loaded.model
    model.requires_grad_(False)
    robot = model_robot(loaded)
    return loaded, model, robot, frame_set_index(args.frame_set, model.base.sets, args.model)


def frame_set_index(value: int | None, sets: int, model: str) -> int:
    """The ``--frame-set`` of a MODEL with ``sets`` frame sets (0 for a single set).

    Raises:
        HybridPKError: several sets and none chosen, or one out of range.
    """
    if value is None:
        if sets > 1:
            raise HybridPKError(
                f"{model} has {sets} base/tool frame sets (one per calibration file); "
                f"choose one with --frame-set 0..{sets - 1}"
            )
        return 0
    if not 0 <= value < sets:
        raise HybridPKError(f"--frame-set {value}: {model} has sets 0..{sets - 1}")
    return value


def data_files(args: argparse.Namespace) -> int:
    """How many files DATA makes once ``--split-at`` has cut them."""
    return len(args.data) + len(getattr(args, "split_at", None) or [])


def frame_sets_for(args: argparse.Namespace, model_sets: int) -> int:
    """Base/tool frame sets of a command that reads MODEL and DATA (evaluate, train).

    With ``--fit-frames``: one set, or one per DATA file with ``--frames-per-file``.
    Without: the model's own sets, which must match the DATA files one to one.

    Raises:
        HybridPKError: when the model's sets and the DATA files do not match.
    """
    files = data_files(args)
    if args.fit_frames:
        return files if args.frames_per_file else 1
    if model_sets > 1 and model_sets != files:
        raise HybridPKError(
            f"{args.model} has {model_sets} base/tool frame sets (one per calibration file) "
            f"but {files} DATA file(s) were given; give one file per set, in the same order, "
            "or --fit-frames"
        )
    if args.frames_per_file and model_sets == 1 and files > 1:
        raise HybridPKError(
            f"{args.model} has one base/tool frame set; --frames-per-file needs --fit-frames"
        )
    return model_sets


def stats_line(label: str, stats: ErrorStats | torch.Tensor, digits: int = 4) -> str:
    """``label  mean .. rms .. p95 .. max ..`` on one line."""
    s = stats if isinstance(stats, ErrorStats) else error_stats(stats)
    return (
        f"{label:<24} mean {s.mean:.{digits}g}  rms {s.rms:.{digits}g}  "
        f"p95 {s.p95:.{digits}g}  max {s.max:.{digits}g}"
    )


def flag_values(args: argparse.Namespace, *names: str) -> dict:
    """``{name: args.<name>}``: flags passed on as the keyword arguments of the same name."""
    return {name: getattr(args, name) for name in names}


def read_json(path: str | os.PathLike, flag: str, kind: str = ""):
    """The document of the JSON file ``path`` given to option ``flag``; a missing or
    unreadable file is a :class:`HybridPKError` naming both (``kind``: what the file
    holds, e.g. ``"diagnosis"``, for the messages)."""
    what = f"{kind} " if kind else ""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise HybridPKError(f"{flag}: {what}file not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise HybridPKError(f"{flag}: {path} is not a {what}JSON file: {exc}") from None


def write_json(path: str | os.PathLike, obj: dict) -> Path:
    """Write ``obj`` as indented JSON (NaN/inf refused: they are not JSON)."""
    return write_text(path, json_text(obj))

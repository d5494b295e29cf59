"""A set-up that changed in the middle of a file: the tracker bumped, the tool re-mounted.

Rows measured before and after such a change need frames of their own, as files of
separate set-ups do (:mod:`.setups`), but one file gives no hint where. Fitted with one
frame set, the nominal model then misses the rows by about the move: 98.9 mm (mean) on
600 rows of the shared UR10's Series B whose last 240 rows were moved by 3° and 55 mm,
where each part's own frames leave 1.2 mm. The diagnosis named nothing and said the
URDF may be wrong in more than one place.

:func:`check_setup_change` finds the row where the set-up changed by the closed-form
registration of the rows before and after each candidate row (coarse to fine: a grid of
rows, then the grid between the best one's neighbours), and confirms it with a fit of
both parts' frames: where one frame set misses the rows by more than small corrections
make (``gross_error_mm``) and the two parts' own frames by less, it stops before any
effect is fitted, naming the file and row.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from hybrid_pk.calibration.poses import model_errors, predicted_poses
from hybrid_pk.calibration.setups import SCREEN_FACTOR, FrameFit, Rows, own_frame_rows
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import DataError
from hybrid_pk.geometry import quat_to_matrix
from hybrid_pk.geometry.registration import register_frames
from hybrid_pk.robot import Robot

__all__ = ["check_setup_change", "setup_change", "setup_change_error"]

# Candidate rows per level of the coarse-to-fine search: 24 intervals find the row of a
# change among n rows in log_24(n) levels (3 for 13,000 rows).
GRID = 24


def check_setup_change(
    model: ExtendedModel, data: MeasuredData, cond: Conditions, how: FrameFit
) -> None:
    """Refuse rows whose set-up changed within one frame group: the
    :class:`~hybrid_pk.errors.DataError` of :func:`setup_change_error` where it has one
    (the arguments are its), with ``file`` and ``row`` of the new set-up's first row."""
    error = setup_change_error(model, data, cond, how)
    if error is not None:
        raise error


def setup_change_error(
    model: ExtendedModel, data: MeasuredData, cond: Conditions, how: FrameFit
) -> DataError | None:
    """The error naming the file and row where the set-up changed within one frame
    group, or None.

    Args:
        model: the nominal model with its frames fitted to ``data`` (rows in the order
            measured) under ``cond``; each of its frame groups (a file with
            ``--frames-per-file``, else all rows) is one sequence for
            :func:`setup_change`, gated by that group's own mean position error.
        how: how that fit was made.

    Returns:
        A :class:`~hybrid_pk.errors.DataError` at the first row of the new set-up
        (``file``, ``row``) with both errors and what to do (split the file there,
        ``--frames-per-file``), for the first group with one.
    """
    position = model_errors(model, data, cond)[0]
    groups = [None] if cond.group is None else cond.group.unique().tolist()
    for g in groups:
        rows = torch.ones(data.n, dtype=torch.bool) if g is None else cond.group == g
        part, part_cond = data.subset(rows), cond.subset(rows)
        shared_mm = float(position[rows].mean())
        found = setup_change(model.robot, (part, part_cond), shared_mm, how)
        if found is not None:
            return _change_error(part, found, shared_mm)
    return None


def _change_error(data: MeasuredData, found: tuple[int, float], shared_mm: float) -> DataError:
    k, own_mm = found
    gross = diagnosis_tuning().gross_error_mm
    file, row = data.sources[int(data.file_index[k])], int(data.rows[k])
    return DataError(
        "the set-up changed here: one base/tool frame set misses the rows by "
        f"{shared_mm:.4g} mm (mean), beyond what small corrections make ({gross:g} mm), "
        f"and the rows before and from this one, each part with its own frames, by "
        f"{own_mm:.3g} mm; the tracker moved or the tool was re-mounted: split the file "
        f"here and rerun with --frames-per-file --split-at {Path(file).name}:{row} "
        "(Python: hybrid_pk.data.parts.split_at, frames_per_file=True)",
        file=file,
        row=row,
    )


def setup_change(robot: Robot, rows: Rows, shared_mm: float, how: FrameFit):
    """The row index where the set-up of ``data`` changed, and the mean position error
    [mm] of the nominal model with frames of its own before and from it; or None.

    Args:
        robot: the nominal robot.
        rows: rows of one frame set, in the order measured, and their conditions
            (``group`` ignored: one sequence).
        shared_mm: mean position error [mm] of the nominal model with one frame set.
        how: how that fit was made.

    Returns:
        ``(k, own_mm)``: the index of the first row of the new set-up and the error;
        or None where ``shared_mm`` is within ``gross_error_mm``, where the rows are too few
        for two parts with frames of their own (:func:`~.setups.own_frame_rows` each),
        or where the two parts' own frames still miss by more.
    """
    data, cond = rows
    least = own_frame_rows(data)  # rows a part needs
    gross = diagnosis_tuning().gross_error_mm
    if not shared_mm > gross or data.n < 2 * least:
        return None
    cond = replace(cond, group=None)
    nominal = ExtendedModel(robot, gravity=how.gravity)
    T_end = predicted_poses(nominal, data.q, cond, end_link=True)
    R = None if data.quat is None else quat_to_matrix(data.quat)
    lo, hi = least, data.n - least
    while True:  # coarse to fine
        rows = torch.linspace(lo, hi, GRID + 1).round().long().unique()
        scores = torch.stack([_registered_mm(T_end, data, R, int(k)) for k in rows])
        best = int(scores.argmin())
        if hi - lo <= GRID:
            k = int(rows[best])
            break
        lo, hi = int(rows[max(best - 1, 0)]), int(rows[min(best + 1, len(rows) - 1)])
    if float(scores[best]) > SCREEN_FACTOR * gross:
        return None  # registered, the parts are not near small corrections either
    parts = (data, replace(cond, group=(torch.arange(data.n) >= k).long()))
    own_mm = float(how.errors(robot, parts, parts, 2)[0].mean())
    return (k, own_mm) if own_mm <= gross else None


def _registered_mm(T_end, data: MeasuredData, R, k: int) -> torch.Tensor:
    """Mean position error [mm] of the rows before and from ``k``, each part with the
    closed-form registration of its own frames."""
    total = T_end.new_zeros(())
    for part in (slice(0, k), slice(k, data.n)):
        base, tool = register_frames(
            T_end[part], data.position[part], None if R is None else R[part]
        )
        p = (base @ T_end[part] @ tool)[:, :3, 3]
        total = total + 1e3 * (p - data.position[part]).norm(dim=-1).sum()
    return total / data.n

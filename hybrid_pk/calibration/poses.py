"""Predicted measured poses of a model, its per-row errors against measured data and
the closed-form start of its frames."""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.calibration.kept_poses import keep_poses, kept_poses
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.evaluation.metrics import pose_error, position_error_mm
from hybrid_pk.geometry import quat_to_matrix
from hybrid_pk.geometry.registration import register_frames

__all__ = ["initialise_frames", "model_errors", "predicted_poses"]


@torch.no_grad()
def initialise_frames(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    which: str = "frames",
) -> None:
    """Set base and/or tool frames to the closed-form registration of ``data``.

    Args:
        which: ``"frames"`` (both), ``"base"`` or ``"tool"``.

    With gravity from a levelled tracker the loaded end pose depends on the base frame
    itself, so the registration is repeated once from the first one's base.
    """
    R_meas = None if data.quat is None else quat_to_matrix(data.quat)
    groups = [None] if model.base.sets == 1 or cond.group is None else range(model.base.sets)
    loaded = bool(model.loaded_effects())
    passes = 2 if model.gravity.levelled and loaded and which != "tool" else 1
    for _ in range(passes):
        T_end = predicted_poses(model, data.q, cond, end_link=True)
        for g in groups:
            rows = slice(None) if g is None else cond.group == g
            if g is not None and not bool(rows.any()):
                continue
            base, tool = register_frames(
                T_end[rows], data.position[rows], None if R_meas is None else R_meas[rows]
            )
            if which in ("frames", "base"):
                model.base.reset_to(base, g)
            if which in ("frames", "tool"):
                model.tool.reset_to(tool, g)


@torch.no_grad()
def model_errors(
    model: ExtendedModel, data: MeasuredData, cond: Conditions | None = None
) -> tuple[Tensor, Tensor | None]:
    """Per-row position [mm] and orientation [deg] errors (None without orientation)."""
    T = predicted_poses(model, data.q, cond or conditions_from_data(data))
    if data.quat is None:
        return position_error_mm(data.position, T[:, :3, 3]), None
    return pose_error(data.T_measured(), T)


# Rows per model evaluation in predicted_poses (bounds the gravity and FK temporaries).
POSE_CHUNK_ROWS = 32768


@torch.no_grad()
def predicted_poses(
    model: ExtendedModel, q: Tensor, cond: Conditions, end_link: bool = False
) -> Tensor:
    """``(N, 4, 4)`` predicted measured poses (or flange poses in the robot root frame,
    ``end_link``) of joint values ``q (N, dof)``, evaluated in chunks of rows (measured
    poses: kept for the same point and rows, :mod:`.kept_poses`)."""
    kept = None if end_link else kept_poses(model, q, cond)
    if kept is not None:
        return kept.clone()  # the caller's to change
    parts = []
    for start in range(0, q.shape[0], POSE_CHUNK_ROWS):
        rows = slice(start, min(start + POSE_CHUNK_ROWS, q.shape[0]))
        sub = cond.subset(rows)
        parts.append(model.end_pose(q[rows], sub) if end_link else model(q[rows], sub))
    T = torch.cat(parts) if parts else model(q, cond)
    if not end_link:
        keep_poses(model, q, cond, T)
    return T

"""Registration that respects frames known from outside the data (``--tool``,
``--base``): the closed-form registration of both frames, then a known frame replaces
its registered value and the other frame is registered again to it."""

from __future__ import annotations

import torch

from hybrid_pk.calibration.fit import initialise_frames, predicted_poses
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import nearest_rotation, quat_to_matrix, transform
from hybrid_pk.geometry.registration import kabsch

__all__ = ["initialise_with_priors"]


def _frame_groups(sets: int, cond: Conditions):
    """``(g, rows)`` of each set ``g`` of a frame with ``sets`` sets that has rows (``g``
    None and all rows for a single set or rows without groups)."""
    if sets == 1 or cond.group is None:
        yield None, slice(None)
        return
    for g in range(sets):
        rows = cond.group == g
        if bool(rows.any()):
            yield g, rows


def _register_base_to_tool(model: ExtendedModel, data: MeasuredData, cond: Conditions) -> None:
    """Closed-form base for the model's current tool: Kabsch of the predicted points."""
    with torch.no_grad():
        T_end = predicted_poses(model, data.q, cond, end_link=True)
        for g, rows in _frame_groups(model.base.sets, cond):
            X = model.tool.matrix()[0 if g is None else g].to(T_end.dtype)
            points = (T_end[rows] @ X)[:, :3, 3]
            R, p = kabsch(points, data.position[rows])
            model.base.reset_to(transform(R, p), g)


def _register_tool_to_base(model: ExtendedModel, data: MeasuredData, cond: Conditions) -> None:
    """Closed-form tool for the model's current base: linear in its translation."""
    with torch.no_grad():
        T_end = predicted_poses(model, data.q, cond, end_link=True)
        for g, rows in _frame_groups(model.tool.sets, cond):
            B = model.base.matrix()[0 if g is None else g].to(T_end.dtype)
            R_F, p_F = T_end[rows, :3, :3], T_end[rows, :3, 3]
            A = B[:3, :3] @ R_F  # (n, 3, 3): p_meas = p_B + R_B p_F + (R_B R_F) p_X
            rhs = data.position[rows] - B[:3, 3] - p_F @ B[:3, :3].T
            p_X = torch.linalg.lstsq(A.reshape(-1, 3), rhs.reshape(-1, 1)).solution[:, 0]
            R_X = model.tool.matrix()[0 if g is None else g, :3, :3].to(T_end.dtype)
            if data.quat is not None:
                R_meas = quat_to_matrix(data.quat[rows])
                M = (R_F.transpose(-1, -2) @ B[:3, :3].T @ R_meas).sum(0)
                R_X = nearest_rotation(M)
            model.tool.reset_to(transform(R_X, p_X), g)


def initialise_with_priors(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    priors: FramePriors | None,
    which: str = "frames",
) -> None:
    """Registration of the ``which`` frames that respects known ones.

    The closed-form registration of both frames, then a given tool (fixed or seed)
    replaces the registered one and the base is registered again to it; a given base
    likewise, with the tool registered to it.

    Args:
        which: ``"frames"``, ``"base"`` or ``"tool"``: the frames to be fitted.
    """
    initialise_frames(model, data, cond, which)
    if priors is None:
        return
    with torch.no_grad():
        if priors.base is not None:
            for g in range(model.base.sets):
                model.base.reset_to(priors.base.matrix(model.base.matrix()[g].detach()), g)
        if priors.tool is not None:
            for g in range(model.tool.sets):
                model.tool.reset_to(priors.tool.matrix(model.tool.matrix()[g].detach()), g)
    if priors.tool is not None and priors.base is None and which in ("frames", "base"):
        _register_base_to_tool(model, data, cond)
    elif priors.base is not None and priors.tool is None and which in ("frames", "tool"):
        _register_tool_to_base(model, data, cond)

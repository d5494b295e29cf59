"""Evidence for a deflection cause (``tilt_compliance``, ``column_bending``): the tilt the
measured residual shows about each axis perpendicular to the joint, against the tilt
the static load predicts.

For every row, the partial residual ``r`` (root frame, the model without this cause;
see :mod:`hybrid_pk.report.evidence`) is explained by a small rotation ``t = (t1, t2)``
of everything the joint carries about ``e1, e2`` through the effect's pivot: the 2x2
least squares of ``[J_1 J_2] t = r`` with ``J_k = (R_i e_k) x (p_point - pivot)``. The
law predicts ``w_k = c_k M_k`` (``b_k q M_k`` for a column), ``M_k`` the gravity
moment about ``e_k``. Both components of every row are points of one plot, measured
tilt against predicted tilt: a slope-1 line if the deflection is there, a flat cloud
if it is not. Rows whose two lever arms barely move the point (the smaller singular
value of ``[J_1 J_2]`` under ``MIN_LEVER_FRACTION`` of its median) say nothing and
are left out.
"""

from __future__ import annotations

import numpy as np
import torch

from hybrid_pk.evaluation.plots import binned_median

__all__ = ["MIN_LEVER_FRACTION", "deflection_evidence"]

MIN_LEVER_FRACTION = 0.2


@torch.no_grad()
def _measured_and_predicted(cause, data, model, res, frames):
    """``(t_measured, t_predicted, lever)``: ``(N, 2)`` [rad] and ``(N,)`` [m]."""
    effect = model.effect(f"{cause.effect}:{cause.joint}")
    i = effect.joint_index
    cond = res.cond
    params = model.kinematic_params(cond)
    gravity = model.gravity_root(cond)
    q_true = model.joint_values(data.q, cond, params, gravity)
    wrench = model.static_wrenches(q_true, params, cond, gravity)
    w_pred, pivot = effect.rotation(wrench[:, i, :], q_true)  # joint frame
    basis = effect.basis.to(torch.float64)  # (2, 3)
    predicted = w_pred @ basis.T  # (N, 2)
    base = frames(res.model, cond)[0]
    R_b, t_b = base[..., :3, :3], base[..., :3, 3]
    p_model = data.position - res.r_meas  # measurement frame
    p_point = (R_b.transpose(-1, -2) @ (p_model - t_b)[..., None])[..., 0]  # root
    F = model.robot.link_frames(q_true, params)[:, i]  # joint frame i, root
    R_i = F[:, :3, :3]
    pivot_root = F[:, :3, 3] + (R_i @ pivot[..., None])[..., 0]
    axes = (R_i[:, None, :, :] @ basis[None, :, :, None])[..., 0]  # (N, 2, 3)
    arm = (p_point - pivot_root)[:, None, :].expand_as(axes)
    J = torch.linalg.cross(axes, arm, dim=-1).transpose(-1, -2)  # (N, 3, 2)
    measured = torch.linalg.lstsq(J, res.r_root[..., None]).solution[..., 0]
    lever = torch.linalg.svdvals(J)[:, -1]
    return measured, predicted, lever


def deflection_evidence(cause, label, title, data, model, res, frames) -> dict:
    """The fields of an ``Evidence`` for a deflection cause (see the module doc).

    Args:
        frames: ``(model, cond) -> (base, tool)`` transforms, as ``evidence`` has them.
    """
    measured, predicted, lever = _measured_and_predicted(cause, data, model, res, frames)
    keep = (lever > MIN_LEVER_FRACTION * lever.median()).numpy()
    rows = np.flatnonzero(keep)
    x = 1e3 * predicted.numpy()[rows].T.reshape(-1)  # [mrad], e1 of all rows, then e2
    y = 1e3 * measured.numpy()[rows].T.reshape(-1)
    w = np.tile(lever.numpy()[rows] ** 2, 2)
    slope = float((w * x * y).sum() / max(float((w * x * x).sum()), 1e-300))
    magnitude = float(model.effect(label).value.detach().norm())
    span = float(np.abs(x).max()) if x.size else 1.0
    curve_x = np.array([-span, span])
    mx, my = binned_median(x, y)
    joint = cause.joint
    per = " x extension" if model.effect(label).joints == "prismatic" else ""
    return {
        "label": label,
        "title": title,
        "x": x,
        "y": y,
        "weight": w,
        "rows": np.tile(rows, 2),
        "x_label": f"tilt of {joint} the gravity moment predicts, about e1, e2 [mrad]",
        "y_label": "tilt the residual shows, same axis [mrad]",
        "curve_x": curve_x,
        "curve_y": curve_x.copy(),
        "median_x": mx,
        "median_y": my,
        "value": magnitude,
        "points_value": slope * magnitude,
        "unit": cause.unit,
        "law": f"tilt = compliance{per} x moment, each axis: slope 1",
    }

"""The base frame's second path into the pose when gravity comes from a levelled tracker.

With ``Gravity.level_tracker()`` gravity is ``-z`` in the measurement frame, so in the
robot's root frame it is ``g_root = R_base^T g_meas``: turning the base frame turns
gravity, which changes the compliance sag and the deflections. The structured
Jacobian of :class:`~hybrid_pk.calibration.fit.Problem` holds the end pose fixed for
the frame columns; this module adds the rest to the base-rotation columns::

    dr/dw_base += (dr/dg_root) (dg_root/dw_base)

``dr/dg_root`` is pushed forward through the whole loaded model (compliance fixed
point, static wrenches, deflection) once per gravity component, every row at once
(each row's residual depends on its own gravity only). Without it the base-rotation
columns are off by ~1e-3 relative on a compliant robot (measured in
``tests/test_mounting_fit.py``); with it, by the fixed point's ~1e-6.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import so3_exp

__all__ = ["levelled_gravity_columns"]


def _loaded(model: ExtendedModel) -> bool:
    return any(e.stage in ("compliance", "deflection") for e in model.effects)


def levelled_gravity_columns(
    model: ExtendedModel,
    q: Tensor,
    cond: Conditions,
    B: Tensor,
    X: Tensor,
    residual_of_pose: Callable[[Tensor], Tensor],
) -> Tensor | None:
    """``(m, 3 G)`` extra derivative of the residuals w.r.t. ``base.rotvec``, or None
    when gravity does not depend on the base frame (or no effect reads it).

    Args:
        model: the model at its current values.
        q: ``(N, dof)`` commanded joints.
        cond: the rows' conditions (``group`` picks each row's base frame).
        B, X: base and tool transforms of every row (fixed).
        residual_of_pose: the problem's map from poses ``(N, 4, 4)`` to residuals.
    """
    if not model.gravity.levelled or not _loaded(model):
        return None
    dtype = model.robot.dtype
    g_meas = torch.tensor(model.gravity.vector, dtype=dtype)
    frame = model.base
    R0, w0 = frame.T0[:, :3, :3].detach(), frame.rotvec.detach()

    def g_root(R0_s: Tensor, w_s: Tensor) -> Tensor:
        return (R0_s @ so3_exp(w_s)).transpose(-1, -2) @ g_meas

    dg_dw = torch.func.vmap(torch.func.jacfwd(g_root, argnums=1))(R0, w0)  # (G, 3, 3)
    with torch.no_grad():
        g_rows = model.gravity_root(cond)
        params = model.kinematic_params(cond)

    def residual_of_gravity(dg: Tensor) -> Tensor:
        g = g_rows + dg  # the same change for every row: rows do not interact
        q_true = model.joint_values(q, cond, params, g)
        bent = model.deflected_params(q_true, params, cond, g)
        return residual_of_pose(B @ model.robot.fk(q_true, params=bent) @ X)

    zero = torch.zeros(3, dtype=dtype)
    D = torch.stack(
        [
            torch.func.jvp(residual_of_gravity, (zero,), (torch.eye(3, dtype=dtype)[k],))[1]
            for k in range(3)
        ],
        -1,
    ).detach()  # (m, 3): each row's residuals per unit change of its own gravity
    n = q.shape[0]
    sets = frame.sets
    group = cond.group if (cond.group is not None and sets > 1) else None
    row = torch.arange(D.shape[0]) % (3 * n) // 3  # the data row of each residual
    grp = torch.zeros(n, dtype=torch.long) if group is None else group
    per_entry = dg_dw[grp[row]]  # (m, 3, 3)
    cols = (D[:, :, None] * per_entry).sum(1)  # (m, 3): d r / d w of the row's own set
    out = torch.zeros(D.shape[0], 3 * sets, dtype=dtype)
    for s in range(sets):
        mine = (grp[row] == s).to(dtype)[:, None]
        out[:, 3 * s : 3 * s + 3] = cols * mine
    return out

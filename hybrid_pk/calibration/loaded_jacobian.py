"""The static load in the structured Jacobian: deflection and a levelled tracker's gravity.

:class:`~hybrid_pk.calibration.problem.Problem` linearises the model about
:func:`loaded_state`: the true joint values ``q*`` (compliance fixed point), the
static wrenches at ``q*`` and the parameters the deflection effects bend.

- :class:`LoadedPose`: the end pose through geometric *and* deflection effects at fixed
  ``q*`` and fixed wrenches, so one forward-mode pass gives both kinds of columns.
  Deflection columns are exact (neither ``q*`` nor the wrenches depend on a deflection
  value); the wrenches' own dependence on joint and geometric parameters (a
  deflection of ~1e-3 rad changing by ~1e-3 relative) is dropped with the compliance
  coupling of the geometry (measured in ``tests/test_mounting_fit.py``: <= 1.3e-3 of a
  column).
- :func:`levelled_gravity_columns`: with ``Gravity.level_tracker()`` gravity is ``-z``
  in the measurement frame, so in the robot's root frame it is ``R_base^T g_meas``:
  turning the base frame turns gravity, which changes the sag and the deflections.
  The frame columns hold the end pose fixed; this adds the rest to the base-rotation
  columns, ``dr/dw_base += (dr/dg_root)(dg_root/dw_base)``, pushed forward through the
  whole loaded model once per gravity component, every row at once (each row's
  residual depends on its own gravity only). Without it those columns are off by
  ~1e-3 relative on a compliant robot; with it, by the fixed point's ~1e-6.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import so3_exp

__all__ = ["LoadedPose", "levelled_gravity_columns", "loaded_state"]


def _loaded(model: ExtendedModel) -> bool:
    return any(e.stage in ("compliance", "deflection") for e in model.effects)


class LoadedPose(torch.nn.Module):
    """End pose with geometric and deflection effects at given true joint values, the
    deflection's static wrenches held fixed (``functional_call`` drives the values)."""

    def __init__(self, model: ExtendedModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, q_true: Tensor, cond: Conditions, wrenches: Tensor | None) -> Tensor:
        params = self.model.kinematic_params(cond)
        params = self.model.deflected_params(q_true, params, cond, wrenches=wrenches)
        return self.model.robot.fk(q_true, params=params)


@torch.no_grad()
def loaded_state(model: ExtendedModel, q: Tensor, cond: Conditions):
    """Everything the structured Jacobian linearises about, at the current values:
    ``(params, gravity, q_star, wrenches, params_bent)``.

    ``gravity`` is the root-frame vector (per row with a levelled tracker and several
    base frames); ``wrenches`` the joint-frame static wrenches at ``q_star`` (None
    without deflection effects); ``params_bent`` the parameters the pose uses.
    """
    params = model.kinematic_params(cond)
    gravity = model.gravity_root(cond)
    q_star = model.joint_values(q, cond, params, gravity)
    wrenches = None
    if any(e.stage == "deflection" for e in model.effects):
        wrenches = model.static_wrenches(q_star, params, cond, gravity)
    bent = model.deflected_params(q_star, params, cond, gravity, wrenches)
    return params, gravity, q_star, wrenches, bent


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

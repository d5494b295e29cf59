"""The static load in the structured Jacobian: deflection and a levelled tracker's gravity.

:class:`~hybrid_pk.calibration.structured_jacobian.StructuredJacobian` linearises the
model about :func:`loaded_state`: the true joint values ``q*`` (compliance fixed
point), the static wrenches at ``q*`` and the chain the deflection effects bend.

- :func:`deflection_twists`: a deflection value ``c_k`` turns everything after its
  joint about the effect's pivot, at the angular rate ``d w / d c_k`` (the wrench held
  fixed), so its twist is closed form: ``omega = R_i J_l(w) dw/dc_k`` in the root frame
  (``R_i`` the bent joint frame, ``J_l`` the left Jacobian of ``exp`` at the current
  deflection), ``v = omega x (p - pivot)``. Exact: neither ``q*`` nor the wrenches
  depend on a deflection value. What is dropped: the wrenches' dependence on the joint
  and geometric parameters (a deflection of ~1e-3 rad changing by ~1e-3 relative), and
  in the geometric columns the turn of a perturbed origin by the deflection after it
  (~|w| relative); both vanish at zero deflection, where the diagnosis scores its
  candidates (measured in ``tests/test_mounting_fit.py``: <= 1.3e-3 of a column).
- :func:`levelled_gravity_twists`: with ``Gravity.level_tracker()`` gravity is ``-z``
  in the measurement frame, so in the robot's root frame it is ``R_base^T g_meas``:
  turning the base frame turns gravity, which changes the sag and the deflections.
  The frame twists hold the end pose fixed; this adds the rest to the base-rotation
  twists, ``dT/dw_base += (dT/dg_root)(dg_root/dw_base)``, pushed forward through the
  whole loaded model once per gravity component, every row at once (each row's pose
  depends on its own gravity only). Without it those columns are off by ~1e-3 relative
  on a compliant robot; with it, by the fixed point's ~1e-6.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import so3_exp, so3_left_jacobian

__all__ = ["deflection_twists", "levelled_gravity_twists", "loaded_state"]


@torch.no_grad()
def loaded_state(model: ExtendedModel, q: Tensor, cond: Conditions):
    """Everything the structured Jacobian linearises about, at the current values:
    ``(params, gravity, q_star, wrenches, params_bent, frames)``.

    ``gravity`` is the root-frame vector (per row with a levelled tracker and several
    base frames); ``wrenches`` the joint-frame static wrenches at ``q_star`` (None
    without deflection effects); ``params_bent`` the parameters the pose uses;
    ``frames`` the link frames at ``q_star`` and ``params_bent`` where the wrenches
    needed them and nothing bends (None otherwise: not computed here).
    """
    params = model.kinematic_params(cond)
    gravity = model.gravity_root(cond)
    q_star = model.joint_values(q, cond, params, gravity)
    wrenches = frames = None
    if any(e.stage == "deflection" for e in model.effects):
        frames = model.robot.link_frames(q_star, params)
        wrenches = model.static_wrenches(q_star, params, cond, gravity, frames=frames)
    bent = model.deflected_params(q_star, params, cond, gravity, wrenches)
    return params, gravity, q_star, wrenches, bent, frames if bent is params else None


@torch.no_grad()
def deflection_twists(
    model: ExtendedModel,
    blocks,
    q_star: Tensor,
    wrenches: Tensor,
    bent,
    point: Tensor,
    R_B: Tensor,
    frames: Tensor | None = None,
) -> dict[str, Tensor]:
    """Twists ``(n, 6, 2)`` of every deflection block, by module path.

    Args:
        blocks: the deflection parameter blocks (``effects.I.value``, scale each).
        q_star: ``(n, dof)`` true joint values; ``wrenches`` their joint-frame wrenches.
        bent: the deflected parameters of the pose (per row).
        point: ``(n, 3)`` measured point in the root frame [m].
        R_B: ``(n, 3, 3)`` or ``(3, 3)`` root -> measurement frame rotation.
        frames: ``Robot.link_frames`` at ``q_star`` and ``bent`` (computed if None).
    """
    effects = dict(model.named_modules())
    frames = model.robot.link_frames(q_star, params=bent) if frames is None else frames
    q_chain = model.robot.chain_q(q_star)
    out = {}
    for b in blocks:
        e = effects[b.name.removesuffix(".value")]
        i = e.joint_index
        w, pivot = e.rotation(wrenches[..., i, :], q_chain)  # joint frame
        # dw/dc_k: w is linear in the value, so one unit value per component
        unit = torch.stack(
            [e.rotation_per_unit(wrenches[..., i, :], q_chain, k) for k in range(2)], -1
        )  # (n, 3, 2)
        F = frames[:, i]
        turn = F[:, :3, :3]  # J_l(0) = I exactly: a candidate at zero skips the product
        turn = turn @ so3_left_jacobian(w) if bool(w.any()) else turn
        omega = turn @ unit  # (n, 3, 2), root frame
        pivot_root = F[:, :3, 3] + (F[:, :3, :3] @ pivot[..., None])[..., 0]
        lever = (point - pivot_root)[:, :, None].expand_as(omega)
        v = torch.linalg.cross(omega, lever, dim=1)
        out[b.name] = torch.cat([R_B @ v, R_B @ omega], 1) * b.scale
    return out


def levelled_gravity_twists(
    model: ExtendedModel,
    q: Tensor,
    cond: Conditions,
    B: Tensor,
    X: Tensor,
    T: Tensor,
) -> Tensor | None:
    """``(n, 6, 3 G)`` extra twists of ``base.rotvec`` (per unit rotation-vector
    component), or None when gravity does not depend on the base frame (or no effect
    reads it).

    Args:
        q: ``(n, dof)`` commanded joints; ``cond`` their conditions (``group``).
        B, X: base and tool transforms of every row (fixed); ``T`` the poses.
    """
    if not model.gravity.levelled or not model.loaded_effects():
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

    def pose_of_gravity(dg: Tensor) -> Tensor:
        g = g_rows + dg  # the same change for every row: rows do not interact
        q_true = model.joint_values(q, cond, params, g)
        bent = model.deflected_params(q_true, params, cond, g)
        return B @ model.robot.fk(q_true, params=bent) @ X

    zero = torch.zeros(3, dtype=dtype)
    eye = torch.eye(3, dtype=dtype)
    dT = torch.stack(
        [torch.func.jvp(pose_of_gravity, (zero,), (eye[k],))[1] for k in range(3)], -1
    ).detach()  # (n, 4, 4, 3): each row's pose per unit change of its own gravity
    dR = dT[:, :3, :3, :].permute(0, 3, 1, 2) @ T[:, None, :3, :3].transpose(-1, -2)
    w = 0.5 * torch.stack(
        [
            dR[..., 2, 1] - dR[..., 1, 2],
            dR[..., 0, 2] - dR[..., 2, 0],
            dR[..., 1, 0] - dR[..., 0, 1],
        ],
        -1,
    )  # (n, 3 gravity components, 3)
    per_g = torch.cat([dT[:, :3, 3, :], w.transpose(1, 2)], 1)  # (n, 6, 3)
    n, sets = q.shape[0], frame.sets
    grp = cond.group if (cond.group is not None and sets > 1) else None
    grp = torch.zeros(n, dtype=torch.long) if grp is None else grp
    tw = per_g @ dg_dw[grp]  # (n, 6, 3): per rotation-vector component of the row's set
    onehot = torch.nn.functional.one_hot(grp, sets).to(dtype)  # (n, G)
    return (tw[:, :, None, :] * onehot[:, None, :, None]).reshape(n, 6, 3 * sets)

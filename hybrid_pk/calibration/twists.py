"""Pose derivatives as twists: how each parameter moves the measured point and frame.

For every row and parameter direction the derivative of the predicted pose
``T = B · E · X`` (base, end link, tool) is a twist ``(v, w)``: the velocity of the
measured point and the angular velocity of the measured frame, both in the
measurement frame, per unit of the parameter. Twists of frames, of geometric effects
(perturbed chain origins) and of joint values (the geometric Jacobian) are computed
in closed form from one pass of link frames; :func:`residual_columns` turns them
into Jacobian columns of the noise-normalised residuals.

Shapes: ``n`` rows, ``k`` parameter directions, twists ``(n, 6, k)`` with rows
``[v (3) [m]; w (3) [rad]]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.effects import RigidFrame
from hybrid_pk.geometry import so3_exp, so3_left_jacobian

__all__ = [
    "frame_rotation_derivatives",
    "frame_twists",
    "geometry_twists",
    "origin_twist_maps",
    "point_joint_twists",
    "residual_columns",
    "vee",
]


def vee(S: Tensor) -> Tensor:
    """``(*B, 3, 3)`` skew part -> ``(*B, 3)`` vector (``vee([w]) = w``)."""
    return 0.5 * torch.stack(
        [S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]],
        -1,
    )


def frame_rotation_derivatives(frame: RigidFrame) -> tuple[Tensor, Tensor]:
    """Rotations ``R (G, 3, 3)`` of a frame's sets and the spatial angular velocity
    ``w (G, 3, 3)`` (``w[g, :, c]``) of each rotation-vector component ``c``:
    ``dR / d rotvec_c = [w_c] R``, ``R = R0 exp(rotvec)``, so ``w = R0 J_l(rotvec)``."""
    R0 = frame.T0[:, :3, :3]
    rv = frame.rotvec.detach()
    return R0 @ so3_exp(rv), R0 @ so3_left_jacobian(rv)


def frame_twists(
    base: RigidFrame, tool: RigidFrame, group: Tensor | None, T_BE: Tensor, T: Tensor
) -> dict[str, Tensor]:
    """Twists ``(n, 6, 3 G)`` of the frame parameter blocks, by module path.

    ``T = B · E · X``: a base parameter moves the whole pose (its rotation turns the
    point about the base origin), a tool translation moves the point along the end
    frame ``T_BE = B · E``, a tool rotation turns only the measured frame.

    Args:
        group: ``(n,)`` frame set of each row (None: set 0 of ``G = 1``).
        T_BE, T: ``(n, 4, 4)`` ``B · E`` and ``B · E · X`` in the measurement frame.
    """
    n, sets = T.shape[0], base.sets
    g = torch.zeros(n, dtype=torch.long, device=T.device) if group is None else group
    _, w_b = frame_rotation_derivatives(base)
    _, w_x = frame_rotation_derivatives(tool)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand(n, 3, 3)
    zero = torch.zeros_like(eye)
    p, t_b = T[:, :3, 3], base.T0[:, :3, 3] + base.dp.detach()
    w_base = w_b[g]  # (n, 3, 3): columns per rotation-vector component
    v_base = torch.linalg.cross(w_base, (p - t_b[g])[:, :, None].expand_as(w_base), dim=1)
    R_BE = T_BE[:, :3, :3]
    own = {
        "base.dp": torch.cat([eye, zero], 1),
        "base.rotvec": torch.cat([v_base, w_base], 1),
        "tool.dp": torch.cat([R_BE, zero], 1),
        "tool.rotvec": torch.cat([zero, R_BE @ w_x[g]], 1),
    }
    if sets == 1:
        return own
    rows, out = torch.arange(n, device=T.device), {}
    for name, tw in own.items():  # each row moves with its own set's parameters only
        spread = tw.new_zeros(n, 6, sets, 3)
        spread[rows, :, g, :] = tw
        out[name] = spread.reshape(n, 6, 3 * sets)
    return out


def point_joint_twists(jac_end: Tensor, lever: Tensor, R_B: Tensor) -> Tensor:
    """``(n, 6, dof)`` twists of the measured point per joint, in the measurement frame.

    Args:
        jac_end: ``(n, 6, dof)`` geometric Jacobian of the end-link origin (root frame).
        lever: ``(n, 3)`` end-link origin -> measured point (root frame) [m].
        R_B: ``(n, 3, 3)`` or ``(3, 3)`` root -> measurement frame rotation.
    """
    v_end, w = jac_end[:, :3, :], jac_end[:, 3:, :]
    v_point = v_end + torch.linalg.cross(w, lever[:, :, None].expand_as(w), dim=1)
    return torch.cat([R_B @ v_point, R_B @ w], 1)


def origin_twist_maps(frames: Tensor, origin_xyz: Tensor, point: Tensor, R_B: Tensor) -> Tensor:
    """``(n, 6, 6 (dof + 1))``: twist of the point (measurement frame) per unit move of
    each chain origin, ``[translation (3); rotation (3)]`` in the origin's parent frame.

    Origin ``i`` sits in the frame of joint ``i`` (the root for ``i = 0``); moving it
    moves everything after it: ``v = R_P d + w x (p - o)``, ``w = R_P dw``.

    Args:
        frames: ``(n, dof + 1, 4, 4)`` ``Robot.link_frames`` at the true joint values.
        origin_xyz: ``(*P, dof + 1, 3)`` current origin translations (``*P`` empty or
            ``(n,)`` for per-row parameters).
        point: ``(n, 3)`` measured point in the root frame [m].
        R_B: ``(n, 3, 3)`` or ``(3, 3)`` root -> measurement frame rotation.
    """
    n, n_orig = frames.shape[0], origin_xyz.shape[-2]
    # Laid out (row, origin, column) so that the rotations act by one product per row
    # (not one 3x3 product per origin) and the blocks are written into place.
    R_P = frames.new_empty(n, 3, n_orig, 3)  # parent frame of origin i
    R_P[:, :, 0] = torch.eye(3, dtype=frames.dtype, device=frames.device)
    R_P[:, :, 1:] = frames[:, : n_orig - 1, :3, :3].transpose(1, 2)
    t_P = frames.new_zeros(n, 3, n_orig)
    t_P[:, :, 1:] = frames[:, : n_orig - 1, :3, 3].transpose(1, 2)
    o = t_P + (R_P * origin_xyz.expand(n, n_orig, 3)[:, None]).sum(-1)  # (n, 3, n_orig)
    R_MP = torch.matmul(R_B, R_P.reshape(n, 3, -1)).reshape(n, 3, n_orig, 3)
    lever = torch.matmul(R_B, point[:, :, None] - o)[..., None]  # measurement frame
    M = frames.new_empty(n, 6, n_orig, 6)
    M[:, :3, :, :3] = R_MP
    M[:, 3:, :, 3:] = R_MP
    M[:, 3:, :, :3] = 0.0
    x, y, z = R_MP.unbind(1)  # each column's components
    lx, ly, lz = lever.unbind(1)
    M[:, 0, :, 3:] = y * lz - z * ly  # -[lever] R_MP: each column crossed with the lever
    M[:, 1, :, 3:] = z * lx - x * lz
    M[:, 2, :, 3:] = x * ly - y * lx
    return M.reshape(n, 6, 6 * n_orig)


def geometry_twists(maps: Tensor, origin_rot: Tensor, d_xyz: Tensor, d_rot: Tensor) -> Tensor:
    """``(n, 6, k)`` twists of the point for ``k`` directions of the chain origins, in
    the measurement frame.

    Args:
        maps: ``(n, 6, 6 (dof + 1))`` from :func:`origin_twist_maps`.
        origin_rot: ``(*P, dof + 1, 3, 3)`` current origin rotations.
        d_xyz, d_rot: ``(k, *P, dof + 1, 3)``, ``(k, *P, dof + 1, 3, 3)`` derivatives
            of the origins along each direction.
    """
    shared_rot = origin_rot if origin_rot.dim() == 3 else origin_rot[0]
    if d_xyz.dim() == 4 and bool((origin_rot == shared_rot).all()):
        # Per-row parameters (a thermal expansion) leave most directions equal in every
        # row (at a zero expansion coefficient exactly): those take the shared path.
        flat_xyz, flat_rot = d_xyz.flatten(2), d_rot.flatten(2)
        same = (flat_xyz == flat_xyz[:, :1]).all(-1).all(-1)
        same &= (flat_rot == flat_rot[:, :1]).all(-1).all(-1)
        if bool(same.any()):
            out = maps.new_empty(maps.shape[0], 6, d_xyz.shape[0])
            out[..., same] = _origin_twists(maps, shared_rot, d_xyz[same, 0], d_rot[same, 0])
            rows = ~same
            if bool(rows.any()):
                out[..., rows] = _origin_twists(maps, origin_rot, d_xyz[rows], d_rot[rows])
            return out
    return _origin_twists(maps, origin_rot, d_xyz, d_rot)


def _origin_twists(maps: Tensor, origin_rot: Tensor, d_xyz: Tensor, d_rot: Tensor) -> Tensor:
    """:func:`geometry_twists` without the split into shared and per-row directions."""
    k = d_xyz.shape[0]
    if d_xyz.dim() == 4 and not bool(d_rot.any()):  # per row, no origin turns (an expansion)
        w_local = torch.zeros_like(d_xyz)  # what the product gives, without n (dof + 1) of them
    else:
        w_local = vee(d_rot @ origin_rot.transpose(-1, -2))  # parent-frame angular rates
    D = torch.cat([d_xyz, w_local], -1)  # (k, *P, n_orig, 6)
    if D.dim() == 3:  # shared parameters: one matrix for every row
        return maps @ D.reshape(k, -1).T
    return maps @ D.reshape(k, D.shape[1], -1).permute(1, 2, 0)


def residual_columns(
    twists: Tensor,
    E_rot: Tensor | None,
    sigma_pos_mm: float,
    sigma_rot_rad: float,
    weights: Tensor | None = None,
    out: list | None = None,
) -> tuple[Tensor, Tensor | None]:
    """Jacobian columns of the residuals from twists ``(n, 6, k)``.

    Position residuals ``(p_meas - p) [mm] / sigma_pos`` change by ``-v``; rotation
    residuals ``vee(E - E^T) / 2 / sigma_rot`` (``E = R_meas R^T``, ``E_rot``) by
    ``-(tr(E) I - E^T) w / 2``. Returns ``(n, 3, k)`` position and rotation columns
    (None without orientation data), each scaled by the row ``weights``; written into
    ``out`` (``[pos, rot]``, views of a chunk's Jacobian) when given.
    """
    pos_out, rot_out = out if out is not None else (None, None)
    pos = torch.mul(twists[:, :3, :], -1000.0 / sigma_pos_mm, out=pos_out)
    rot = None
    if E_rot is not None:
        tr = E_rot.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
        A = tr * torch.eye(3, dtype=E_rot.dtype, device=E_rot.device) - E_rot.transpose(-1, -2)
        rot = torch.mul(A @ twists[:, 3:, :], -0.5 / sigma_rot_rad, out=rot_out)
    if weights is not None:
        pos.mul_(weights[:, None, None])
        if rot is not None:
            rot.mul_(weights[:, None, None])
    return pos, rot

"""Batched SO(3)/SE(3) helpers on plain tensors.

Shapes: any leading batch shape ``*B``; rotation vectors ``(*B, 3)`` [rad], rotation
matrices ``(*B, 3, 3)``, homogeneous transforms ``(*B, 4, 4)`` [m], quaternions
``(*B, 4)`` ordered ``(w, x, y, z)``. Every function is differentiable and finite at
the identity and at rotations of pi (the two places naive formulas divide by zero).
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from hybrid_pk.geometry.shapes import broadcast_shapes
from hybrid_pk.geometry.tangents import carried

__all__ = [
    "axis_near_pi",
    "matrix_to_quat",
    "matrix_to_rpy",
    "nearest_rotation",
    "quat_to_matrix",
    "rotation_angle",
    "rpy_to_matrix",
    "skew",
    "so3_exp",
    "so3_left_jacobian",
    "so3_log",
    "transform",
    "transform_inverse",
    "twist_swing",
    "vee_antisym",
]

# Below this angle [rad] Taylor series replace the closed forms.
_SMALL = 1e-4


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix: ``skew(a) @ b == a x b``. ``(*B, 3) -> (*B, 3, 3)``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)],
        dim=-2,
    )


def vee_antisym(R: Tensor) -> Tensor:
    """``vee(R - R^T)`` = ``2 sin(theta) * axis``."""
    return torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )


def so3_exp(w: Tensor) -> Tensor:
    """Rodrigues: rotation vector ``(*B, 3)`` [rad] -> rotation matrix ``(*B, 3, 3)``."""
    theta2 = (w * w).sum(-1, keepdim=True).unsqueeze(-1)  # (*B, 1, 1)
    small = theta2 < _SMALL**2
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    c = functools.partial(carried, like=theta2)  # constants in forward mode: see tangents
    a = torch.where(small, 1 - theta2 / c(6.0), torch.sin(theta) / theta)
    # (1 - cos t) / t^2 written as 2 sin^2(t/2) / t^2: no cancellation for small t in float32.
    s = torch.sin(theta / c(2.0))
    b = torch.where(small, 0.5 - theta2 / c(24.0), c(2.0) * s**2 / theta2_safe)
    K = skew(w)
    aK = a * K
    eye = carried(torch.eye(3, dtype=w.dtype, device=w.device), aK).expand_as(K)
    return eye + aK + b * (K @ K)


def so3_left_jacobian(w: Tensor) -> Tensor:
    """``(*B, 3, 3)`` left Jacobian of :func:`so3_exp` at ``w (*B, 3)`` [rad]:
    ``d exp(w) = [J_l(w) dw] exp(w)``."""
    theta2 = (w * w).sum(-1)[..., None, None]
    small = theta2 < 1e-8
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    a = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(t)) / t2)
    b = torch.where(small, 1.0 / 6 - theta2 / 120, (t - torch.sin(t)) / (t2 * t))
    K = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def rotation_angle(R: Tensor) -> Tensor:
    """Angle [rad] in ``[0, pi]`` of rotation matrices ``(*B, 3, 3) -> (*B,)``.

    Uses ``atan2(|sin|, cos)``, accurate at every angle (``acos`` of the trace loses
    half the digits near 0 and pi).
    """
    s = vee_antisym(R).norm(dim=-1) / 2
    c = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.atan2(s, c)


def nearest_rotation(M: Tensor) -> Tensor:
    """Rotation nearest to ``M`` in the Frobenius norm, ``(*B, 3, 3) -> (*B, 3, 3)``.

    The orthogonal polar factor of ``M = U S V^T`` with the sign of its last singular
    direction chosen so that ``det = +1``: ``U diag(1, 1, det(U V^T)) V^T``. Kabsch,
    chordal means of rotations and the re-orthonormalisation of a noisy rotation are
    this projection of a sum of (outer products of) rotations.
    """
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    one = torch.ones_like(d)
    return (U * torch.stack([one, one, d], -1)[..., None, :]) @ Vh


def so3_log(R: Tensor) -> Tensor:
    """Rotation matrix ``(*B, 3, 3)`` -> rotation vector ``(*B, 3)`` [rad], angle in [0, pi]."""
    vee = vee_antisym(R)  # 2 sin(theta) axis
    s = vee.norm(dim=-1, keepdim=True) / 2
    c = ((R.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True)) - 1) / 2
    theta = torch.atan2(s, c)

    # Regular branch: w = theta / (2 sin theta) * vee, with the Taylor form near 0.
    s_safe = torch.where(s < _SMALL, torch.ones_like(s), s)
    scale = torch.where(s < _SMALL, 0.5 + theta * theta / 12, theta / (2 * s_safe))
    w_regular = scale * vee

    w_pi = axis_near_pi(R, vee, c) * theta
    near_pi = c < -0.9  # theta > ~154 deg: regular branch loses accuracy there
    return torch.where(near_pi, w_pi, w_regular)


def axis_near_pi(R: Tensor, vee: Tensor, cos: Tensor) -> Tensor:
    """Unit axes ``(*B, 3)`` of rotations ``R (*B, 3, 3)`` by an angle near pi, with
    ``vee = vee_antisym(R)`` ``(*B, 3)`` (2 sin(angle) axis) and ``cos (*B, 1)`` the
    angle's cosine. Near pi ``vee`` has lost the axis' digits but not its sign; the axis
    comes from the symmetric part, ``(R + R^T) / 2 - cos I = (1 - cos) a a^T``: the
    column of its largest diagonal entry, normalised, signed like ``vee``."""
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    M = (R + R.transpose(-1, -2)) / 2 - cos.unsqueeze(-1) * eye
    k = M.diagonal(dim1=-2, dim2=-1).argmax(-1, keepdim=True)  # (*B, 1)
    col = torch.take_along_dim(M, k.unsqueeze(-1).expand(*k.shape[:-1], 3, 1), dim=-1)[..., 0]
    axis = col / col.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(R.dtype).tiny)
    return torch.where((axis * vee).sum(-1, keepdim=True) < 0, -axis, axis)


def rpy_to_matrix(rpy: Tensor) -> Tensor:
    """URDF fixed-axis roll-pitch-yaw ``(*B, 3)`` [rad] -> ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = rpy.unbind(-1)
    cr, sr, cp, sp, cy, sy = r.cos(), r.sin(), p.cos(), p.sin(), y.cos(), y.sin()
    return torch.stack(
        [
            torch.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            torch.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            torch.stack([-sp, cp * sr, cp * cr], -1),
        ],
        dim=-2,
    )


def matrix_to_rpy(R: Tensor) -> Tensor:
    """Inverse of :func:`rpy_to_matrix` (pitch in [-pi/2, pi/2]); ``(*B, 3, 3) -> (*B, 3)``.

    At gimbal lock (pitch = +-pi/2) only roll -/+ yaw is defined; the angles returned
    there still reproduce ``R`` (their gradient there is not meaningful).
    """
    yaw = torch.atan2(R[..., 1, 0], R[..., 0, 0])
    cy, sy = yaw.cos(), yaw.sin()
    # Undo the yaw: N = Rz(-yaw) R = Ry(pitch) Rx(roll). Its rows have unit norm whatever
    # the pitch, so roll stays well conditioned near gimbal lock (R[2, 1], R[2, 2] -> 0).
    n00 = cy * R[..., 0, 0] + sy * R[..., 1, 0]  # = cos(pitch) >= 0
    n11 = cy * R[..., 1, 1] - sy * R[..., 0, 1]  # = cos(roll)
    n12 = cy * R[..., 1, 2] - sy * R[..., 0, 2]  # = -sin(roll)
    pitch = torch.atan2(-R[..., 2, 0], n00)
    roll = torch.atan2(-n12, n11)
    return torch.stack([roll, pitch, yaw], -1)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternion ``(*B, 4)`` as ``(w, x, y, z)`` -> rotation matrix ``(*B, 3, 3)``.

    The quaternion is normalised first, so ``q`` and ``-q`` give the same matrix.
    """
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        dim=-2,
    )


def matrix_to_quat(R: Tensor) -> Tensor:
    """Rotation matrix ``(*B, 3, 3)`` -> unit quaternion ``(w, x, y, z)`` with ``w >= 0``."""
    R00, R01, R02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    R10, R11, R12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    R20, R21, R22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # 4 * (w, x, y, z) * q_k for k = w, x, y, z: four candidate (unnormalised) quaternions;
    # use per element the one with the largest |q_k|, the best conditioned.
    tw, tx, ty, tz = (
        1 + R00 + R11 + R22,
        1 + R00 - R11 - R22,
        1 - R00 + R11 - R22,
        1 - R00 - R11 + R22,
    )
    dx, dy, dz = R21 - R12, R02 - R20, R10 - R01
    sxy, sxz, syz = R01 + R10, R02 + R20, R12 + R21
    cands = torch.stack(
        [
            torch.stack([tw, dx, dy, dz], -1),
            torch.stack([dx, tx, sxy, sxz], -1),
            torch.stack([dy, sxy, ty, syz], -1),
            torch.stack([dz, sxz, syz, tz], -1),
        ],
        dim=-2,
    )  # (*B, 4 candidates, 4)
    diag = torch.stack([tw, tx, ty, tz], -1)
    best = diag.argmax(-1, keepdim=True)
    q = torch.take_along_dim(cands, best.unsqueeze(-1).expand(*best.shape[:-1], 1, 4), dim=-2)
    q = q[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def twist_swing(R: Tensor, axis: Tensor) -> tuple[Tensor, Tensor]:
    """Angles [rad] of the swing-twist decomposition ``R = swing @ twist`` about the unit
    ``axis (3,)``: ``twist`` turns about the axis (in (-pi, pi]), ``swing`` about an
    axis perpendicular to it (in [0, pi]). From the quaternion ``(w, v)``:
    ``twist = 2 atan2(v . axis, w)``, ``swing = 2 acos(|(w, (v . axis) axis)|)``."""
    q = matrix_to_quat(R)
    w, p = q[..., 0], (q[..., 1:] * axis.to(q.dtype)).sum(-1)
    twist = torch.remainder(2 * torch.atan2(p, w) + math.pi, 2 * math.pi) - math.pi
    swing = 2 * torch.acos(torch.hypot(w, p).clamp(max=1.0))
    return twist, swing


def transform(R: Tensor, p: Tensor) -> Tensor:
    """Homogeneous transform from rotation ``(*B, 3, 3)`` and translation ``(*B, 3)`` [m]."""
    batch = broadcast_shapes(R.shape[:-2], p.shape[:-1])
    top = torch.cat([R.expand(*batch, 3, 3), p.expand(*batch, 3).unsqueeze(-1)], -1)
    bottom = torch.zeros(*batch, 1, 4, dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def transform_inverse(T: Tensor) -> Tensor:
    """Inverse of rigid transforms ``(*B, 4, 4)`` without a general matrix inverse."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    return transform(Rt, -(Rt @ T[..., :3, 3:])[..., 0])

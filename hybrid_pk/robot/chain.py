"""Batched, differentiable product of a serial chain.

Why not pytorch-kinematics' ``forward_kinematics``: its analytic backward returns no
gradient for the chain's origins when ``q`` requires grad, and calibration needs
both at once. Here every step is plain autograd, so gradients reach ``q`` and every
kinematic parameter together.

Each joint's local transform is linear in two scalar functions of ``q``::

    origin · [Rot(a, q) 0; 0 1] = M0 + sin(q) · M1 + (1 - cos(q)) · M2      (revolute)
    origin · [I  q·a;  0 1]     = M0 + q · M1                                (prismatic)

with ``M1 = origin · [K 0; 0 0]``, ``M2 = origin · [K² 0; 0 0]`` (Rodrigues, ``K``
the cross matrix of the unit axis ``a``). The constant matrices (:func:`chain_terms`)
are computed once for all joints and evaluated in one of two layouts:

- batch first, the pose only (:func:`local_transforms`, :func:`product`): the
  ``dof`` local transforms multiply in a balanced tree (``log2(dof)`` batched
  matmuls), the fastest pose at every batch size (``Robot.fk``);
- batch last, pose and geometric Jacobian (:func:`batch_last_terms`,
  :func:`pose_jacobian_batch_last`): a rotation is a ``(3, 3, M)`` tensor, so one
  product is three fused multiply-adds over contiguous memory instead of a batched
  matmul of 3×3 blocks; several times faster than batch-first frames for the
  Jacobian from about a hundred configurations on (``Robot.jacobian``, the IK kernel).

Without derivatives the pose and the frames after each joint come from the z-aligned
chain of :mod:`hybrid_pk.robot.aligned` instead, from the same constants.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.geometry import skew, transform
from hybrid_pk.geometry.batch_last import compose, rotate

__all__ = [
    "BatchLastTerms",
    "ChainTerms",
    "KinematicParams",
    "batch_last_terms",
    "chain_terms",
    "local_batch_last",
    "local_transforms",
    "plain_inputs",
    "pose_jacobian_batch_last",
    "product",
]


class KinematicParams(NamedTuple):
    """Kinematic parameters of a chain with ``dof`` joints (values, not modules).

    Attributes:
        origin_xyz: ``(*P, dof + 1, 3)`` [m] translation of each origin (see ChainSpec).
        origin_rot: ``(*P, dof + 1, 3, 3)`` rotation of each origin.
        axis: ``(*P, dof, 3)`` joint axes in their joint frames (normalised on use).

    ``*P`` is usually empty; a leading batch shape gives per-sample parameters.
    """

    origin_xyz: Tensor
    origin_rot: Tensor
    axis: Tensor


class ChainTerms(NamedTuple):
    """Per-joint constant matrices ``M0, M1, M2``: ``(*P, dof, 4, 4)`` each, the tip
    ``(*P, 4, 4)`` (last segment -> end link) and the unit axes ``(*P, dof, 3)``.

    ``*P`` is empty for shared parameters and a batch shape broadcastable with ``q``'s
    for per-sample parameters. Here ``dof`` counts the chain's movable joints.
    """

    M0: Tensor
    M1: Tensor
    M2: Tensor
    tip: Tensor
    axis: Tensor


def chain_terms(params: KinematicParams, revolute: Tensor, fold_tip: bool = False) -> ChainTerms:
    """Precompute the joint matrices of :func:`local_transforms`.

    Args:
        params: kinematic parameters; each may carry leading batch dimensions
            (per-sample parameters, e.g. thermally scaled links).
        revolute: ``(dof,)`` bool, True for revolute/continuous joints.
        fold_tip: right-multiply the last joint's matrices by the tip transform, so
            the product of the local transforms is the end-link pose directly.
    """
    origins = transform(params.origin_rot, params.origin_xyz)  # (*P, dof+1, 4, 4)
    a = params.axis / params.axis.norm(dim=-1, keepdim=True)  # (*P, dof, 3)
    K = skew(a)
    dof = revolute.shape[0]
    rev = revolute.view(dof, 1, 1)
    zero3 = a.new_zeros(()).expand(*a.shape[:-1], 3, 1)
    top1 = torch.cat([torch.where(rev, K, 0.0), torch.where(rev, zero3, a[..., None])], -1)
    top2 = torch.cat([torch.where(rev, K @ K, 0.0), zero3], -1)
    pad = a.new_zeros(()).expand(*a.shape[:-1], 1, 4)
    G1 = torch.cat([top1, pad], -2)  # (*P, dof, 4, 4)
    G2 = torch.cat([top2, pad], -2)
    O = origins[..., :dof, :, :]
    M0, M1, M2, tip = O, O @ G1, O @ G2, origins[..., dof, :, :]
    if fold_tip:
        last = torch.stack([M0[..., -1, :, :], M1[..., -1, :, :], M2[..., -1, :, :]], -3)
        last = last @ tip[..., None, :, :]
        M0 = torch.cat([M0[..., :-1, :, :], last[..., 0:1, :, :]], -3)
        M1 = torch.cat([M1[..., :-1, :, :], last[..., 1:2, :, :]], -3)
        M2 = torch.cat([M2[..., :-1, :, :], last[..., 2:3, :, :]], -3)
        tip = torch.eye(4, dtype=tip.dtype, device=tip.device).expand_as(tip)
    return ChainTerms(M0, M1, M2, tip, a)


def local_transforms(q: Tensor, terms: ChainTerms, revolute: Tensor) -> Tensor:
    """Local transform of every joint: ``q (*B, dof) -> (*B, dof, 4, 4)``."""
    if bool(revolute.all()):  # the common case: skip the per-element selects
        f1, f2 = torch.sin(q), 1 - torch.cos(q)
    else:
        f1 = torch.where(revolute, torch.sin(q), q)
        f2 = torch.where(revolute, 1 - torch.cos(q), 0.0)
    out = torch.addcmul(terms.M0, f1[..., None, None], terms.M1)
    return out.addcmul_(f2[..., None, None], terms.M2)  # fused, no temporaries


def product(local: Tensor) -> Tensor:
    """Ordered product ``local[..., 0, :, :] @ local[..., 1, :, :] @ …``: ``(*B, n, 4, 4)``.

    Pairs neighbours level by level, so ``n`` factors cost about ``log2 n`` batched
    matmul calls instead of ``n - 1`` (what matters at small batch sizes).
    """
    n = local.shape[-3]
    if n == 1:
        return local[..., 0, :, :]
    if n % 2:
        return product(local[..., : n - 1, :, :]) @ local[..., n - 1, :, :]
    return product(local[..., 0::2, :, :] @ local[..., 1::2, :, :])


class BatchLastTerms(NamedTuple):
    """:class:`ChainTerms` of ``n`` joints in batch-last layout; ``m`` is 1 for shared
    parameters or the flat batch size of per-sample ones.

    Attributes:
        R: ``(3 terms, 3, 3, n, m)`` rotation blocks of ``M0, M1, M2``.
        t: ``(3, n, m)`` translation of ``M0``.
        d: ``(3, n, m)`` translation of ``M1`` (prismatic joints: per unit of ``q``).
        axis: ``(3, n, m)`` unit axes in the joint frames.
        R_tip, t_tip: ``(3, 3, m)``, ``(3, m)`` the tip transform.
    """

    R: Tensor
    t: Tensor
    d: Tensor
    axis: Tensor
    R_tip: Tensor
    t_tip: Tensor


def batch_last_terms(terms: ChainTerms, batch: tuple[int, ...] = ()) -> BatchLastTerms:
    """Rearrange ``terms`` (shared, or per sample with a batch shape broadcastable to
    ``batch``) into :class:`BatchLastTerms` (views; ``.contiguous()`` them to keep)."""
    n = terms.M0.shape[-3]
    per_sample = terms.M0.dim() > 3
    if per_sample:
        M0, M1, M2 = (t.expand(*batch, n, 4, 4) for t in terms[:3])
        tip, axis = terms.tip.expand(*batch, 4, 4), terms.axis.expand(*batch, n, 3)
        terms = ChainTerms(M0, M1, M2, tip, axis)
    m = -1 if per_sample else 1
    M = torch.stack([t.reshape(m, n, 4, 4) for t in terms[:3]])[..., :3, :]  # (3, m, n, 3, 4)
    L = M.permute(0, 3, 4, 2, 1)  # (3 terms, 3, 4, n, m)
    tip = terms.tip.reshape(m, 4, 4).permute(1, 2, 0)
    axis = terms.axis.reshape(m, n, 3).permute(2, 1, 0)
    return BatchLastTerms(L[:, :, :3], L[0, :, 3], L[1, :, 3], axis, tip[:3, :3], tip[:3, 3])


def local_batch_last(
    C: BatchLastTerms, qt: Tensor, revolute: Tensor, all_revolute: bool
) -> tuple[Tensor, Tensor]:
    """Local rotation ``(3, 3, n, M)`` and translation ``(3, n, M or 1)`` of every
    joint at chain joint values ``qt (n, M)`` (batch-last :func:`local_transforms`)."""
    if all_revolute:
        f1, f2 = torch.sin(qt), 1 - torch.cos(qt)
    else:
        rev = revolute[:, None]
        f1 = torch.where(rev, torch.sin(qt), qt)
        f2 = torch.where(rev, 1 - torch.cos(qt), 0.0)
    R_loc = torch.addcmul(C.R[0], f1, C.R[1])
    R_loc = torch.addcmul(R_loc, f2, C.R[2])
    return R_loc, C.t if all_revolute else torch.addcmul(C.t, f1, C.d)


def pose_jacobian_batch_last(
    C: BatchLastTerms, qt: Tensor, revolute: Tensor, all_revolute: bool | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Pose and geometric Jacobian at chain joint values ``qt (n, M)`` [rad or m].

    ``revolute (n,)`` marks the revolute joints; ``all_revolute`` is ``revolute.all()``
    when the caller knows it (the IK loop calls this thousands of times).

    Returns:
        ``R (3, 3, M)``, ``p (3, M)`` [m] of the end link and ``J (6, n, M)``, rows
        ``[v; omega]``: velocity of the end-link origin and angular velocity, in the
        frame of the chain's root (or of whatever ``C``'s first origin starts from).
    """
    if all_revolute is None:
        all_revolute = bool(revolute.all())
    R_loc, t_loc = local_batch_last(C, qt, revolute, all_revolute)
    R = R_loc[:, :, 0]
    p = t_loc[:, 0].expand(3, qt.shape[1])
    origins, axes = [p], [rotate(R, C.axis[:, 0])]
    for i in range(1, qt.shape[0]):
        p = p + rotate(R, t_loc[:, i])
        R = compose(R, R_loc[:, :, i])
        origins.append(p)
        axes.append(rotate(R, C.axis[:, i]))
    p_end = p + rotate(R, C.t_tip)
    R_end = compose(R, C.R_tip)
    z = torch.stack(axes, 1)  # (3, n, M)
    w = p_end[:, None, :] - torch.stack(origins, 1)
    v = torch.stack(  # z x w, written out (linalg.cross is slow on this layout)
        [z[1] * w[2] - z[2] * w[1], z[2] * w[0] - z[0] * w[2], z[0] * w[1] - z[1] * w[0]]
    )
    if not all_revolute:
        rev = revolute[None, :, None]
        v = torch.where(rev, v, z)
        z = torch.where(rev, z, 0.0)
    return R_end, p_end, torch.cat([v, z], 0)


def plain_inputs(*tensors: Tensor) -> bool:
    """True when no tensor carries derivatives: no autograd graph would be built, no
    forward-mode tangent, no torch.func wrapper (then the no-grad path may be taken)."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return False
    wrapped = torch._C._functorch.is_functorch_wrapped_tensor
    unpack = torch.autograd.forward_ad.unpack_dual
    return not any(wrapped(t) or unpack(t).tangent is not None for t in tensors)

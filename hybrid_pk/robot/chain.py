"""Batched, differentiable product of a serial chain.

Why not pytorch-kinematics' ``forward_kinematics``: its analytic backward returns no
gradient for the chain's origins when ``q`` requires grad, and calibration needs
both at once. Here every step is plain autograd, so gradients reach ``q`` and every
kinematic parameter together.

Each joint's local transform is linear in two scalar functions of ``q``::

    origin · [Rot(a, q) 0; 0 1] = M0 + sin(q) · M1 + (1 - cos(q)) · M2      (revolute)
    origin · [I  q·a;  0 1]     = M0 + q · M1                                (prismatic)

with ``M1 = origin · [K 0; 0 0]``, ``M2 = origin · [K² 0; 0 0]`` (Rodrigues, ``K``
the cross matrix of the unit axis ``a``). The constant matrices are computed once
per call for all joints, then the ``dof`` local transforms multiply in a balanced
tree (``log2(dof)`` batched matmuls).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.geometry import skew, transform

__all__ = ["ChainTerms", "KinematicParams", "chain_terms", "local_transforms", "product"]


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

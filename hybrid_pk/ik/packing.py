"""Packing of each target's kept solutions into padded ``(N, K, ...)`` tensors:
kept slots first, ordered by joint values, NaN padding (``IKResult``'s layout)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["concat_padded", "lexicographic_order", "pack"]

F64 = torch.float64


def lexicographic_order(q: Tensor, valid: Tensor) -> Tensor:
    """``(N, K)`` slot order per target: valid first, then by joint values."""
    order = torch.arange(q.shape[1], device=q.device).expand(q.shape[0], -1)
    for j in reversed(range(q.shape[-1])):
        key = torch.take_along_dim(q[..., j], order, 1)
        order = torch.take_along_dim(order, torch.argsort(key, dim=1, stable=True), 1)
    key = torch.take_along_dim((~valid).to(torch.int8), order, 1)
    return torch.take_along_dim(order, torch.argsort(key, dim=1, stable=True), 1)


def pack(
    q: Tensor, pos: Tensor, ori: Tensor, keep: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Sort each target's kept slots first and cut to the largest count.

    Args:
        q: ``(N, K, dof)``; pos, ori, keep: ``(N, K)``.

    Returns:
        ``q (N, K', dof)``, ``pos``, ``ori``, ``valid`` with NaN in unused slots.
    """
    k = int(keep.sum(-1).max()) if keep.numel() else 0
    # Only the first k slots of each target are returned: sort just those (the kept
    # slots first, in their order, then padding) instead of all K seeds.
    first = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)[:, :k]
    keep_k = torch.take_along_dim(keep, first, 1)
    sub = lexicographic_order(torch.take_along_dim(q, first[..., None], 1), keep_k)
    order = torch.take_along_dim(first, sub, 1)
    valid = torch.take_along_dim(keep, order, 1)
    q = torch.take_along_dim(q, order[..., None], 1)
    pos = torch.take_along_dim(pos, order, 1)
    ori = torch.take_along_dim(ori, order, 1)
    nan = torch.tensor(math.nan, dtype=q.dtype, device=q.device)
    return (
        torch.where(valid[..., None], q, nan),
        torch.where(valid, pos, nan),
        torch.where(valid, ori, nan),
        valid,
    )


def concat_padded(parts: list[tuple[Tensor, ...]], dof: int) -> tuple[Tensor, ...]:
    """Concatenate packed ``(q, pos, ori, valid)`` chunks along targets, NaN-padded."""
    if not parts:  # no targets at all
        empty = torch.zeros(0, 0, dtype=F64)
        return empty.reshape(0, 0, dof), empty, empty, empty.bool()
    k = max((p[0].shape[1] for p in parts), default=0)
    out_q, out_p, out_o, out_v = [], [], [], []
    for q, pos, ori, valid in parts:
        pad = k - q.shape[1]
        n = q.shape[0]
        out_q.append(torch.cat([q, q.new_full((n, pad, dof), math.nan)], 1))
        out_p.append(torch.cat([pos, pos.new_full((n, pad), math.nan)], 1))
        out_o.append(torch.cat([ori, ori.new_full((n, pad), math.nan)], 1))
        out_v.append(torch.cat([valid, valid.new_zeros(n, pad)], 1))
    return torch.cat(out_q), torch.cat(out_p), torch.cat(out_o), torch.cat(out_v)

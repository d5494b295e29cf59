"""Gross errors in a campaign: rows whose measured position is off by millimetres (a
tracker beam broken and re-acquired on another reflector, a mistyped row), for tests
and benchmarks of the robust fit and of the outlier listing."""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData

__all__ = ["displace_rows"]


def displace_rows(
    data: MeasuredData,
    fraction: float,
    gen: torch.Generator,
    lo_mm: float = 2.0,
    hi_mm: float = 10.0,
) -> tuple[MeasuredData, Tensor]:
    """``data`` with ``fraction`` of its rows (at least one) moved by ``lo_mm``-``hi_mm``
    mm (uniform) in random directions, and the indices of those rows."""
    k = max(1, round(fraction * data.n))
    bad = torch.randperm(data.n, generator=gen)[:k]
    d = torch.randn(k, 3, generator=gen, dtype=data.position.dtype)
    size = lo_mm + (hi_mm - lo_mm) * torch.rand(k, 1, generator=gen, dtype=data.position.dtype)
    position = data.position.clone()
    position[bad] += 1e-3 * size * d / d.norm(dim=1, keepdim=True)
    return dataclasses.replace(data, position=position), bad

"""The Gram matrices of the blocked hold-out (:mod:`.blocked`): built, and solved.

A cell's Gram of ``[J r]`` is ``M^T M`` over its rows, summed chunk by chunk. It is
symmetric, so only its lower triangle is accumulated, by BLAS's symmetric rank-k update
(``syrk``: half the multiplications of a product, ~2x faster on the UR10 series' cells)
and mirrored once at the end (:func:`filled`). The fits per block solve such a Gram
for its minimum-norm least-squares step (:func:`solve_gram`), from the eigenvalues of
the Gram equilibrated by its diagonal: a Gram of frames per file is singular (the
directions no row of a block sees), so a Cholesky factor does not serve.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["add_gram", "filled", "solve_gram"]


def add_gram(G: Tensor, rows: Tensor) -> None:
    """Add the lower triangle of ``rows^T rows`` (``rows (m, k)``) to that of ``G (k, k)``,
    in place; the upper triangle is left for :func:`filled`."""
    rows = rows.detach()
    if G.dtype == rows.dtype == torch.float64 and G.device.type == rows.device.type == "cpu":
        # scipy.linalg (~0.3 s to import) on first use: commands that import this
        # package without building a Gram (ik, export, evaluate) do not load it
        from scipy.linalg.blas import dsyrk

        # C-ordered arrays read as their Fortran-ordered transposes: the update of the
        # upper triangle of (rows^T)(rows^T)^T there is the lower one of G here
        c = G.numpy().T
        out = dsyrk(1.0, rows.contiguous().numpy().T, beta=1.0, c=c, trans=0, overwrite_c=1)
        if not np.shares_memory(out, c):  # BLAS worked on a copy: write it back
            c[...] = out
    else:
        G += torch.tril(rows.mT @ rows)


def filled(G: Tensor) -> Tensor:
    """The symmetric Gram(s) ``(..., k, k)`` whose lower triangle is ``G``'s."""
    lower = torch.tril(G)
    return lower + torch.tril(G, -1).mT


def solve_gram(H: Tensor, g: Tensor) -> Tensor:
    """Minimum-norm ``-H^+ g`` of a Gram ``H`` (or a batch), equilibrated by its
    diagonal first. Eigenvalues below ``eps`` times the size times the largest are
    round-off, as for an SVD least squares (``lstsq``'s ``gelsd``, which it replaced:
    the same solution, ~0.7x the time on the batches of a candidate's folds)."""
    d = H.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()
    if H.shape[-1] == 0:  # nothing to fit
        return torch.zeros_like(d)
    A = H * d[..., :, None] * d[..., None, :]
    lam, V = torch.linalg.eigh(A)
    cut = torch.finfo(A.dtype).eps * A.shape[-1] * lam.abs().amax(-1, keepdim=True)
    inverse = torch.where(lam.abs() > cut, 1.0 / lam, torch.zeros_like(lam))
    y = V @ (inverse * (V.mT @ (g * d)[..., None])[..., 0])[..., None]
    return -d * y[..., 0]

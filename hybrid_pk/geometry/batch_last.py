"""Small-matrix algebra in batch-last layout ("structure of arrays").

The IK inner loop handles thousands of 3×3 rotations and 6×6 normal equations at
once. PyTorch's batched matmul and LU are slow on such tiny matrices on a CPU; with
the batch as the last dimension every entry is a contiguous vector and each product
or factorisation step is one fused elementwise operation over the whole batch.

Shapes: a rotation is ``(3, 3, M)``, a vector ``(3, M)``, a matrix ``(n, n, M)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["compose", "rotate", "solve_spd"]

# Below this batch size the per-operation overhead of the unrolled Cholesky exceeds
# the cost of the batched LU.
_UNROLL_MIN_BATCH = 1024


def compose(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` for ``(3, 3, M)`` rotations (either may have ``M = 1``; views allowed)."""
    C = A[:, 0:1] * B[0:1]
    C = torch.addcmul(C, A[:, 1:2], B[1:2])
    return torch.addcmul(C, A[:, 2:3], B[2:3])


def rotate(A: Tensor, v: Tensor) -> Tensor:
    """``A @ v`` for ``A (3, 3, M)`` and ``v (3, M)`` or ``(3, 1)`` -> ``(3, M)``."""
    out = A[:, 0] * v[0]
    out = torch.addcmul(out, A[:, 1], v[1])
    return torch.addcmul(out, A[:, 2], v[2])


def _cholesky_unrolled(A: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    n = b.shape[0]
    tiny = torch.finfo(A.dtype).tiny
    ok = torch.ones(b.shape[1:], dtype=torch.bool, device=b.device)
    L: list[list[Tensor | None]] = [[None] * n for _ in range(n)]
    inv: list[Tensor] = []
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s = torch.addcmul(s, L[j][k], L[j][k], value=-1)
        ok &= s > 0
        inv.append(torch.rsqrt(s.clamp_min(tiny)))
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t = torch.addcmul(t, L[i][k], L[j][k], value=-1)
            L[i][j] = t * inv[j]
    y: list[Tensor] = []
    for i in range(n):
        t = b[i]
        for k in range(i):
            t = torch.addcmul(t, L[i][k], y[k], value=-1)
        y.append(t * inv[i])
    x: list[Tensor | None] = [None] * n
    for i in reversed(range(n)):
        t = y[i]
        for k in range(i + 1, n):
            t = torch.addcmul(t, L[k][i], x[k], value=-1)
        x[i] = t * inv[i]
    return torch.stack(x), ok


def solve_spd(A: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Solve ``A x = b`` for symmetric positive definite ``A (n, n, M)``, ``b (n, M)``.

    Never raises: a matrix that is not numerically positive definite gives
    ``ok = False`` for its column (and an unusable ``x`` there).

    Returns:
        ``x (n, M)`` and ``ok (M,)`` bool.
    """
    M = b.shape[-1]
    if M >= _UNROLL_MIN_BATCH:
        x, ok = _cholesky_unrolled(A, b)
    else:
        x, info = torch.linalg.solve_ex(A.permute(2, 0, 1), b.T)
        x, ok = x.T, info == 0
    return x, ok & torch.isfinite(x).all(0)

"""The blocked hold-out's Gram arithmetic (hybrid_pk.calibration.diagnosis.grams): the
rank-k update against a plain product, the solve against an SVD least squares."""

from __future__ import annotations

import pytest
import torch

from hybrid_pk.calibration.diagnosis.grams import add_gram, filled, solve_gram


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_chunked_updates_give_the_gram(dtype):
    gen = torch.Generator().manual_seed(0)
    M = torch.randn(700, 9, generator=gen, dtype=torch.float64).to(dtype)
    G = torch.zeros(9, 9, dtype=dtype)
    for chunk in (M[:250], M[250:251], M[251:, :].T.contiguous().T):  # last: not contiguous
        add_gram(G, chunk)
    ref = M.double().T @ M.double()
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    assert torch.allclose(filled(G).double(), ref, rtol=tol, atol=tol * float(ref.abs().max()))
    assert torch.equal(filled(G), filled(G).mT)


def _gelsd(H, g):
    d = H.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()
    A = H * d[..., :, None] * d[..., None, :]
    return -d * torch.linalg.lstsq(A, (g * d)[..., None], driver="gelsd").solution[..., 0]


def test_solve_matches_the_svd_least_squares():
    gen = torch.Generator().manual_seed(1)
    J = torch.randn(20, 300, 8, generator=gen, dtype=torch.float64)
    J[10:, :, 7] = J[10:, :, 2] - J[10:, :, 5]  # half the batch singular: a column repeats others
    J[15:, :, 6] = 0.0  # and a column no row sees
    r = torch.randn(20, 300, generator=gen, dtype=torch.float64)
    H, g = J.mT @ J, (J.mT @ r[..., None])[..., 0]
    x = solve_gram(H, g)
    ref = _gelsd(H, g)
    assert torch.allclose(x, ref, rtol=1e-9, atol=1e-9)
    # of minimum norm at unit column norms: no part along the direction the repeated
    # column leaves free (H n = 0 with n = e7 - e2 + e5; at unit norms D^-1 n, D = diag(H)^-1/2)
    n = torch.zeros(8, dtype=torch.float64)
    n[[7, 2, 5]] = torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)
    assert float((H[10:] @ n).abs().max()) < 1e-9 * float(H.abs().max())
    scaled = x[10:] * H[10:].diagonal(dim1=-2, dim2=-1).sqrt()  # the step at unit norms
    along = (scaled * n * H[10:].diagonal(dim1=-2, dim2=-1).sqrt()).sum(-1)
    assert float(along.abs().max()) < 1e-9 * float(scaled.norm(dim=-1).max())
    assert torch.equal(x[15:, 6], torch.zeros(5, dtype=torch.float64))  # the unseen column
    one = solve_gram(H[0], g[0])  # unbatched
    assert torch.allclose(one, x[0], rtol=1e-12, atol=1e-12)
    assert solve_gram(H[:, :0, :0], g[:, :0]).shape == (20, 0)

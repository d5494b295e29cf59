"""Shortcuts of the diagnosis' linear algebra against the plain computation: the factor
of ``[J r]`` completed from the Gram (QR of the leading columns only) and the LM stop
on the predicted next drop."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from hybrid_pk.calibration.diagnosis.blocked import cell_factors
from hybrid_pk.calibration.least_squares import levenberg_marquardt


class _Chunks:
    """A stand-in for :class:`Problem`: ``[J r]`` in chunks, position-only rows."""

    def __init__(self, J: torch.Tensor, r: torch.Tensor, rows_per_chunk: int) -> None:
        self.J, self.r, self.step = J, r, rows_per_chunk
        self.x0 = torch.zeros(J.shape[1], dtype=J.dtype)
        self.R_meas = None
        self.data = SimpleNamespace(n=J.shape[0] // 3)

    def augmented_chunks(self, theta):
        for s in range(0, self.J.shape[0], self.step):
            yield torch.cat([self.J[s : s + self.step], self.r[s : s + self.step, None]], 1)

    def r_factor(self, theta):
        return torch.linalg.qr(torch.cat([self.J, self.r[:, None]], 1), mode="r").R


def _projected_share(R: torch.Tensor, lead: int) -> torch.Tensor:
    """Share of each later column's squared norm left once projected off the leading
    columns, read from a factor ``R`` of ``[J r]``."""
    Q, _ = torch.linalg.qr(R[:, :lead])
    rest = R[:, lead:]
    left = rest - Q @ (Q.T @ rest)
    return left.pow(2).sum(0) / rest.pow(2).sum(0)


def test_completed_factor_matches_the_qr_one_with_a_degenerate_pair():
    g = torch.Generator().manual_seed(3)
    m, lead = 3 * 400, 6
    J = torch.randn(m, lead + 8, generator=g, dtype=torch.float64)
    J[:, 5] = 2.0 * J[:, 4]  # two leading parameters the data cannot tell apart
    J[:, lead] = J[:, 0] - 0.5 * J[:, 2]  # a candidate the leading columns explain
    J[:, lead + 1] = J[:, 1] + 1e-3 * J[:, lead + 2]  # nearly explained
    r = torch.randn(m, generator=g, dtype=torch.float64)
    problem = _Chunks(J, r, rows_per_chunk=3 * 70)
    R, _, _ = cell_factors(problem, None, True, lead)
    full = problem.r_factor(None)
    G = torch.cat([J, r[:, None]], 1)
    G = G.T @ G
    assert torch.allclose(R.T @ R, G, rtol=1e-10, atol=1e-10 * float(G.abs().max()))
    assert torch.allclose(R.T @ R, full.T @ full, rtol=1e-10, atol=1e-10 * float(G.abs().max()))
    # the span of the leading columns, rank-revealed on the rows themselves
    U, S, _ = torch.linalg.svd(J[:, :lead], full_matrices=False)
    U = U[:, S > 1e-10 * S[0]]
    rest = torch.cat([J[:, lead:], r[:, None]], 1)
    exact = (rest - U @ (U.T @ rest)).pow(2).sum(0) / rest.pow(2).sum(0)
    share = _projected_share(R, lead)
    assert float(share[0]) < 1e-12  # still equivalent to the model (selection: < 1e-8)
    assert torch.allclose(share[1:], exact[1:], rtol=1e-8, atol=1e-14)


def test_lm_stop_on_the_predicted_drop_reaches_the_same_minimum():
    t = torch.linspace(0.0, 3.0, 200, dtype=torch.float64)
    noise = 0.01 * torch.randn(200, generator=torch.Generator().manual_seed(1), dtype=t.dtype)
    y = 2.0 * torch.exp(-1.3 * t) + 0.5 + noise

    def residual(x: torch.Tensor) -> torch.Tensor:
        return (x[0] * torch.exp(-x[1] * t) + x[2] - y) / 0.01

    x0 = torch.tensor([1.0, 1.0, 0.0], dtype=t.dtype)
    plain = levenberg_marquardt(residual, x0)
    early = levenberg_marquardt(residual, x0, drop_tol=1e-4 / 200)
    assert early.converged
    assert early.iterations < plain.iterations
    # the stop leaves < 1e-4 of cost per residual: the values agree far inside their std
    assert abs(early.cost - plain.cost) < 1e-4 * plain.cost / 200 + 1e-6
    J = torch.autograd.functional.jacobian(residual, plain.x)
    std = torch.linalg.inv(J.T @ J).diagonal().sqrt()
    assert float(((early.x - plain.x) / std).abs().max()) < 0.01

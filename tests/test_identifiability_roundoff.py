"""The diagnosis' identifiability fields report measurements, not round-off: an exact
degeneracy of the fitted parameters (a singular value at the level of the Jacobian's
rounding errors) is counted and reported as 0, and the condition number and the
observability index are taken over the determined directions only. Before, two
Jacobians equal but for the order of their sums reported smallest singular values of
9.7e-16 and 4.8e-16 (the UR10 diagnosis) and observability indices 1.8 % apart."""

from __future__ import annotations

import pytest
import torch

from hybrid_pk.calibration.covariance import svd_covariance
from hybrid_pk.calibration.diagnosis.result import identifiability_json
from hybrid_pk.calibration.fit import FitResult

F64 = torch.float64


def _result(J: torch.Tensor) -> FitResult:
    """A fit result whose covariance fields come from Jacobian ``J`` (the rest unused)."""
    m, n = J.shape
    svd = svd_covariance(J, m, 1.0)
    zeros = torch.zeros(n, dtype=F64)
    return FitResult(
        blocks=(), x=zeros, std=zeros, corr=svd["corr"], singular_values=svd["singular_values"],
        condition=float(svd["singular_values"][0] / svd["singular_values"][-1]),
        sigma_pos_mm=0.02, sigma_rot_rad=None, position_mm=torch.zeros(m // 3, dtype=F64),
        orientation_deg=None, n_obs=m, n_params=n, iterations=1, converged=True,
    )  # fmt: skip


def _twice(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One Jacobian ``P M^-1 Q D`` with an exact trade-off (column 3 of ``Q`` = column
    0 - 2 column 1) and column sizes over 4 decades, built twice: ``P (M^-1 Q)`` and
    ``(P M^-1) Q``, as the compliance's feedback can be applied (equal in exact
    arithmetic, different in the last bits)."""
    g = torch.Generator().manual_seed(seed)
    P = torch.randn(300, 8, generator=g, dtype=F64)
    M = torch.eye(8, dtype=F64) + 0.3 * torch.randn(8, 8, generator=g, dtype=F64)
    Q = torch.randn(8, 6, generator=g, dtype=F64)
    Q[:, 3] = Q[:, 0] - 2.0 * Q[:, 1]
    D = torch.logspace(-2, 2, 6, dtype=F64)
    Ja = P @ torch.linalg.solve(M, Q) * D
    Jb = torch.linalg.solve(M.T, P.T).T @ Q * D
    return Ja, Jb


@pytest.mark.parametrize("seed", range(6))
def test_round_off_does_not_move_the_identifiability_fields(seed):
    Ja, Jb = _twice(seed)
    assert not torch.equal(Ja, Jb)  # the two builds differ, by round-off only
    a = identifiability_json(_result(Ja), [])
    b = identifiability_json(_result(Jb), [])
    assert a["singular_values"] == pytest.approx(b["singular_values"], rel=1e-9, abs=0)
    for key in ("condition_number", "observability_index"):
        assert a[key] == pytest.approx(b[key], rel=1e-9), key
    assert a["singular_values"][-1] == 0.0
    assert a["unidentifiable_directions"] == b["unidentifiable_directions"] == 1
    assert a["condition_number"] < 1e8  # over the determined directions: finite, modest


def test_a_determined_fit_reports_every_singular_value():
    """Without a degeneracy nothing is cut: the fields are the plain SVD's."""
    J = _twice(0)[0]
    g = torch.Generator().manual_seed(9)
    J[:, 3] += 1e-6 * J[:, 3].norm() * torch.randn(300, generator=g, dtype=F64)
    res = _result(J)
    fields = identifiability_json(res, [])
    assert fields["unidentifiable_directions"] == 0
    assert fields["singular_values"] == [float(v) for v in res.singular_values]
    assert fields["condition_number"] == pytest.approx(res.condition, rel=1e-12)
    s = res.singular_values
    assert fields["observability_index"] == pytest.approx(
        float(s.log().mean().exp()) / 300**0.5, rel=1e-12
    )


def test_a_jacobian_that_sees_nothing_has_no_condition_number():
    """No determined direction at all: every direction counted, no ratio to report
    (JSON null rather than NaN, which strict JSON cannot hold)."""
    fields = identifiability_json(_result(torch.zeros(30, 4, dtype=F64)), [])
    assert fields["unidentifiable_directions"] == 4
    assert fields["singular_values"] == [0.0] * 4
    assert fields["condition_number"] is None
    assert fields["observability_index"] == 0.0

"""hybrid_pk.distributions against scipy.stats: within 1e-13 relative (the same numbers
to the bit with scipy 1.17, where scipy.stats evaluates the same special functions; the
tolerance leaves room for a later scipy's rounding), within 1e-12 absolute for the
non-central survival functions (one minus the distribution function here)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy import stats

from hybrid_pk import distributions as dist

PROBS = [1e-300, 1e-40, 4e-6, 1e-3, 0.05, 0.5, 0.9, 1 - 1e-9]
DOFS = [1, 2, 3, 6, 7.5, 40, 1000]
XS = [1e-8, 0.1, 1.0, 3.0, 17.5, 250.0]


def _same(a: float, b: float) -> bool:
    return a == b or (np.isnan(a) and np.isnan(b)) or math.isclose(a, b, rel_tol=1e-13)


@pytest.mark.parametrize(("d1", "d2"), itertools.product(DOFS, DOFS))
def test_f_matches_scipy_stats(d1, d2):
    for x in XS:
        assert _same(dist.f_sf(x, d1, d2), float(stats.f.sf(x, d1, d2))), (x, d1, d2)
    for q in PROBS:
        assert _same(dist.f_isf(q, d1, d2), float(stats.f.isf(q, d1, d2))), (q, d1, d2)


@pytest.mark.parametrize("df", DOFS)
def test_chi2_matches_scipy_stats(df):
    for p in PROBS:
        assert _same(dist.chi2_ppf(p, df), float(stats.chi2.ppf(p, df))), (p, df)
        assert _same(dist.chi2_isf(p, df), float(stats.chi2.isf(p, df))), (p, df)
    for x in XS:
        assert _same(dist.chi2_pdf(x, df), float(stats.chi2.pdf(x, df))), (x, df)
    assert _same(dist.chi2_ppf(0.5, df), float(stats.chi2.median(df)))


def test_normal_matches_scipy_stats():
    for x in [-40.0, -3.0, -1e-9, 0.0, 0.7, 2.5, 6.0, 38.0]:
        assert _same(dist.norm_sf(x), float(stats.norm.sf(x))), x
    for q in PROBS:
        assert _same(dist.norm_isf(q), float(stats.norm.isf(q))), q


@pytest.mark.parametrize("df", [1, 3, 6, 12])
def test_noncentral_survival_close_to_scipy_stats(df):
    for x, nc in itertools.product([0.5, 5.0, 20.0, 60.0], [0.1, 4.0, 30.0]):
        assert dist.ncx2_sf(x, df, nc) == pytest.approx(float(stats.ncx2.sf(x, df, nc)), abs=1e-12)
        for d2 in (4, 50, 3000):
            got, want = dist.ncf_sf(x / df, df, d2, nc), float(stats.ncf.sf(x / df, df, d2, nc))
            assert got == pytest.approx(want, abs=1e-12), (x, df, d2, nc)


def test_chi2_quantile_of_an_array_of_degrees_of_freedom():
    df = np.array([3, 6, 9, 300])
    got = dist.chi2_ppf(0.5, df)
    assert isinstance(got, np.ndarray)
    np.testing.assert_allclose(got, stats.chi2.median(df), rtol=1e-13)

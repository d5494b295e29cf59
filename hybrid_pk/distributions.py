"""The distribution functions of the tool's tests and thresholds, on ``scipy.special``.

``scipy.stats`` costs ~0.3 s to import on top of ``scipy.special`` (0.6 s alone on CI's
two cores), and every ``diagnose`` and ``calibrate`` paid it for a handful of scalar
quantiles. These are the special functions ``scipy.stats`` evaluates for the same
quantities (with scipy 1.17 the F, chi-square and normal distributions give the same
numbers to the bit; tests/test_distributions.py holds them within 1e-13); the non-central
survival functions are one minus the public distribution functions (``scipy.stats`` takes
them from a private module), accurate to ~1e-16 absolute, which is what a detection power
needs. ``f_isf`` inverts the distribution function at ``1 - q``, as ``scipy.stats`` does:
below ``q`` ~ 1e-16 it returns inf (the diagnosis' levels, alpha over the candidates,
stay far above).

Scalars in, floats out (``chi2_ppf`` also takes an array of degrees of freedom).
"""

from __future__ import annotations

import numpy as np
from scipy import special

__all__ = [
    "chi2_isf",
    "chi2_pdf",
    "chi2_ppf",
    "f_isf",
    "f_sf",
    "ncf_sf",
    "ncx2_sf",
    "norm_isf",
    "norm_sf",
]


def f_sf(x: float, d1: float, d2: float) -> float:
    """Survival function of the F(``d1``, ``d2``) distribution at ``x``."""
    return float(special.fdtrc(d1, d2, x))


def f_isf(q: float, d1: float, d2: float) -> float:
    """``x`` whose F(``d1``, ``d2``) survival probability is ``q``."""
    return float(special.fdtri(d1, d2, 1.0 - q))


def chi2_ppf(p: float, df: float | np.ndarray) -> float | np.ndarray:
    """Quantile of chi-square(``df``) at probability ``p`` (``p = 0.5``: its median); an
    array of degrees of freedom gives an array."""
    out = 2 * special.gammaincinv(np.asarray(df, dtype=np.float64) / 2, p)
    return float(out) if np.ndim(out) == 0 else out


def chi2_isf(q: float, df: float) -> float:
    """``x`` whose chi-square(``df``) survival probability is ``q``."""
    return float(special.chdtri(df, q))


def chi2_pdf(x: float, df: float) -> float:
    """Density of chi-square(``df``) at ``x``."""
    log = special.xlogy(df / 2.0 - 1, x) - x / 2.0 - special.gammaln(df / 2.0)
    return float(np.exp(log - (np.log(2) * df) / 2.0))


def norm_sf(x: float) -> float:
    """Survival function of the standard normal distribution at ``x``."""
    return float(special.ndtr(-x))


def norm_isf(q: float) -> float:
    """``x`` whose standard normal survival probability is ``q``."""
    return float(-special.ndtri(q))


def ncx2_sf(x: float, df: float, nc: float) -> float:
    """Survival function of the non-central chi-square(``df``, ``nc``) at ``x``."""
    return float(1.0 - special.chndtr(x, df, nc))


def ncf_sf(x: float, d1: float, d2: float, nc: float) -> float:
    """Survival function of the non-central F(``d1``, ``d2``, ``nc``) at ``x``."""
    return float(1.0 - special.ncfdtr(d1, d2, nc, x))

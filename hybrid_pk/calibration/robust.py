"""Robust fits: rows with gross errors are down-weighted, listed, never dropped silently.

A measured row ``i`` has the noise-normalised residual ``e_i`` (3 position components
[mm / sigma_pos], plus 3 rotation components [rad / sigma_rot] with orientation data)
and the squared distance ``d_i^2 = |e_i|^2``, chi-square with ``dim`` degrees of
freedom when the row is only noise. Robust fits are iteratively re-weighted least
squares on whole rows (a broken beam spoils a row, not one coordinate):

- ``huber``:  ``w = min(1, c / d)`` (bounded influence, convex);
- ``cauchy``: ``w = 1 / (1 + d^2 / c^2)`` (redescending: a wild point has no pull);

with ``c^2`` the 99 % quantile of chi-square(``dim``) (a clean row keeps at least half
its weight 99 times in 100, so clean data fit as by least squares), and the noise
levels estimated from the median row distance (which outliers do not move) instead of
the mean. Every row a robust fit gives less than half its weight is reported.

A row is an *outlier* when ``d_i^2`` lies beyond the chi-square quantile that has the
tail probability of a ``k``-sigma deviation of one normal coordinate (``k = 4``: one
clean row in 16 000 is listed), or, in campaigns of more than ``FAMILY_ALPHA / 6.3e-5``
rows, the Bonferroni quantile ``FAMILY_ALPHA / N`` (a clean campaign lists a row in at
most one of 20 campaigns, whatever its size). For the listing, ``d_i^2`` uses noise
levels re-estimated from the median of the rows' squared position (and rotation)
errors against that of chi-square(3): a least-squares fit's noise estimate carries the
gross rows themselves (2 % of rows displaced by 2-10 mm make a 0.05 mm noise look
like 0.5 mm and hide the smaller of them), the median does not.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.distributions import chi2_isf, chi2_ppf, norm_sf
from hybrid_pk.errors import HybridPKError

__all__ = [
    "CUT_WEIGHT",
    "DOWN_WEIGHT",
    "FAMILY_ALPHA",
    "LEVER_M",
    "NOISE_FLOOR_MM",
    "OUTLIER_K",
    "ROBUST_LOSSES",
    "check_robust",
    "down_weighted",
    "irls_update",
    "list_outliers",
    "outlier_cut",
    "outlier_threshold",
    "reestimated_noise",
    "robust_cost",
    "robust_noise",
    "robust_weights",
    "rotation_noise",
    "row_d2",
    "row_distances",
    "row_weights_vector",
]


# The lever [m] that bounds how finely an orientation noise may weigh against the
# position noise: the reach of a large industrial arm. No instrument pairs the two more
# finely (a 6-DoF laser tracker: 0.01 deg against 15 um, sigma_pos / sigma_rot ~ 0.09 m);
# below sigma_pos / LEVER_M the orientation is not measured but exact (rounding, a
# simulation without orientation noise) and would outweigh every position row.
LEVER_M = 2.0


# The smallest position noise [mm] a fit or an outlier listing assumes: a nanometre, a
# thousand times below any tracker's resolution and far above float64 round-off of
# metre-scale positions (~1e-13 mm): rows simulated without noise are taken as measured
# to 1 nm, so their round-off is neither a noise level nor an outlier.
NOISE_FLOOR_MM = 1e-6


def rotation_noise(sigma_rot_rad: float, sigma_pos_mm: float) -> float:
    """``sigma_rot_rad`` [rad], at least the position noise over :data:`LEVER_M`."""
    return max(sigma_rot_rad, 1e-3 * sigma_pos_mm / LEVER_M, 1e-9)


ROBUST_LOSSES = ("huber", "cauchy")
# Rows beyond the tail probability of a k-sigma normal deviation are outliers.
OUTLIER_K = 4.0
# Family-wise false-listing rate of a clean campaign (Bonferroni over its rows).
FAMILY_ALPHA = 0.05
# Quantile of chi-square(dim) whose square root is the tuning constant c.
TUNING_QUANTILE = 0.99
# A row with a weight below this is reported as down-weighted ...
DOWN_WEIGHT = 0.5
# ... and below this as cut (a gross error: its pull on the fit is gone).
CUT_WEIGHT = 0.1


def check_robust(loss: str | None) -> str | None:
    """``None``/``"none"`` -> None; a known loss name; else a clear error."""
    if loss is None or loss == "none":
        return None
    if loss not in ROBUST_LOSSES:
        raise HybridPKError(
            f"--robust: unknown loss {loss!r}; choose none, {' or '.join(ROBUST_LOSSES)}"
        )
    return loss


def outlier_threshold(dim: int, k: float = OUTLIER_K) -> float:
    """``d^2`` beyond which a row of ``dim`` components is an outlier (k-sigma tail)."""
    return chi2_isf(2.0 * norm_sf(k), dim)


def _median_sigma(err: Tensor, given: float, floor: float) -> float:
    """Per-coordinate noise from the median of the squared 3-D errors ``err (N,)``
    against chi-square(3)'s, at least ``floor``; ``given`` where there are too few rows
    or no spread."""
    if err.numel() < 5:  # a median of fewer rows says little
        return given
    s = math.sqrt(float(err.pow(2).median()) / chi2_ppf(0.5, 3))
    return max(s, floor) if s > 0 else given


def row_d2(
    position_mm: Tensor,
    orientation_deg: Tensor | None,
    sigma_pos_mm: float,
    sigma_rot_rad: float | None,
) -> tuple[Tensor, int]:
    """``(d2 (N,), dim)``: each row's squared noise-normalised distance for the outlier
    listing, with the noise levels from the medians of the rows (module docstring)."""
    sp = _median_sigma(position_mm, sigma_pos_mm, NOISE_FLOOR_MM)
    d2 = (position_mm / sp) ** 2
    if orientation_deg is None or sigma_rot_rad is None:
        return d2, 3
    rot = torch.deg2rad(orientation_deg)
    return d2 + (rot / _median_sigma(rot, sigma_rot_rad, rotation_noise(0.0, sp))) ** 2, 6


def outlier_cut(d2: Tensor, dim: int, k: float = OUTLIER_K) -> float:
    """``d^2`` beyond which a row is listed: the ``k``-sigma tail, or the Bonferroni
    tail ``FAMILY_ALPHA / N`` where that is stricter."""
    tail = min(2.0 * norm_sf(k), FAMILY_ALPHA / max(d2.numel(), 1))
    return chi2_isf(tail, dim)


def row_distances(r: Tensor, n_rows: int) -> Tensor:
    """``(N,)`` squared row distances ``d^2`` of a residual ``(3 N)`` or ``(6 N)``
    laid out as the fit's: position components row by row, then rotation."""
    parts = r.reshape(-1, n_rows, 3)
    return (parts**2).sum(-1).sum(0)


def row_weights_vector(w: Tensor, n_parts: int) -> Tensor:
    """Per-row weights ``(N,)`` expanded to the residual layout (``sqrt`` not taken)."""
    return w.repeat_interleave(3).repeat(n_parts)


def robust_weights(d2: Tensor, dim: int, loss: str) -> Tensor:
    """``(N,)`` IRLS weights of rows with squared distances ``d2``."""
    c2 = chi2_ppf(TUNING_QUANTILE, dim)
    if loss == "huber":
        return torch.clamp(math.sqrt(c2) / d2.clamp_min(1e-300).sqrt(), max=1.0)
    if loss == "cauchy":
        return 1.0 / (1.0 + d2 / c2)
    raise HybridPKError(f"unknown robust loss {loss!r}")


def robust_cost(d2: Tensor, dim: int, loss: str) -> float:
    """``sum rho(d)`` of rows with squared distances ``d2``, scaled so that
    ``rho(d) = d^2`` for small ``d`` (a sum of squares for clean rows).

    Huber: ``d^2`` up to ``c``, then ``2 c d - c^2``; Cauchy: ``c^2 log(1 + d^2 / c^2)``.
    """
    c2 = chi2_ppf(TUNING_QUANTILE, dim)
    if loss == "huber":
        d = d2.clamp_min(0).sqrt()
        c = math.sqrt(c2)
        return float(torch.where(d <= c, d2, 2 * c * d - c2).sum())
    if loss == "cauchy":
        return float((c2 * torch.log1p(d2 / c2)).sum())
    raise HybridPKError(f"unknown robust loss {loss!r}")


def robust_noise(r: Tensor, n_rows: int, dof_factor: float = 1.0) -> tuple[float, float | None]:
    """Factors by which the noise levels behind ``r`` should change: from the median
    squared row norm of the position part (and of the rotation part), each against the
    median of chi-square(3). Returns ``(factor_pos, factor_rot or None)``."""
    parts = (r.reshape(-1, n_rows, 3) ** 2).sum(-1)  # (1 or 2, N)
    med = chi2_ppf(0.5, 3)
    factors = [float((p.median() / med * dof_factor).clamp_min(1e-300).sqrt()) for p in parts]
    return factors[0], factors[1] if len(factors) > 1 else None


def irls_update(
    r: Tensor,
    n_rows: int,
    n_params: int,
    sigmas: tuple[float, float],
    fixed: tuple[float | None, float | None],
    loss: str,
    weights: Tensor,
) -> tuple[float, float, Tensor, float]:
    """One IRLS update after a pass of a robust fit.

    Args:
        r: ``(3 N)`` or ``(6 N)`` residuals of the rows (without their robust weights)
            under the noise levels ``sigmas = (sigma_pos_mm, sigma_rot_rad)``.
        n_rows, n_params: rows N and fitted parameters (degrees of freedom).
        fixed: noise levels given by the caller (not re-estimated), or None.
        loss: ``"huber"`` or ``"cauchy"``.
        weights: ``(N,)`` the weights of the pass.

    Returns:
        ``(sigma_pos_mm, sigma_rot_rad, weights, change)``: noise levels from the median
        row distance, the rows' new weights, and the largest relative change of a noise
        level or (doubled) of a weight.
    """
    sig_p, sig_r = sigmas
    position_only = r.numel() == 3 * n_rows
    dof_factor = r.numel() / max(r.numel() - n_params, 1)
    f_p, f_r = robust_noise(r, n_rows, dof_factor)
    new_p = fixed[0] or max(sig_p * f_p, NOISE_FLOOR_MM)
    new_r = sig_r if position_only or fixed[1] is not None else rotation_noise(sig_r * f_r, new_p)
    change = (
        0.0
        if fixed[0] and (fixed[1] or position_only)
        else max(abs(new_p / sig_p - 1), abs(new_r / sig_r - 1))
    )
    parts = r.reshape(-1, n_rows, 3).clone()
    parts[0] *= sig_p / new_p
    if not position_only:
        parts[1] *= sig_r / new_r
    new_w = robust_weights(row_distances(parts, n_rows), 3 if position_only else 6, loss)
    return new_p, new_r, new_w, max(change, float((new_w - weights).abs().max()) / 0.5)


def reestimated_noise(
    r: Tensor,
    n_rows: int,
    n_params: int,
    sigmas: tuple[float, float],
    fixed: tuple[float | None, float | None] = (None, None),
    position_only: bool = False,
) -> tuple[float, float]:
    """Noise levels ``(sigma_pos_mm, sigma_rot_rad)`` that make the mean square of the
    residuals ``r`` (computed under ``sigmas``) one per degree of freedom.

    ``fixed`` levels (not None) are kept; so is the rotation level without orientation.
    """
    sig_p, sig_r = sigmas
    n_pos = 3 * n_rows
    dof_factor = r.numel() / max(r.numel() - n_params, 1)
    new_p = fixed[0] or max(
        sig_p * float((r[:n_pos] ** 2).mean() * dof_factor) ** 0.5, NOISE_FLOOR_MM
    )
    new_r = sig_r
    if not position_only and fixed[1] is None:
        rot = r[n_pos : 2 * n_pos]
        new_r = rotation_noise(sig_r * float((rot**2).mean() * dof_factor) ** 0.5, new_p)
    return new_p, new_r


def list_outliers(
    data: MeasuredData,
    position_mm: Tensor,
    orientation_deg: Tensor | None,
    sigma_pos_mm: float,
    sigma_rot_rad: float | None,
    k: float = OUTLIER_K,
    d2: Tensor | None = None,
) -> list[dict]:
    """Rows beyond ``k`` sigma: ``{"file", "row", "position_mm", "orientation_deg",
    "sigma"}``, with ``row`` the 1-based data row of ``file``, largest first.

    Args:
        data: the rows.
        position_mm, orientation_deg: ``(N,)`` errors of the model on them.
        sigma_pos_mm, sigma_rot_rad: per-coordinate noise of a clean row.
        d2: ``(N,)`` squared noise-normalised row distances (default: from the errors,
            taking an error as isotropic).
    """
    dim = 3 if orientation_deg is None or sigma_rot_rad is None else 6
    if d2 is None:
        d2, dim = row_d2(position_mm, orientation_deg, sigma_pos_mm, sigma_rot_rad)
    threshold = outlier_cut(d2, dim, k)
    idx = torch.nonzero(d2 > threshold).reshape(-1)
    idx = idx[torch.argsort(d2[idx], descending=True)]
    out = []
    for i in idx.tolist():
        entry = {
            "file": Path(data.sources[int(data.file_index[i])]).name,
            "row": int(data.rows[i]),
            "position_mm": float(position_mm[i]),
            "orientation_deg": None if orientation_deg is None else float(orientation_deg[i]),
            "sigma": float(d2[i].sqrt()),
        }
        out.append(entry)
    return out


def down_weighted(data: MeasuredData, weights: Tensor, rows: Tensor | None = None) -> list[dict]:
    """Rows whose robust weight is below ``DOWN_WEIGHT``: ``{"file", "row", "weight"}``.

    Args:
        weights: ``(n,)`` weights of the fitted rows.
        rows: ``(n,)`` indices of those rows in ``data`` (default all).
    """
    index = torch.arange(data.n) if rows is None else rows
    out = []
    for j in torch.nonzero(weights < DOWN_WEIGHT).reshape(-1).tolist():
        i = int(index[j])
        out.append(
            {
                "file": Path(data.sources[int(data.file_index[i])]).name,
                "row": int(data.rows[i]),
                "weight": float(weights[j]),
            }
        )
    return out

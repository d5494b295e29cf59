"""The measurement noise of a campaign, from its own data and no model of its errors.

Two poses close in joint space see nearly the same systematic error (any smooth error
of the arm, modelled or not), so the difference of their nominal-model residuals is
the difference of two independent noise draws: per coordinate of variance
``2 sigma^2``. Per file (a set-up: its frames and its drift its own) the closest pairs
are taken, repeated poses first (they are the closest); half the squared difference of
the position residuals, summed over the three coordinates, is ``sigma^2 chi^2_3``, so
the median over the pairs divided by the median of ``chi^2_3`` estimates ``sigma^2``
(robustly: a pair with a gross row or a backlash flip does not move it). The files'
variances are pooled, weighted by their pairs.

Closeness is measured in metres of point motion: each joint's angle difference times
its median lever (:func:`.regions.joint_levers`), so a wrist joint that hardly moves
the point does not make a pair look far apart. Where no pair is close, the change of
the systematic error between its poses adds to the estimate: it is an upper bound of
the noise there, and the diagnosis caps it by the fit's sigma.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.regions import joint_levers
from hybrid_pk.calibration.fit import predicted_poses
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.distributions import chi2_pdf, chi2_ppf
from hybrid_pk.effects import Conditions, ExtendedModel

__all__ = ["NOISE_PAIRS", "NoiseEstimate", "beyond_noise", "measurement_noise"]

# Closest pairs per file: the median of 50 chi^2_3 draws gives sigma within 8 % (one
# standard deviation, 20 % at 99 %), and 50 pairs stay the close ones in a campaign of
# a few hundred rows.
NOISE_PAIRS = 50
# Neighbours per row searched for pairs: each row's nearest few hold the closest pairs.
NEIGHBOURS = 3

# Standard deviations of the log mean square beyond which the left error is called
# larger than the noise: the 4 sigma of the neighbour test (statistics.py).
BEYOND_SD = 4.0

METHOD = (
    "model-free: per file the {pairs} closest pairs in joint space (metres of point "
    "motion, repeats first), median of half the squared difference of their nominal-model "
    "position residuals / median of chi^2_3, pooled over files"
)


@dataclass(frozen=True)
class NoiseEstimate:
    """Position noise per coordinate [mm] from close pairs of poses.

    Attributes:
        sigma_mm: the pooled estimate (None: no file has a pair).
        files: per file ``{"file", "sigma_mm", "pairs", "repeats", "max_distance_mm"}``
            (``max_distance_mm``: the farthest pair used, in point motion).
    """

    sigma_mm: float | None
    files: tuple[dict, ...]

    def to_json(self) -> dict:
        return {
            "sigma_mm": self.sigma_mm,
            "method": METHOD.format(pairs=NOISE_PAIRS),
            "files": list(self.files),
        }


@torch.no_grad()
def measurement_noise(model: ExtendedModel, data: MeasuredData, cond: Conditions) -> NoiseEstimate:
    """The noise estimate of ``data`` (see the module) from ``model``'s residuals (the
    nominal model with its fitted frames; its errors cancel between close poses)."""
    from scipy import spatial  # ~0.2 s to import: on first use

    residual = (data.position - predicted_poses(model, data.q, cond)[:, :3, 3]) * 1000.0
    lever = torch.tensor(joint_levers(model, data.q, cond), dtype=data.q.dtype)
    x = (data.q * lever).numpy()  # [m] of point motion
    files, total, weight = [], 0.0, 0
    for f in range(len(data.sources)):
        rows = torch.nonzero(data.file_index == f).flatten()
        if rows.numel() < 2:
            continue
        pairs, dist = _closest_pairs(spatial.cKDTree(x[rows.numpy()]), x[rows.numpy()])
        d = residual[rows[pairs[:, 0]]] - residual[rows[pairs[:, 1]]]
        half = 0.5 * (d**2).sum(1)
        kept = torch.nonzero(half > 0).flatten()[:NOISE_PAIRS]  # 0: a copied row
        if kept.numel() == 0:
            continue
        half, dist = half[kept], dist[kept.numpy()]
        var = float(half.median()) / chi2_ppf(0.5, 3)
        files.append(
            {
                "file": data.sources[f],
                "sigma_mm": math.sqrt(var),
                "pairs": int(half.numel()),
                "repeats": int((dist == 0).sum()),
                "max_distance_mm": float(dist.max()) * 1000.0,
            }
        )
        total, weight = total + var * half.numel(), weight + half.numel()
    sigma = math.sqrt(total / weight) if weight else None
    return NoiseEstimate(sigma, tuple(files))


def _closest_pairs(tree, x):
    """``(pairs (k, 2) long, distances (k,))``: the distinct pairs among each row's
    :data:`NEIGHBOURS` nearest rows, closest first."""
    import numpy as np

    k = min(NEIGHBOURS + 1, x.shape[0])
    dist, idx = tree.query(x, k=k)
    rows = np.repeat(np.arange(x.shape[0]), k)
    a, b, dist = rows, idx.reshape(-1), dist.reshape(-1)
    keep = a != b  # a repeated pose may list its twin before itself
    a, b, dist = np.minimum(a, b)[keep], np.maximum(a, b)[keep], dist[keep]
    _, first = np.unique(a * x.shape[0] + b, return_index=True)
    order = first[np.argsort(dist[first], kind="stable")]
    pairs = torch.from_numpy(np.stack([a[order], b[order]], 1)).long()
    return pairs, dist[order]


def beyond_noise(position_mm: Tensor, noise: NoiseEstimate | None) -> dict | None:
    """Is the left position error ``(N, 3)`` [mm] of the hold-out rows larger than the
    measurement noise? Both sides are read the same robust way: the median over rows of
    the squared error (three coordinates) over the median of chi^2_3 estimates the
    per-coordinate variance, as :func:`measurement_noise` does over its P closest pairs
    (a gross row or a backlash flip moves neither). Each median of K draws has a
    relative variance ``1 / (4 K f(m)^2 m^2)`` (``f`` the chi^2_3 density at its median
    ``m``); the error is beyond the noise when the log of the two variances' ratio
    exceeds :data:`BEYOND_SD` standard deviations of their sum. None without a noise
    estimate. A smooth error that neighbouring hold-out poses are too far apart to share
    (a few hundred rows in many joints) still shows here, unless it varies over less
    than the distance of the estimate's pairs (``pair_distance_mm``, point motion)."""
    if noise is None or noise.sigma_mm is None or position_mm.shape[0] < 2:
        return None
    m = chi2_ppf(0.5, 3)
    per_draw = 1.0 / (4 * chi2_pdf(m, 3) ** 2 * m**2)  # K = 1
    pairs = sum(f["pairs"] for f in noise.files)
    sd = math.sqrt(per_draw / position_mm.shape[0] + per_draw / pairs)
    sigma = math.sqrt(float(position_mm.pow(2).sum(-1).median()) / m)
    ratio, limit = sigma / noise.sigma_mm, math.exp(BEYOND_SD * sd / 2)  # sigma: half the log
    return {
        "sigma_mm": sigma,
        "noise_mm": noise.sigma_mm,
        "ratio": ratio,
        "limit": limit,
        "beyond": ratio > limit,
        # an error that varies over less than this differs between the estimate's pairs:
        # it is counted as noise there, and cannot be told from noise here
        "pair_distance_mm": max(f["max_distance_mm"] for f in noise.files),
    }

"""Initial joint configurations ("seeds") for the IK solver.

Quasi-random points (scrambled Sobol or Halton) fill the joint box more evenly than
uniform random ones, so a fixed number of seeds reaches more of the basins of the
distinct IK branches. The same seeds serve every target of a call (deterministic for
a given ``seed``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.errors import ShapeError

__all__ = ["SEED_METHODS", "quasi_random_seeds", "seed_box"]

SEED_METHODS = ("sobol", "halton", "uniform")
# Seeds stay this fraction of the range away from each limit: a seed on a limit starts
# the projected iteration with that joint pinned.
_MARGIN = 0.005
# Range [m] sampled for a prismatic joint without limits.
_FREE_PRISMATIC = 1.0


def seed_box(lower: Tensor, upper: Tensor, revolute: Tensor) -> tuple[Tensor, Tensor]:
    """Finite box ``(lo, hi)``, each ``(dof,)``, that seeds are drawn from.

    Finite limits are used as they are; a continuous joint gets ``[-pi, pi]`` (every
    angle once), an unlimited prismatic joint ``[-1, 1]`` m.
    """
    free = torch.where(revolute, math.pi, _FREE_PRISMATIC).to(lower.dtype)
    lo = torch.where(torch.isfinite(lower), lower, -free)
    hi = torch.where(torch.isfinite(upper), upper, free)
    return lo, hi


def quasi_random_seeds(
    lower: Tensor,
    upper: Tensor,
    revolute: Tensor,
    n: int,
    *,
    method: str = "sobol",
    seed: int = 0,
) -> Tensor:
    """``n`` joint configurations spread over the joint limits.

    Args:
        lower: ``(dof,)`` lower limits [rad or m].
        upper: ``(dof,)`` upper limits.
        revolute: ``(dof,)`` bool, revolute/continuous joints.
        n: number of seeds (>= 1).
        method: ``"sobol"`` (scrambled, default), ``"halton"`` (scrambled) or
            ``"uniform"`` (pseudo-random).
        seed: scrambling / random seed: same seed, same points.

    Returns:
        ``(n, dof)`` float64 joint values inside the limits [rad or m].
    """
    if n < 1:
        raise ShapeError(f"need at least one seed, got n={n}")
    if method not in SEED_METHODS:
        raise ShapeError(f"seed method must be one of {', '.join(SEED_METHODS)}, got {method!r}")
    dof = lower.shape[-1]
    if method == "sobol":
        engine = torch.quasirandom.SobolEngine(dof, scramble=True, seed=seed)
        u = engine.draw(n, dtype=torch.float64)
    elif method == "halton":
        from scipy.stats import qmc

        u = torch.from_numpy(qmc.Halton(dof, scramble=True, seed=seed).random(n))
    else:
        rng = np.random.default_rng(seed)
        u = torch.from_numpy(rng.random((n, dof)))
    lo, hi = seed_box(lower.to(torch.float64), upper.to(torch.float64), revolute)
    u = _MARGIN + (1 - 2 * _MARGIN) * u.to(torch.float64)
    return lo + u * (hi - lo)

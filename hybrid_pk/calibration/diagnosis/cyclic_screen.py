"""Which orders of a cyclic joint error to test: a periodogram of each joint's angle error.

Every order ``n`` of ``cyclic_error_<n>`` on every revolute joint is a candidate (some
two hundred on a six-axis arm). Scoring them all at every step would multiply the
Jacobian the search builds by ten. Instead, once the frames are fitted, the position
residual of each fit row is read as the angle error of each joint that would explain it
best (``e = J_j · r / |J_j|²``, rows where the joint moves the point at all), and the
weighted periodogram of ``e`` against that joint's angle ranks the orders. The best
:data:`SCREEN_KEEP` orders per joint go on as candidates; the others count in the
Bonferroni level of every step all the same (they were looked at).
"""

from __future__ import annotations

from collections import defaultdict

import torch

from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.effects.joint import CYCLIC_PREFIX

__all__ = ["SCREEN_KEEP", "screen_cyclic"]

SCREEN_KEEP = 2  # orders per joint that go on to the score test
_STEP = 1e-6  # [rad] finite-difference step of the joint's point Jacobian
_MIN_LEVER = 0.2  # rows whose |J_j| is below this fraction of the median are left out
_MIN_ROWS = 8  # fewer informative rows than this: the joint's orders are not scored


def screen_cyclic(
    model: ExtendedModel, split: Split, pool: list[str], weights: torch.Tensor | None = None
) -> tuple[list[str], int]:
    """``pool`` with its cyclic candidates cut to the best orders per joint, and how
    many were set aside (to add to the candidate count of the Bonferroni level).

    ``weights``: ``(n_fit,)`` robust row weights of the fit (a gross row does not
    choose an order); None: every row alike.
    """
    orders: dict[str, list[int]] = defaultdict(list)
    for label in pool:
        kind, _, joint = label.partition(":")
        if kind.startswith(CYCLIC_PREFIX):
            orders[joint].append(int(kind.removeprefix(CYCLIC_PREFIX)))
    if not orders:
        return pool, 0
    data, cond = split.train, split.cond_fit
    names = model.robot.joint_names
    with torch.no_grad():
        p0 = model(data.q, cond)[:, :3, 3]
        r = data.position.to(p0.dtype) - p0
        kept = set()
        for joint, ns in orders.items():
            j = names.index(joint)
            dq = torch.zeros_like(data.q)
            dq[:, j] = _STEP
            J = (model(data.q + dq, cond)[:, :3, 3] - p0) / _STEP  # (n, 3) [m/rad]
            w = (J * J).sum(-1)
            rows = w > _MIN_LEVER**2 * w.median()
            if int(rows.sum()) < _MIN_ROWS:
                continue  # the joint barely moves the point: no order to rank
            e = (J * r).sum(-1)[rows] / w[rows]  # equivalent angle error [rad]
            w_rows = w[rows] if weights is None else w[rows] * weights[rows].to(w.dtype)
            ranked = sorted(ns, key=lambda n: -_explained(e, w_rows, data.q[rows, j], n))
            kept |= {f"{CYCLIC_PREFIX}{n}:{joint}" for n in ranked[:SCREEN_KEEP]}
    out = [c for c in pool if not c.startswith(CYCLIC_PREFIX) or c in kept]
    return out, len(pool) - len(out)


def _explained(e: torch.Tensor, w: torch.Tensor, theta: torch.Tensor, n: int) -> float:
    """Weighted sum of squares of ``e`` that ``a sin(n theta) + b cos(n theta) + c``
    explains beyond the constant ``c``."""
    s = w.sqrt()
    A = torch.stack([torch.sin(n * theta), torch.cos(n * theta), torch.ones_like(theta)], 1)
    y = e * s
    coef = torch.linalg.lstsq(A * s[:, None], y[:, None]).solution[:, 0]
    fitted = (A @ coef) * s
    mean = (y * s).sum() / (s * s).sum()
    return float(((y - mean * s) ** 2).sum() - ((y - fitted) ** 2).sum())

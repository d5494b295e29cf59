"""Which orders of a cyclic joint error to test: a blocked periodogram of each joint's
angle error.

Every order ``n`` of ``cyclic_error_<n>`` on every revolute joint is a candidate (some
two hundred on a six-axis arm). Scoring them all at every step would multiply the
Jacobian the search builds by ten. Instead, at every step of the search, the position
residual the current model leaves on each fit row is read as the angle error of each
joint that would explain it best (``e = J_j · r / |J_j|²``, rows where the joint moves
the point at all), and for each order the sinusoid ``a sin(n q) + b cos(n q) + c`` of
that angle error is fitted block by block (the blocks of the blocked hold-out,
:mod:`.blocked`) and scored on the held-out block. An order goes on to that step's
score test when it predicts the held-out blocks better than the constant alone by the
practical margin (the displacement ``e |J_j|`` along the joint's motion, RMS in mm):
that one-dimensional gain exceeds the gain the same order brings to the 3-D error (the
error of the other directions adds to the RMS and does not change), so no order that
could earn its place is screened out. The others count in the step's Bonferroni level
all the same (they were looked at). Ranking anew at every step matters: before a large
error (a misaligned wrist axis) is explained, it leaks into every joint's ``e`` and
hides a smaller periodic error.

Whether a chosen order is resolved (no other order predicts the held-out blocks nearly
as well) is decided on the full model: :mod:`.settle`.
"""

from __future__ import annotations

from collections import defaultdict

import torch

from hybrid_pk.calibration.diagnosis.blocked import Folds
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import equivalent_angle_error
from hybrid_pk.calibration.fit import predicted_poses
from hybrid_pk.calibration.structured_jacobian import point_jacobian
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.effects.joint import CYCLIC_PREFIX

__all__ = ["angle_error", "blocked_order_gains", "screen_cyclic"]

# rows whose |J_j| is below this fraction of the median are left out: a row's angle
# error is its position residual / |J_j|, so such a row carries over 5x the median
# row's noise and under 4 % of its weight (|J_j|^2): noise, hardly information.
_MIN_LEVER = 0.2
# fewer informative rows than this: the joint's orders are not scored (with a fifth of
# them held out, 8 rows leave about 6 to fit the 3 regressors sin, cos and constant).
_MIN_ROWS = 8


def screen_cyclic(
    model: ExtendedModel,
    split: Split,
    pool: list[str],
    weights: torch.Tensor | None = None,
    folds: Folds | None = None,
    margin: float = 0.0,
) -> tuple[list[str], int]:
    """``pool`` with its cyclic candidates cut to the orders whose angle-error sinusoid
    gains ``margin`` [mm] on the blocked hold-out (``folds``; without blocks every
    order is kept), and how many were set aside (to add to the candidate count of the
    Bonferroni level).

    ``weights``: ``(n_fit,)`` robust row weights of the fit (a gross row does not
    choose an order); None: every row alike.
    """
    orders: dict[str, list[int]] = defaultdict(list)
    for label in pool:
        kind, _, joint = label.partition(":")
        if kind.startswith(CYCLIC_PREFIX):
            orders[joint].append(int(kind.removeprefix(CYCLIC_PREFIX)))
    if not orders or folds is None:
        return pool, 0
    data, cond = split.train, split.cond_fit
    names = model.robot.joint_names
    with torch.no_grad():
        T0 = predicted_poses(model, data.q, cond)  # kept where the refit ended
        r = data.position.to(T0.dtype) - T0[:, :3, 3]
        J = point_jacobian(model, data.q, cond)
        kept = set()
        for joint, ns in orders.items():
            got = angle_error(J[:, :, names.index(joint)], split, names.index(joint), r, weights)
            if got is None:
                continue  # the joint barely moves the point: no order to rank
            gains = blocked_order_gains(*got, folds, ns)
            kept |= {f"{CYCLIC_PREFIX}{n}:{joint}" for n, g in gains.items() if g >= margin}
    out = [c for c in pool if not c.startswith(CYCLIC_PREFIX) or c in kept]
    return out, len(pool) - len(out)


def blocked_order_gains(e, w, theta, rows, folds: Folds, ns: list[int]) -> dict[int, float]:
    """Per order ``n``: the drop [mm] of the blocked RMS of ``e |J|`` when the sinusoid
    of ``n`` cycles per turn is fitted per block besides the constant."""
    cells = folds.cell[rows]
    cell_rows = torch.nn.functional.one_hot(cells, folds.n_cells).to(e.dtype).T.contiguous()
    n_rows = sum(int((cells[:, None] == torch.tensor(f)).any(1).sum()) for f in folds.folds)
    held = torch.zeros(len(folds.folds), folds.n_cells, dtype=e.dtype)  # fold x cell
    for i, f in enumerate(folds.folds):
        held[i, list(f)] = 1.0
    # Per cell, the weighted Gram of [sin(n q), cos(n q), 1, e] of every order at once:
    # products of the cell indicator with the rows' weighted products.
    order = torch.tensor(ns, dtype=e.dtype)
    S, C = torch.sin(theta[:, None] * order), torch.cos(theta[:, None] * order)  # (N, L)
    wS, wC, we = w[:, None] * S, w[:, None] * C, w * e
    per_order = {  # (i, j) entries of the Gram of [sin, cos, 1, e], summed per cell
        (0, 0): S * wS, (0, 1): C * wS, (0, 2): wS, (0, 3): e[:, None] * wS,
        (1, 1): C * wC, (1, 2): wC, (1, 3): e[:, None] * wC,
    }  # fmt: skip
    shared = {(2, 2): w, (2, 3): we, (3, 3): we * e}
    grams = e.new_empty(folds.n_cells, len(ns), 4, 4)
    for (i, j), x in per_order.items():
        grams[:, :, i, j] = grams[:, :, j, i] = cell_rows @ x
    for (i, j), x in shared.items():
        grams[:, :, i, j] = grams[:, :, j, i] = (cell_rows @ x)[:, None]
    base = _blocked_rms(grams[:, :1, 2:, 2:], held, n_rows)[0]  # the constant alone
    gains = base - _blocked_rms(grams, held, n_rows)
    return dict(zip(ns, gains.tolist(), strict=True))


def _blocked_rms(grams, held, n_rows: int):
    """Blocked RMS [mm] per order of the residual of ``e`` after its regressors, each
    fitted on the other blocks: ``grams (cells, L, p, p)``, the Gram of ``[A e]`` per
    cell (regressors first), ``held (folds, cells)`` the cells each fold holds out."""
    cells, L, p = grams.shape[0], grams.shape[1], grams.shape[-1]
    test = (held @ grams.reshape(cells, -1)).reshape(-1, L, p, p)  # every fold at once
    train = grams.sum(0) - test
    k = p - 1
    coef = torch.linalg.lstsq(train[..., :k, :k], train[..., :k, k:], driver="gelsd").solution
    v = torch.cat([-coef, coef.new_ones(*coef.shape[:2], 1, 1)], -2)  # (folds, L, p, 1)
    ssr = (v.transpose(-1, -2) @ test @ v)[..., 0, 0].sum(0)  # (L,)
    return 1000.0 * (ssr.clamp_min(0.0) / max(n_rows, 1)).sqrt()  # m -> mm


def angle_error(J, split, j, r, weights):
    """``(e, w, theta, rows)`` of the rows where joint ``j`` moves the measured point
    (``J (n, 3)`` [m/rad], :func:`point_jacobian`): the angle error [rad] that best
    explains each row's position residual ``r (n, 3)`` [m], its weight ``|J_j|²``
    (times the robust row weight), the joint angle and the mask of those fit rows;
    None for too few such rows."""
    data = split.train
    e, w, rows = equivalent_angle_error(J, r, _MIN_LEVER)
    if int(rows.sum()) < _MIN_ROWS:
        return None
    w_rows = w[rows] if weights is None else w[rows] * weights[rows].to(w.dtype)
    return e[rows], w_rows, data.q[rows, j], rows

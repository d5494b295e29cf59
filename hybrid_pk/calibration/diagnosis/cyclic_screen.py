"""Which orders of a cyclic joint error to test: a periodogram of each joint's angle error.

Every order ``n`` of ``cyclic_error_<n>`` on every revolute joint is a candidate (some
two hundred on a six-axis arm). Scoring them all at every step would multiply the
Jacobian the search builds by ten. Instead, at every step of the search, the position
residual the current model leaves on each fit row is read as the angle error of each
joint that would explain it best (``e = J_j · r / |J_j|²``, rows where the joint moves
the point at all), and the weighted periodogram of ``e`` against that joint's angle
ranks the orders. The best :data:`SCREEN_KEEP` peaks per joint and the orders next
to each (a range of a few radians resolves the order only to a cycle or so, and the
proxy ``e`` may rank a neighbour first that the full fit does not) go on to that
step's score test; the others count in its Bonferroni level all the same (they were
looked at). Ranking anew at every step matters: before a large error (a misaligned
wrist axis) is explained, it leaks into every joint's ``e`` and hides a smaller
periodic error (the UR10's 17 cycles per turn of the shoulder pan are named at step 7
of the search; with one screen of the frames-only residual the search never tested
them).

After the search, the same periodogram of what the model leaves without a chosen
cyclic error tells whether a neighbouring order would do nearly as well (a joint range
of a few radians resolves the order only to a cycle or so): :func:`unresolved_orders`.
"""

from __future__ import annotations

from collections import defaultdict

import torch

from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.diagnosis.statistics import equivalent_angle_error
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.effects.joint import CYCLIC_PREFIX, MAX_CYCLIC_ORDER
from hybrid_pk.geometry import so3_log

__all__ = ["ORDER_SHARE", "SCREEN_KEEP", "screen_cyclic", "unresolved_orders"]

SCREEN_KEEP = 2  # peaks per joint whose orders (and the orders next to them) are scored
_STEP = 1e-6  # [rad] finite-difference step of the joint's point Jacobian
_MIN_LEVER = 0.2  # rows whose |J_j| is below this fraction of the median are left out
_MIN_ROWS = 8  # fewer informative rows than this: the joint's orders are not scored
NEIGHBOURS = 3  # orders on either side of a chosen one that are compared with it
ORDER_SHARE = 0.9  # a neighbour explaining this share of the chosen order's part is listed


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
        T0 = model(data.q, cond)
        r = data.position.to(T0.dtype) - T0[:, :3, 3]
        kept = set()
        for joint, ns in orders.items():
            got = _angle_error(model, split, names.index(joint), T0, r, weights)
            if got is None:
                continue  # the joint barely moves the point: no order to rank
            ranked = sorted(ns, key=lambda n: -_explained(*got, n))
            near = {m for n in ranked[:SCREEN_KEEP] for m in (n - 1, n, n + 1)}
            kept |= {f"{CYCLIC_PREFIX}{n}:{joint}" for n in ns if n in near}
    out = [c for c in pool if not c.startswith(CYCLIC_PREFIX) or c in kept]
    return out, len(pool) - len(out)


def unresolved_orders(
    model: ExtendedModel, split: Split, weights: torch.Tensor | None = None
) -> list[dict]:
    """Ambiguity entries for each chosen ``cyclic_error_<n>`` against the neighbouring
    orders (within :data:`NEIGHBOURS`) that explain at least :data:`ORDER_SHARE` of
    what order ``n`` explains of the angle error the model leaves without that cause.

    The angle error is read from the position residual (as the screen reads it) or, for
    full poses, from the rotation residual about the joint's axis, whichever the chosen
    order explains the larger share of: a wrist-3 error may barely move the measured
    point and be chosen for what it does to the orientation."""
    data, cond = split.train, split.cond_fit
    out = []
    for e in [x for x in model.effects if x.kind.startswith(CYCLIC_PREFIX)]:
        saved = e.value.detach().clone()
        with torch.no_grad():
            e.value.zero_()
            T0 = model(data.q, cond)
            r = data.position.to(T0.dtype) - T0[:, :3, 3]
            channels = {"position": _angle_error(model, split, e.joint_index, T0, r, weights)}
            if not split.position_only:
                R0 = T0[:, :3, :3]
                rot = so3_log(data.T_measured()[:, :3, :3].to(R0.dtype) @ R0.transpose(-1, -2))
                channels["orientation"] = _angle_error(
                    model, split, e.joint_index, T0, rot, weights, "orientation"
                )
            e.value.copy_(saved)
        shares = {k: _share(g, e.order) for k, g in channels.items() if g is not None}
        if not shares:
            continue
        channel = max(shares, key=shares.get)
        got = channels[channel]
        own = _explained(*got, e.order)
        lo, hi = max(2, e.order - NEIGHBOURS), min(MAX_CYCLIC_ORDER, e.order + NEIGHBOURS)
        for m in [m for m in range(lo, hi + 1) if m != e.order]:
            share = _explained(*got, m) / max(own, 1e-300)
            if share >= ORDER_SHARE:
                out.append(
                    {
                        "effects": [e.label, f"{CYCLIC_PREFIX}{m}:{e.joint}"],
                        "why": f"{m} cycles per turn explain {100 * share:.0f} % of what "
                        f"{e.order} explain of {e.joint}'s angle error (read from the "
                        f"{channel}): the order is not resolved by these rows",
                    }
                )
    return out


def _share(got, n: int) -> float:
    """Share of the weighted variance of the angle error that order ``n`` explains."""
    e, w, theta = got
    total = float((w * (e - (w * e).sum() / w.sum()) ** 2).sum())
    return _explained(e, w, theta, n) / max(total, 1e-300)


def _angle_error(model, split, j, T0, r, weights, reading: str = "position"):
    """``(e, w, theta)`` of the rows where joint ``j`` moves the measured pose: the angle
    error [rad] that best explains each row's residual ``r (n, 3)``, its weight
    ``|J_j|²`` (times the robust row weight) and the joint angle; None for too few such
    rows. ``T0``: the model's poses at the fit rows; ``reading``: ``position`` (``r`` the
    position residual [m], ``J_j`` the point's motion) or ``orientation`` (``r`` the
    rotation vector of ``R_meas R_modelᵀ``, ``J_j`` the joint's axis: a revolute joint
    turns the measured frame by its full angle on every row)."""
    data, cond = split.train, split.cond_fit
    dq = torch.zeros_like(data.q)
    dq[:, j] = _STEP
    T1 = model(data.q + dq, cond)
    if reading == "position":
        J = (T1[:, :3, 3] - T0[:, :3, 3]) / _STEP  # (n, 3) [m/rad]
    else:
        J = so3_log(T1[:, :3, :3] @ T0[:, :3, :3].transpose(-1, -2)) / _STEP
    e, w, rows = equivalent_angle_error(J, r, _MIN_LEVER)
    if int(rows.sum()) < _MIN_ROWS:
        return None
    w_rows = w[rows] if weights is None else w[rows] * weights[rows].to(w.dtype)
    return e[rows], w_rows, data.q[rows, j]


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

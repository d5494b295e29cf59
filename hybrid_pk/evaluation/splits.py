"""Hold-out splits: at random, or a whole *region* of the workspace held out.

A random hold-out measures interpolation: every held-out pose has fitted neighbours.
What matters for a calibrated model is accuracy where it saw no data, so the
generalisation test holds out a contiguous block of the workspace:

- :func:`region_split` cuts the workspace with a plane: the rows beyond it (the
  ``holdout`` fraction with the largest, or smallest, coordinate along ``axis``) are
  held out. Positions are the nominal flange positions in the robot root frame
  (``fk(q)``; x forward, z up for the shipped robots), so the rule does not depend
  on where the tracker stood and works for several files measured with different
  tracker set-ups. ``axis="radial"`` cuts with a cylinder about the root z axis
  instead (hold out the far reach, or the near one with ``side="low"``).
  Without a robot the measured positions are used (one file, one tracker frame).
- :func:`joint_box_split` holds out a box in joint space: the rows whose chosen
  joints all lie in their upper (or lower, or central) range, sized so that about
  ``holdout`` of the rows fall inside. This is what a residual network restricted to
  its training joint range must survive.

Every split returns sorted row indices and the rule in words (for reports).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.errors import DataError

__all__ = ["Split", "joint_box_split", "random_split", "region_split"]

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


class Split(NamedTuple):
    """Fit and hold-out rows.

    Attributes:
        fit: ``(N_fit,)`` sorted row indices (long).
        holdout: ``(N_holdout,)`` sorted row indices (long).
        rule: how the hold-out was chosen, in words.
    """

    fit: Tensor
    holdout: Tensor
    rule: str

    def apply(self, data: MeasuredData) -> tuple[MeasuredData, MeasuredData]:
        """``(fit rows, hold-out rows)`` of ``data``."""
        return data.subset(self.fit), data.subset(self.holdout)


def _check_fraction(holdout: float, n: int) -> int:
    if not 0 < holdout < 1:
        raise ValueError(f"holdout must be a fraction in (0, 1), got {holdout}")
    k = round(holdout * n)
    if k < 1 or k > n - 1:
        raise DataError(f"a hold-out fraction of {holdout} of {n} rows leaves one side empty")
    return k


def _split(mask: np.ndarray, rule: str) -> Split:
    idx = np.arange(len(mask))
    return Split(torch.as_tensor(idx[~mask]), torch.as_tensor(idx[mask]), rule)


def random_split(data: MeasuredData | int, holdout: float = 0.2, seed: int = 0) -> Split:
    """``round(holdout · N)`` rows drawn at random (seeded) are held out."""
    n = data if isinstance(data, int) else data.n
    k = _check_fraction(holdout, n)
    gen = torch.Generator().manual_seed(int(seed))
    mask = np.zeros(n, bool)
    mask[torch.randperm(n, generator=gen)[:k].numpy()] = True
    return _split(mask, f"random {k} of {n} rows (seed {seed})")


def _positions(data: MeasuredData, robot: Any) -> tuple[np.ndarray, str]:
    if robot is None:
        if len(data.sources) > 1 and int(data.file_index.max()) > 0:
            raise DataError(
                "a region split of several files needs the robot: their measured positions "
                "are in different tracker frames; pass robot= to cut in the robot root frame"
            )
        return data.position.numpy(), "measured positions (measurement frame)"
    with torch.no_grad():
        T = robot.fk(data.q.to(robot.dtype))
    return T[:, :3, 3].double().numpy(), "nominal flange positions (robot root frame)"


def region_split(
    data: MeasuredData,
    robot: Any = None,
    *,
    holdout: float = 0.2,
    axis: str | Sequence[float] = "auto",
    side: str = "high",
) -> Split:
    """Hold out the rows beyond a plane (or a cylinder): a contiguous workspace block.

    Args:
        data: measured rows.
        robot: nominal robot; positions are then ``fk(q)`` in its root frame [m].
            None: measured positions (single-file data only).
        holdout: fraction of rows held out.
        axis: ``"x"``, ``"y"``, ``"z"``, a direction ``(3,)``, ``"auto"`` (the direction
            of largest spread of the positions, sign made positive on its largest
            component) or ``"radial"`` (horizontal distance from the root z axis;
            needs ``robot``).
        side: ``"high"`` holds out the largest coordinates, ``"low"`` the smallest.

    Returns:
        The split; ``rule`` names the plane: ``s = u · p >= threshold``.
    """
    if side not in ("high", "low"):
        raise ValueError(f"side must be 'high' or 'low', got {side!r}")
    k = _check_fraction(holdout, data.n)
    p, where = _positions(data, robot)
    if isinstance(axis, str) and axis == "radial":
        if robot is None:
            raise DataError("axis='radial' needs the robot (distance from its root z axis)")
        s = np.hypot(p[:, 0], p[:, 1])
        what = "horizontal distance from the root z axis"
    else:
        if isinstance(axis, str) and axis == "auto":
            centred = p - p.mean(0)
            u = np.linalg.svd(centred, full_matrices=False)[2][0]
            u = u * np.sign(u[np.argmax(np.abs(u))])
        elif isinstance(axis, str):
            if axis not in _AXES:
                raise ValueError(f"axis must be x, y, z, auto, radial or a vector, got {axis!r}")
            u = np.array(_AXES[axis])
        else:
            u = np.asarray(axis, dtype=np.float64)
            if u.shape != (3,) or not np.linalg.norm(u) > 0:
                raise ValueError(f"axis vector must be a non-zero (3,), got {u}")
            u = u / np.linalg.norm(u)
        s = p @ u
        what = f"u · p with u = ({u[0]:.3f}, {u[1]:.3f}, {u[2]:.3f})"
    order = np.argsort(s, kind="stable")
    chosen = order[-k:] if side == "high" else order[:k]
    mask = np.zeros(data.n, bool)
    mask[chosen] = True
    threshold = float(s[chosen].min() if side == "high" else s[chosen].max())
    # Rows tied with the threshold go with the hold-out so the cut is a clean plane.
    mask |= (s >= threshold) if side == "high" else (s <= threshold)
    op = ">=" if side == "high" else "<="
    rule = (
        f"region: {int(mask.sum())} of {data.n} rows with {what} {op} {threshold:.4f} m ({where})"
    )
    return _split(mask, rule)


def joint_box_split(
    data: MeasuredData,
    *,
    box: Mapping[str, tuple[float, float]] | None = None,
    joints: Sequence[str] | None = None,
    holdout: float = 0.2,
    corner: str = "high",
) -> Split:
    """Hold out the rows inside a joint-space box.

    Args:
        data: measured rows.
        box: explicit ``{joint: (lo, hi)}`` [rad, m]; rows with every named joint in
            its interval are held out. Overrides ``joints``/``holdout``/``corner``.
        joints: joints that span the box (default: the first three, which place the
            wrist).
        holdout: target fraction inside the box (the nearest reachable with the data's
            joint values; at least this fraction).
        corner: ``"high"`` (upper part of each joint's range), ``"low"`` or ``"centre"``.
    """
    names = list(data.joint_names)
    q = data.q.numpy()
    if box is not None:
        unknown = [j for j in box if j not in names]
        if unknown:
            raise DataError(f"unknown joint(s) {unknown} in the box; joints: {', '.join(names)}")
        inside = np.ones(data.n, bool)
        for j, (lo, hi) in box.items():
            inside &= (q[:, names.index(j)] >= lo) & (q[:, names.index(j)] <= hi)
        if not inside.any() or inside.all():
            raise DataError(f"the box {dict(box)} holds {int(inside.sum())} of {data.n} rows")
        text = ", ".join(f"{j} in [{lo:.4f}, {hi:.4f}]" for j, (lo, hi) in box.items())
        return _split(inside, f"joint box: {int(inside.sum())} of {data.n} rows with {text} rad")
    if corner not in ("high", "low", "centre"):
        raise ValueError(f"corner must be 'high', 'low' or 'centre', got {corner!r}")
    joints = list(joints) if joints is not None else names[:3]
    unknown = [j for j in joints if j not in names]
    if unknown:
        raise DataError(f"unknown joint(s) {unknown}; joints: {', '.join(names)}")
    _check_fraction(holdout, data.n)
    cols = q[:, [names.index(j) for j in joints]]

    def bounds(level: float) -> tuple[np.ndarray, np.ndarray]:
        if corner == "high":
            return np.quantile(cols, 1 - level, axis=0), cols.max(0)
        if corner == "low":
            return cols.min(0), np.quantile(cols, level, axis=0)
        return np.quantile(cols, 0.5 - level / 2, axis=0), np.quantile(
            cols, 0.5 + level / 2, axis=0
        )

    def fraction(level: float) -> float:
        lo, hi = bounds(level)
        return float(((cols >= lo) & (cols <= hi)).all(-1).mean())

    a, b = 0.0, 1.0  # the fraction inside grows with the level: bisect for holdout
    for _ in range(50):
        mid = (a + b) / 2
        a, b = (mid, b) if fraction(mid) < holdout else (a, mid)
    lo, hi = bounds(b)
    inside = ((cols >= lo) & (cols <= hi)).all(-1)
    if inside.all():
        raise DataError("the joint values do not spread enough to hold out a box")
    text = ", ".join(f"{j} in [{lo[i]:.4f}, {hi[i]:.4f}]" for i, j in enumerate(joints))
    return _split(
        inside, f"joint box ({corner}): {int(inside.sum())} of {data.n} rows with {text} rad"
    )

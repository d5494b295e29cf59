"""Stream samples: checked arrays and time stamps, tracker poses between samples.

Positions are interpolated linearly, orientations by SLERP along the shorter arc; a
query between two tracker samples further apart than a gap limit (a beam break) is
invalid rather than bridged.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from hybrid_pk.errors import DataError

__all__ = ["GAP_FACTOR", "checked_array", "interpolate_poses", "slerp", "stream_times"]

GAP_FACTOR = 5.0  # a tracker gap longer than this many median periods is a beam break


def checked_array(x: Any, name: str, shape_tail: tuple[int, ...] = ()) -> np.ndarray:
    """``x`` as a float64 array ``(N, *shape_tail)`` of finite values, or a DataError
    naming ``name`` (and the first row that is not finite)."""
    a = np.array(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float64)
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        want = "(N" + "".join(f", {d}" for d in shape_tail) + ")"
        raise DataError(f"{name}: expected shape {want}, found {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a).reshape(len(a), -1).all(-1))
    if bad.size:
        raise DataError(f"{name}: value is not finite", row=int(bad[0]) + 1, column=name)
    return a


def stream_times(t: Any, name: str) -> np.ndarray:
    """Time stamps [s] of a stream: at least 3, strictly increasing."""
    t = checked_array(t, name)
    if len(t) < 3:
        raise DataError(f"{name}: a stream needs at least 3 samples, found {len(t)}")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise DataError(
            f"{name}: time stamps must increase; {t[k - 1]:.9g} s then {t[k]:.9g} s",
            row=k + 1,
            column=name,
        )
    return t


def interpolate_poses(
    tracker_t: np.ndarray,
    position: np.ndarray,
    quat: np.ndarray | None,
    times: np.ndarray,
    max_gap: float | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Tracker poses at ``times`` [s, tracker clock]: positions linear, orientations SLERP.

    Args:
        tracker_t: ``(M,)`` increasing tracker times [s].
        position: ``(M, 3)`` [m].
        quat: ``(M, 4)`` ``(w, x, y, z)`` or None.
        times: ``(K,)`` query times [s].
        max_gap: [s] a query between samples further apart than this is invalid;
            default :data:`GAP_FACTOR` median periods.

    Returns:
        ``(position (K, 3), quat (K, 4) | None, valid (K,) bool)``; invalid rows hold NaN.
    """
    if max_gap is None:
        max_gap = GAP_FACTOR * float(np.median(np.diff(tracker_t)))
    k = np.searchsorted(tracker_t, times, side="right")
    inside = (times >= tracker_t[0]) & (times <= tracker_t[-1])
    hi = np.clip(k, 1, len(tracker_t) - 1)
    gap = tracker_t[hi] - tracker_t[hi - 1]
    valid = inside & (gap <= max_gap)
    # from the two samples around each query: np.interp on a column would copy the
    # whole stream (millions of rows) at every call
    lo, up = hi[valid] - 1, hi[valid]
    u = (times[valid] - tracker_t[lo]) / (tracker_t[up] - tracker_t[lo])
    pos = np.full((len(times), 3), np.nan)
    pos[valid] = position[lo] + u[:, None] * (position[up] - position[lo])
    out_q = None
    if quat is not None:
        out_q = np.full((len(times), 4), np.nan)
        out_q[valid] = slerp(quat[lo], quat[up], u)
    return pos, out_q, valid


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions ``(K, 4)`` at fractions ``u (K,)``,
    along the shorter arc; ``w >= 0`` on output."""
    dot = (q0 * q1).sum(-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    small = theta < 1e-8
    sin = np.where(small, 1.0, np.sin(theta))
    a = np.where(small, 1 - u, np.sin((1 - u) * theta) / sin)
    b = np.where(small, u, np.sin(u * theta) / sin)
    out = a[:, None] * q0 + b[:, None] * q1
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return out * np.where(out[:, :1] < 0, -1.0, 1.0)

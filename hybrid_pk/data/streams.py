"""Dynamic campaigns (Ojer et al. 2024, section 4.3): two clocks, one table.

A dynamic campaign records a joint stream from the robot controller (≈110 Hz, robot
clock) and a pose stream from the laser tracker (≈3 kHz, tracker clock) while the
robot moves slowly. The clocks differ by an unknown constant offset::

    tracker time = robot time + offset      [s]

so the tracker sample of robot row ``k`` is the one at ``t_k + offset``.

1. :func:`estimate_time_offset` finds ``offset`` in two stages:

   - coarse: cross-correlation of speed profiles: the speed of the measured point
     ``|dp/dt|`` (tracker) against the speed of the nominal model's flange
     ``|d fk(q)/dt|`` (robot). Speeds do not depend on the unknown tracker frame,
     so no registration is needed; both are filtered identically (box filter then
     central difference over ``smooth`` seconds) so filtering adds no lag.
   - refine: a bounded 1-D search (Brent) of the offset that minimises the RMS
     position residual of the frame registration on the tracker data interpolated at
     ``t_k + offset``: closed-form guess
     (:func:`~hybrid_pk.geometry.registration.register_frames`), then Gauss-Newton
     on base frame and tool point, so the residual is the least-squares value. A wrong
     offset turns the motion into a position error of ``speed x offset error``, which
     no pair of frames can absorb. The coarse stage is repeated once with the tool
     point of a registration at the first estimate, whose speed has the tracker's
     shape; the search window covers the two coarse estimates' disagreement.

2. :func:`synchronise` interpolates the tracker stream at the robot times: positions
   linearly, orientations by SLERP (at 3 kHz the tracker moves ~0.1 mm between
   samples). Robot rows outside the tracker's span or inside a tracker gap (beam
   break) are left out and reported. The result keeps ``t`` (robot clock).

The offset is a constant: a clock rate difference (drift) of the two devices is not
modelled; over long campaigns estimate the offset per segment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.errors import DataError
from hybrid_pk.geometry.registration import register_frames

__all__ = [
    "OffsetEstimate",
    "SyncResult",
    "estimate_time_offset",
    "interpolate_poses",
    "speed_profile",
    "synchronise",
]

GRID_DT = 1e-3  # [s] resampling step of the speed profiles
SMOOTH_S = 0.02  # [s] box filter and difference span of the speed profiles
REFINE_POINTS = 1500  # robot rows used by the registration refinement (evenly spaced)
GAP_FACTOR = 5.0  # a tracker gap longer than this many median periods is a beam break


def _f64(x: Any, name: str, shape_tail: tuple[int, ...] = ()) -> np.ndarray:
    a = np.array(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float64)
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        want = "(N" + "".join(f", {d}" for d in shape_tail) + ")"
        raise DataError(f"{name}: expected shape {want}, found {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a).reshape(len(a), -1).all(-1))
    if bad.size:
        raise DataError(f"{name}: value is not finite", row=int(bad[0]) + 1, column=name)
    return a


def _times(t: Any, name: str) -> np.ndarray:
    t = _f64(t, name)
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


def speed_profile(t: np.ndarray, p: np.ndarray, grid: np.ndarray, smooth: float) -> np.ndarray:
    """Speed ``|dp/dt|`` [m/s] of points ``p (M, 3)`` [m] at times ``t (M,)`` [s], on ``grid``.

    Positions are interpolated linearly onto ``grid`` (uniform step), box-filtered over
    ``smooth`` seconds and differenced over ``smooth`` seconds. Applied identically to
    both streams, the filter shifts neither. Where the filter would reach past the
    ends of ``grid`` the speed is NaN.
    """
    dt = float(grid[1] - grid[0])
    half = max(round(smooth / dt / 2), 1)
    width = 2 * half + 1  # odd: the filtered value sits on a grid point
    v = np.full(len(grid), np.nan)
    if len(grid) <= 2 * width:
        return v
    g = np.stack([np.interp(grid, t, p[:, k]) for k in range(3)], -1)
    c = np.concatenate([np.zeros((1, 3)), np.cumsum(g, 0)])
    box = (c[width:] - c[:-width]) / width  # box[i] = mean of g[i : i + width]
    speed = np.linalg.norm(box[2 * half :] - box[: -2 * half], axis=-1) / (2 * half * dt)
    v[2 * half : 2 * half + len(speed)] = speed  # speed[0] is centred on grid index 2 half
    return v


@dataclass(frozen=True)
class OffsetEstimate:
    """Result of :func:`estimate_time_offset`.

    Attributes:
        offset: [s] tracker time = robot time + offset.
        coarse: [s] the speed-profile cross-correlation estimate.
        correlation: peak normalised correlation of the speed profiles (1 = same shape).
        residual_mm: RMS position residual [mm] of the registration at ``offset``.
        coarse_residual_mm: the same at ``coarse``.
        bounds: [s] interval of the refinement search.
        n_rows: robot rows used by the refinement.
    """

    offset: float
    coarse: float
    correlation: float
    residual_mm: float
    coarse_residual_mm: float
    bounds: tuple[float, float]
    n_rows: int

    def summary(self) -> str:
        """One line for humans."""
        return (
            f"time offset {1e3 * self.offset:.3f} ms (tracker = robot + offset): speed "
            f"correlation {self.correlation:.3f} at {1e3 * self.coarse:.1f} ms, registration "
            f"residual {self.coarse_residual_mm:.3f} -> {self.residual_mm:.3f} mm RMS "
            f"({self.n_rows} rows)"
        )


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    # Elementwise sums, not BLAS dot products: called hundreds of times on small
    # vectors, where a threaded BLAS on a busy machine costs more than the arithmetic.
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / den if den > 0 else 0.0


def _best_lag(
    grid: np.ndarray,
    v_robot: np.ndarray,
    t_tr: np.ndarray,
    v_tr: np.ndarray,
    lags: np.ndarray,
    min_overlap: int,
) -> tuple[float, float]:
    """Lag of the largest correlation of ``v_robot(t)`` and ``v_tr(t + lag)``, refined by a
    parabola through the peak and its neighbours."""
    scores = np.full(len(lags), -np.inf)
    ok_r = np.isfinite(v_robot)
    ok_tr = np.isfinite(v_tr)
    for i, lag in enumerate(lags):
        inside = ok_r & (grid + lag >= t_tr[0]) & (grid + lag <= t_tr[-1])
        other = np.interp(grid[inside] + lag, t_tr, np.where(ok_tr, v_tr, np.nan))
        keep = np.isfinite(other)
        if keep.sum() < min_overlap:
            continue
        scores[i] = _correlation(v_robot[inside][keep], other[keep])
    if not np.isfinite(scores).any():
        raise DataError(
            "the robot and tracker streams do not overlap in time for any offset searched; "
            "check both time columns and max_offset"
        )
    i = int(np.argmax(scores))
    lag = float(lags[i])
    if 0 < i < len(lags) - 1 and np.isfinite(scores[i - 1]) and np.isfinite(scores[i + 1]):
        den = scores[i - 1] - 2 * scores[i] + scores[i + 1]
        if den < 0:
            lag += 0.5 * (scores[i - 1] - scores[i + 1]) / den * float(lags[1] - lags[0])
    return lag, float(scores[i])


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
    pos = np.full((len(times), 3), np.nan)
    pos[valid] = np.stack(
        [np.interp(times[valid], tracker_t, position[:, c]) for c in range(3)], -1
    )
    out_q = None
    if quat is not None:
        out_q = np.full((len(times), 4), np.nan)
        lo = hi[valid] - 1
        u = (times[valid] - tracker_t[lo]) / (tracker_t[hi[valid]] - tracker_t[lo])
        out_q[valid] = _slerp(quat[lo], quat[hi[valid]], u)
    return pos, out_q, valid


def _slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
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


def _rotations(quat: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    """``(K, 4)`` ``(w, x, y, z)`` -> ``(K, 3, 3)`` rotation matrices."""
    return torch.as_tensor(Rotation.from_quat(quat[:, [1, 2, 3, 0]]).as_matrix(), dtype=dtype)


class _PointFrames:
    """Least-squares base frame and tool point from positions: ``p ≈ R_B (R_F p_X + p_F) + p_B``.

    Gauss-Newton from a closed-form registration, warm-started at each call so the
    residual is the converged least-squares value (a smooth function of the offset).
    """

    def __init__(self, T_end: torch.Tensor, guess: tuple[torch.Tensor, torch.Tensor]) -> None:
        T = T_end.double().numpy()
        self.R_F, self.p_F = T[:, :3, :3], T[:, :3, 3]
        base, tool = (g.double().numpy() for g in guess)
        self.R_B, self.p_B = base[:3, :3], base[:3, 3]
        self.p_X = tool[:3, 3]

    def rms_mm(self, p: np.ndarray, iterations: int = 8) -> float:
        R_B, p_B, p_X = self.R_B.copy(), self.p_B.copy(), self.p_X.copy()
        k = len(p)
        for _ in range(iterations):
            a = np.einsum("kij,j->ki", self.R_F, p_X) + self.p_F
            b = a @ R_B.T
            r = b + p_B - p
            J = np.zeros((k, 3, 9))
            J[:, 0, 1], J[:, 0, 2] = b[:, 2], -b[:, 1]  # -[b]x: d(R_B a) for R_B <- exp(w) R_B
            J[:, 1, 0], J[:, 1, 2] = -b[:, 2], b[:, 0]
            J[:, 2, 0], J[:, 2, 1] = b[:, 1], -b[:, 0]
            J[:, :, 3:6] = np.eye(3)
            J[:, :, 6:9] = R_B @ self.R_F
            Jf, rf = J.reshape(-1, 9), r.reshape(-1)
            step = -np.linalg.solve(Jf.T @ Jf, Jf.T @ rf)
            w = step[:3]
            angle = float(np.linalg.norm(w))
            if angle > 0:
                K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / angle
                R_B = (np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K) @ R_B
            p_B, p_X = p_B + step[3:6], p_X + step[6:9]
            if float(np.abs(step).max()) < 1e-12:
                break
        a = np.einsum("kij,j->ki", self.R_F, p_X) + self.p_F
        r = a @ R_B.T + p_B - p
        return 1e3 * math.sqrt(float((r * r).sum(-1).mean()))


def estimate_time_offset(
    robot_t: Any,
    q: Any,
    tracker_t: Any,
    position: Any,
    robot: Any,
    *,
    quat: Any = None,
    max_offset: float = 1.0,
    refine_window: float = 0.02,
    smooth: float = SMOOTH_S,
    grid_dt: float = GRID_DT,
    refine_points: int = REFINE_POINTS,
) -> OffsetEstimate:
    """Offset between a robot joint stream and a tracker stream (module docstring).

    Args:
        robot_t: ``(N,)`` robot time stamps [s], increasing.
        q: ``(N, dof)`` joint values [rad, m for prismatic].
        tracker_t: ``(M,)`` tracker time stamps [s], increasing.
        position: ``(M, 3)`` measured points in the tracker frame [m].
        robot: nominal :class:`~hybrid_pk.Robot` (anything with ``fk`` and ``dtype``).
        quat: ``(M, 4)`` measured orientations ``(w, x, y, z)``, or None.
        max_offset: [s] largest |offset| searched by the cross-correlation.
        refine_window: [s] half-width of the refinement search around the coarse value.
        smooth: [s] filter span of the speed profiles.
        grid_dt: [s] resampling step of the speed profiles.
        refine_points: robot rows used by the refinement (evenly spaced).

    Returns:
        The estimate; ``offset`` is the refined value.

    Raises:
        DataError: bad shapes or times, streams that never overlap, a robot that does
            not move (no speed to correlate), too few rows overlapping the tracker span.
    """
    t_r = _times(robot_t, "robot t")
    t_m = _times(tracker_t, "tracker t")
    q = _f64(q, "q", (np.asarray(q).shape[-1],))
    if len(q) != len(t_r):
        raise DataError(f"q has {len(q)} rows but robot t has {len(t_r)}")
    pos = _f64(position, "position", (3,))
    if len(pos) != len(t_m):
        raise DataError(f"position has {len(pos)} rows but tracker t has {len(t_m)}")
    quat_np = None if quat is None else _f64(quat, "quat", (4,))
    if quat_np is not None and len(quat_np) != len(t_m):
        raise DataError(f"quat has {len(quat_np)} rows but tracker t has {len(t_m)}")

    # Coarse 1: flange speed (the tool offset is not known yet) against point speed.
    grid_r = np.arange(t_r[0], t_r[-1], grid_dt)
    grid_m = np.arange(t_m[0], t_m[-1], grid_dt)
    v_m = speed_profile(t_m, pos, grid_m, smooth)
    with torch.no_grad():
        T_all = robot.fk(torch.as_tensor(q, dtype=robot.dtype)).double()
    v_r = speed_profile(t_r, T_all[:, :3, 3].numpy(), grid_r, smooth)
    if not np.isfinite(v_r).any() or float(np.nanstd(v_r)) < 1e-6:
        raise DataError("the robot stream does not move: no speed profile to correlate")
    min_overlap = max(int(0.25 * len(grid_r)), 10)
    step = max(5 * grid_dt, smooth / 4)

    def correlate(v_robot: np.ndarray, centre: float, half_width: float) -> tuple[float, float]:
        lags = np.arange(centre - half_width, centre + half_width + step / 2, step)
        lag, _ = _best_lag(grid_r, v_robot, grid_m, v_m, lags, min_overlap)
        fine = np.arange(lag - 2 * step, lag + 2 * step + grid_dt / 2, grid_dt)
        return _best_lag(grid_r, v_robot, grid_m, v_m, fine, min_overlap)

    lag0, _ = correlate(v_r, 0.0, max_offset)
    max_gap = GAP_FACTOR * float(np.median(np.diff(t_m)))

    def rows_near(centre: float, half_width: float) -> np.ndarray:
        """Robot rows whose tracker time stays inside the stream and away from gaps for
        every offset in ``centre ± half_width`` (a fixed set: the cost does not jump)."""
        lo, hi = centre - half_width, centre + half_width
        usable = np.flatnonzero((t_r + lo >= t_m[0]) & (t_r + hi <= t_m[-1]))
        gaps = np.flatnonzero(np.diff(t_m) > max_gap)
        if gaps.size and usable.size:
            g0, g1 = t_m[gaps], t_m[gaps + 1]
            first = np.clip(np.searchsorted(g1, t_r[usable] + lo, side="right"), 0, gaps.size - 1)
            touches = (g0[first] < t_r[usable] + hi) & (g1[first] > t_r[usable] + lo)
            usable = usable[~touches]
        if len(usable) < 10:
            raise DataError(
                f"only {len(usable)} robot rows overlap the tracker stream (away from gaps) "
                f"near offset {centre:.4f} s; need at least 10"
            )
        count = min(refine_points, len(usable))
        return usable[np.unique(np.linspace(0, len(usable) - 1, count).round().astype(int))]

    def cost(offset: float, pick: np.ndarray, frames: _PointFrames) -> float:
        p, _, _ = interpolate_poses(t_m, pos, None, t_r[pick] + offset, max_gap)
        return frames.rms_mm(p)

    def registered(offset: float, pick: np.ndarray) -> _PointFrames:
        p, qq, _ = interpolate_poses(t_m, pos, quat_np, t_r[pick] + offset, max_gap)
        R = None if qq is None else _rotations(qq, T_all.dtype)
        return _PointFrames(T_all[pick], register_frames(T_all[pick], torch.as_tensor(p), R))

    # Coarse 2: with the tool offset of a registration at lag0, the model's point speed
    # has the tracker's shape, so the correlation peak is no longer biased.
    pick = rows_near(lag0, 0.0)
    frames = registered(lag0, pick)
    tool = torch.eye(4, dtype=T_all.dtype)
    tool[:3, 3] = torch.as_tensor(frames.p_X)
    v_point = speed_profile(t_r, (T_all @ tool)[:, :3, 3].numpy(), grid_r, smooth)
    coarse, corr = correlate(v_point, lag0, min(max_offset, 10 * refine_window))

    # Refine: bounded search of the registration residual; the window covers the
    # disagreement of the two coarse stages and is re-centred if the minimum is on a bound.
    half_width = max(refine_window, 1.5 * abs(coarse - lag0))
    centre = coarse
    for _ in range(5):
        lo, hi = centre - half_width, centre + half_width
        pick = rows_near(centre, half_width)
        frames = registered(centre, pick)
        res = minimize_scalar(
            cost, bounds=(lo, hi), args=(pick, frames), method="bounded", options={"xatol": 1e-6}
        )
        if min(res.x - lo, hi - res.x) > 0.05 * half_width:
            break
        centre = float(res.x)
    return OffsetEstimate(
        offset=float(res.x),
        coarse=float(coarse),
        correlation=corr,
        residual_mm=float(res.fun),
        coarse_residual_mm=cost(coarse, pick, frames),
        bounds=(float(lo), float(hi)),
        n_rows=len(pick),
    )


@dataclass(frozen=True)
class SyncResult:
    """Result of :func:`synchronise`.

    Attributes:
        data: one row per kept robot sample; ``t`` on the robot clock.
        outside: 1-based robot rows left out: their tracker time is outside the
            tracker stream.
        in_gap: 1-based robot rows left out: their tracker time falls in a gap.
        offset: [s] the offset used.
    """

    data: MeasuredData
    outside: tuple[int, ...]
    in_gap: tuple[int, ...]
    offset: float

    def summary(self) -> str:
        """Short human summary."""
        line = f"synchronised {self.data.n} rows at offset {1e3 * self.offset:.3f} ms"
        for rows, why in ((self.outside, "outside the tracker stream"), (self.in_gap, "in gaps")):
            if rows:
                shown = ", ".join(map(str, rows[:10])) + (" ..." if len(rows) > 10 else "")
                line += f"; left out {len(rows)} robot row(s) {why}: {shown}"
        return line


def synchronise(
    robot_t: Any,
    q: Any,
    tracker_t: Any,
    position: Any,
    offset: float,
    *,
    joint_names: tuple[str, ...] | list[str],
    quat: Any = None,
    temperature: Any = None,
    tracker_temperature: Any = None,
    max_gap: float | None = None,
    source: str = "<streams>",
    robot_rows: Any = None,
) -> SyncResult:
    """Tracker stream interpolated at the robot times: a measured pose table.

    Args:
        robot_t: ``(N,)`` robot times [s]; kept as ``t``.
        q: ``(N, dof)`` joint values [rad, m].
        tracker_t: ``(M,)`` tracker times [s].
        position: ``(M, 3)`` [m].
        offset: [s] tracker time = robot time + offset.
        joint_names: the ``dof`` joint names.
        quat: ``(M, 4)`` ``(w, x, y, z)`` or None.
        temperature: ``(N,)`` [°C] per robot sample, or None.
        tracker_temperature: ``(M,)`` [°C] per tracker sample (interpolated), or None.
        max_gap: [s] tracker gap that invalidates a row; default 5 median periods.
        source: name recorded in ``MeasuredData.sources``.
        robot_rows: ``(N,)`` 1-based rows of the robot stream file (default 1..N).
    """
    t_r = _times(robot_t, "robot t")
    t_m = _times(tracker_t, "tracker t")
    q = _f64(q, "q", (np.asarray(q).shape[-1],))
    pos = _f64(position, "position", (3,))
    quat_np = None if quat is None else _f64(quat, "quat", (4,))
    if len(q) != len(t_r) or len(pos) != len(t_m):
        raise DataError("q must have one row per robot time and position one per tracker time")
    rows = np.arange(1, len(t_r) + 1) if robot_rows is None else np.asarray(robot_rows)
    query = t_r + float(offset)
    p, qq, valid = interpolate_poses(t_m, pos, quat_np, query, max_gap)
    inside = (query >= t_m[0]) & (query <= t_m[-1])
    temp = None
    if tracker_temperature is not None:
        temp = np.interp(query, t_m, _f64(tracker_temperature, "tracker temperature"))
    elif temperature is not None:
        temp = _f64(temperature, "temperature")
    if not valid.any():
        raise DataError(
            f"no robot sample falls inside the tracker stream at offset {offset:.6g} s "
            f"(robot {t_r[0]:.6g}..{t_r[-1]:.6g} s, tracker {t_m[0]:.6g}..{t_m[-1]:.6g} s)"
        )
    data = MeasuredData(
        q=q[valid],
        position=p[valid],
        quat=None if qq is None else qq[valid],
        joint_names=tuple(joint_names),
        file_index=np.zeros(int(valid.sum()), dtype=np.int64),
        rows=rows[valid],
        sources=(source,),
        t=t_r[valid],
        temperature=None if temp is None else temp[valid],
    )
    return SyncResult(
        data,
        tuple(int(r) for r in rows[~inside]),
        tuple(int(r) for r in rows[inside & ~valid]),
        float(offset),
    )

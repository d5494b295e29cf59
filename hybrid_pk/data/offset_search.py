"""The two streams of :func:`~hybrid_pk.data.time_offset.estimate_time_offset` on
common ground: speed profiles on uniform grids, their cross-correlation, the robot rows
usable near an offset, and the registration residual as a function of the offset.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation, RotationSpline

from hybrid_pk.data.clock_jump import find_clock_jumps, noise_rms
from hybrid_pk.data.interpolation import GAP_FACTOR, interpolate_poses
from hybrid_pk.data.point_frames import PointFrames
from hybrid_pk.errors import DataError
from hybrid_pk.geometry.registration import register_frames

__all__ = ["SCAN_POINTS", "OffsetSearch", "evenly", "speed_profile"]

# Robot rows per offset of the residual scan: 900 equations for 9 unknowns; an offset in
# another basin leaves a residual of mm (speed x error) against µm of noise, so a fifth
# of the refinement's rows tells the basins apart at a fifth of its cost per fit.
SCAN_POINTS = 300
# Alternations of the closed-form registration that starts the second fit at each lag: a
# start for Gauss-Newton in the right basin, not the answer (its default 20 made the scan
# of a 12 s stream 5x slower).
COLD_ITERATIONS = 3


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
            "the robot and tracker streams do not overlap in time for any offset searched: "
            f"robot t {grid[0]:.6g}..{grid[-1]:.6g} s, tracker t {t_tr[0]:.6g}.."
            f"{t_tr[-1]:.6g} s, offsets {lags[0]:.6g}..{lags[-1]:.6g} s (tracker = robot "
            "+ offset); check both time columns (units: a ms column read as s) and max_offset"
        )
    i = int(np.argmax(scores))
    lag = float(lags[i])
    if 0 < i < len(lags) - 1 and np.isfinite(scores[i - 1]) and np.isfinite(scores[i + 1]):
        den = scores[i - 1] - 2 * scores[i] + scores[i + 1]
        if den < 0:
            lag += 0.5 * (scores[i - 1] - scores[i + 1]) / den * float(lags[1] - lags[0])
    return lag, float(scores[i])


def _rotations(quat: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
    """``(K, 4)`` ``(w, x, y, z)`` -> ``(K, 3, 3)`` rotation matrices."""
    return torch.as_tensor(Rotation.from_quat(quat[:, [1, 2, 3, 0]]).as_matrix(), dtype=dtype)


class OffsetSearch:
    """Both streams on common ground: speed profiles on uniform grids, the robot rows
    usable near an offset, and the registration residual as a function of the offset."""

    def __init__(
        self,
        t_r: np.ndarray,
        T_all: torch.Tensor,
        t_m: np.ndarray,
        pos: np.ndarray,
        quat: np.ndarray | None,
        *,
        smooth: float,
        grid_dt: float,
        refine_points: int,
    ) -> None:
        self.t_r, self.T_all, self.t_m, self.pos, self.quat = t_r, T_all, t_m, pos, quat
        self.smooth, self.grid_dt, self.refine_points = smooth, grid_dt, refine_points
        self.grid_r = np.arange(t_r[0], t_r[-1], grid_dt)
        self.grid_m = np.arange(t_m[0], t_m[-1], grid_dt)
        self.v_m = speed_profile(t_m, pos, self.grid_m, smooth)
        self.min_overlap = max(int(0.25 * len(self.grid_r)), 10)
        self.step = max(5 * grid_dt, smooth / 4)
        self.max_gap = GAP_FACTOR * float(np.median(np.diff(t_m)))
        self.gaps = np.flatnonzero(np.diff(t_m) > self.max_gap)  # tracker rows before a gap
        self._splines = None  # of the flange poses over robot time (flange_at)
        step = np.diff(t_r)
        self.robot_gaps = np.flatnonzero(step > GAP_FACTOR * float(np.median(step)))

    def robot_speed(self, tool_point: np.ndarray | None = None) -> np.ndarray:
        """Speed profile of the flange, or of ``tool_point`` [m] on the flange."""
        if tool_point is None:
            p = self.T_all[:, :3, 3]
        else:
            tool = torch.eye(4, dtype=self.T_all.dtype)
            tool[:3, 3] = torch.as_tensor(tool_point)
            p = (self.T_all @ tool)[:, :3, 3]
        return speed_profile(self.t_r, p.numpy(), self.grid_r, self.smooth)

    def correlate(
        self, v_robot: np.ndarray, centre: float, half_width: float
    ) -> tuple[float, float]:
        """Best lag in ``centre ± half_width``: a coarse scan, then a fine one at the peak."""
        step, args = self.step, (self.grid_r, v_robot, self.grid_m, self.v_m)
        lags = np.arange(centre - half_width, centre + half_width + step / 2, step)
        lag, _ = _best_lag(*args, lags, self.min_overlap)
        fine = np.arange(lag - 2 * step, lag + 2 * step + self.grid_dt / 2, self.grid_dt)
        return _best_lag(*args, fine, self.min_overlap)

    def usable(self, centre: float, half_width: float) -> np.ndarray:
        """All robot rows whose tracker time stays inside the stream and away from gaps
        for every offset in ``centre ± half_width``."""
        t_r, t_m = self.t_r, self.t_m
        lo, hi = centre - half_width, centre + half_width
        usable = np.flatnonzero((t_r + lo >= t_m[0]) & (t_r + hi <= t_m[-1]))
        gaps = self.gaps
        if gaps.size and usable.size:
            g0, g1 = t_m[gaps], t_m[gaps + 1]
            first = np.clip(np.searchsorted(g1, t_r[usable] + lo, side="right"), 0, gaps.size - 1)
            touches = (g0[first] < t_r[usable] + hi) & (g1[first] > t_r[usable] + lo)
            usable = usable[~touches]
        return usable

    def rows_near(self, centre: float, half_width: float) -> np.ndarray:
        """``refine_points`` of :meth:`usable`, evenly spaced (a fixed set for the whole
        interval: the cost does not jump)."""
        usable = self.usable(centre, half_width)
        if len(usable) < 10:
            raise DataError(
                f"only {len(usable)} robot rows overlap the tracker stream (away from gaps) "
                f"near offset {centre:.4f} s; need at least 10"
            )
        return evenly(usable, self.refine_points)

    def points(self, offset: float, pick: np.ndarray) -> np.ndarray:
        """``(K, 3)`` tracker points [m] at the robot rows ``pick`` shifted by ``offset``."""
        times = self.t_r[pick] + offset
        return interpolate_poses(self.t_m, self.pos, None, times, self.max_gap)[0]

    def cost(self, offset: float, pick: np.ndarray, frames: PointFrames) -> float:
        """RMS registration residual [mm] of rows ``pick`` at ``offset``."""
        return frames.rms_mm(self.points(offset, pick))

    def registered(self, offset: float, pick: np.ndarray) -> PointFrames:
        """Frames registered on rows ``pick`` at ``offset`` (the warm start of ``cost``)."""
        times = self.t_r[pick] + offset
        p, qq, _ = interpolate_poses(self.t_m, self.pos, self.quat, times, self.max_gap)
        R = None if qq is None else _rotations(qq, self.T_all.dtype)
        T = self.T_all[pick]
        return PointFrames.from_guess(T, register_frames(T, torch.as_tensor(p), R))

    def scan(self, lags: np.ndarray, start: float, pose: tuple) -> tuple[np.ndarray, list]:
        """RMS registration residual [mm] at each of ``lags`` (increasing), on
        :data:`SCAN_POINTS` rows overlapping the tracker there, and the registration
        ``(R_B, p_B, p_X)`` there; NaN and None where fewer than a quarter of the robot
        rows overlap (a short overlap fits many offsets).

        Walks out from the lag nearest ``start`` [s] in both directions, each fit
        warm-started at its neighbour's (first at ``pose``, registered near ``start``)
        and from the closed form, the better kept (:meth:`best_registration`): a few
        Gauss-Newton steps each, whatever the length of the streams.
        """
        out, poses = np.full(len(lags), np.nan), [None] * len(lags)
        first = int(np.argmin(np.abs(lags - start)))
        for order in (range(first, len(lags)), range(first - 1, -1, -1)):
            pose_i = pose
            for i in order:
                usable = self.usable(float(lags[i]), 0.0)
                if len(usable) < max(len(self.t_r) // 4, 10):
                    continue
                pick = evenly(usable, SCAN_POINTS)
                pose_i, ms = self.best_registration(float(lags[i]), pick, pose_i)
                out[i], poses[i] = 1e3 * math.sqrt(ms), pose_i
        return out, poses

    def best_registration(self, offset: float, pick: np.ndarray, pose: tuple) -> tuple:
        """``(pose, mean squared residual [m²])`` of the better of two registrations of
        rows ``pick`` at ``offset``: warm-started at ``pose`` and from the closed form.
        On a short, nearly straight path the rotation about the path is barely seen and
        the registration has several local minima; a walk warm-started from lag to lag
        can stay on a poor one (160 µm where the closed form reaches the 28 µm of the
        noise, on 1 s of a simulated UR10 path)."""
        return _registration(self.T_all[pick], self.points(offset, pick), pose, cold=True)

    def covered(self, offset: float, samples: np.ndarray | None = None) -> np.ndarray:
        """Whether each tracker sample (of ``samples``, indices; default all) has its
        robot time ``t - offset`` inside the robot stream and not in a pause of it (rows
        further apart than :data:`GAP_FACTOR` median steps: a logger's pause, where no
        spline knows the path)."""
        t = self.t_m - offset if samples is None else self.t_m[samples] - offset
        inside = (t >= self.t_r[0]) & (t <= self.t_r[-1])
        if self.robot_gaps.size:
            before = np.searchsorted(self.t_r, t, side="right") - 1
            inside &= ~np.isin(np.clip(before, 0, len(self.t_r) - 2), self.robot_gaps)
        return inside

    def flange_at(self, times: np.ndarray) -> torch.Tensor:
        """``(K, 4, 4)`` nominal flange poses at robot ``times`` [s] inside the stream:
        cubic splines of the positions and of the rotations (C2, through every row)."""
        if self._splines is None:
            T = self.T_all.double().numpy()
            self._splines = (
                CubicSpline(self.t_r, T[:, :3, 3]),
                RotationSpline(self.t_r, Rotation.from_matrix(T[:, :3, :3])),
            )
        out = np.zeros((len(times), 4, 4))
        out[:, :3, 3] = self._splines[0](times)
        out[:, :3, :3] = self._splines[1](times).as_matrix()
        out[:, 3, 3] = 1.0
        return torch.from_numpy(out)

    def sample_registration(
        self, offset: float, samples: np.ndarray, pose: tuple, cold: bool = True
    ) -> tuple:
        """``(pose, mean squared residual [m²])`` of tracker ``samples`` (indices) at
        ``offset``, the model's flange interpolated at their robot times: Gauss-Newton
        from ``pose``, and with ``cold`` the better of that and the closed form's
        (:meth:`best_registration`)."""
        T = self.flange_at(self.t_m[samples] - offset)
        return _registration(T, self.pos[samples], pose, cold)

    def check(self, offset: float, pose: tuple):
        """``(jumps, noise [m])`` at ``offset`` and the registration ``pose``: the steps of
        the offset inside the streams and the noise the residuals show (:func:`noise_rms`)."""
        return find_clock_jumps(*self.streams, offset, pose, self.max_gap), self.noise(offset, pose)

    @property
    def streams(self) -> tuple:
        """``(robot_t, T_end, tracker_t, position)`` as :mod:`.clock_jump` takes them."""
        return self.t_r, self.T_all, self.t_m, self.pos

    def noise(self, offset: float, pose: tuple) -> float:
        """[m] the noise the rows show at ``offset`` and registration ``pose``
        (:func:`noise_rms`)."""
        return noise_rms(self.streams, offset, pose, self.max_gap)

    def refine(self, centre: float, half_width: float, pose: tuple | None = None):
        """Bounded search of ``cost``, re-centred while the minimum sits on a bound; the
        registration at the centre is the better of the closed form and ``pose`` (the
        scan's there, when given).

        Returns ``(result, (lo, hi), pick, frames)`` of the last search.
        """
        for _ in range(5):
            lo, hi = centre - half_width, centre + half_width
            pick = self.rows_near(centre, half_width)
            frames = self.registered(centre, pick)
            if pose is not None:  # the scan's registration, where it fits better
                T = self.T_all[pick]
                frames = PointFrames(
                    T, _better(T, self.points(centre, pick), (frames.pose, pose))[0]
                )
            res = minimize_scalar(
                self.cost,
                bounds=(lo, hi),
                args=(pick, frames),
                method="bounded",
                options={"xatol": 1e-6},
            )
            if min(res.x - lo, hi - res.x) > 0.05 * half_width:
                break
            centre, pose = float(res.x), frames.fit(self.points(res.x, pick))
        return res, (lo, hi), pick, frames


def evenly(indices: np.ndarray, count: int) -> np.ndarray:
    """At most ``count`` of ``indices``, evenly spaced over them (the first and the last
    kept)."""
    count = min(count, len(indices))
    return indices[np.unique(np.linspace(0, len(indices) - 1, count).round().astype(int))]


def _registration(T: torch.Tensor, p: np.ndarray, pose: tuple, cold: bool) -> tuple:
    """``(pose, mean squared residual [m²])`` of flange poses ``T`` registered on
    positions ``p``: Gauss-Newton from ``pose``, and with ``cold`` the better of that and
    a start from the closed form (:data:`COLD_ITERATIONS`)."""
    starts = [pose]
    if cold:
        guess = register_frames(T, torch.as_tensor(p), None, iterations=COLD_ITERATIONS)
        starts.append(PointFrames.from_guess(T, guess).pose)
    return _better(T, p, starts)


def _better(T: torch.Tensor, p: np.ndarray, starts) -> tuple:
    """``(pose, mean squared residual [m²])`` of flange poses ``T`` registered on points
    ``p``: the lowest of Gauss-Newton from each of ``starts``."""
    fits = []
    for start in starts:
        frames = PointFrames(T, start)
        fitted = frames.fit(p)
        r = frames.points(*fitted) - p
        ms = float((r * r).sum(-1).mean())
        fits.append((fitted, ms if math.isfinite(ms) else math.inf))
    return min(fits, key=lambda f: f[1])

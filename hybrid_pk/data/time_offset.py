"""Time offset between a robot joint stream and a tracker pose stream.

``tracker time = robot time + offset`` [s]; the method is described in
:mod:`hybrid_pk.data.streams`: a coarse cross-correlation of speed profiles (first of
the flange, then of the registered tool point) and a bounded search of the
registration residual around it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from hybrid_pk.data.clock_drift import ClockDrift, fit_drift
from hybrid_pk.data.clock_jump import ClockJump
from hybrid_pk.data.interpolation import (
    checked_array,
    stream_times,
)
from hybrid_pk.data.offset_evidence import LIKELIHOOD_RATIO, Rival, interval, rivals
from hybrid_pk.data.offset_search import OffsetSearch, speed_profile
from hybrid_pk.errors import DataError

__all__ = [
    "OffsetEstimate",
    "check_clock_jumps",
    "check_offset",
    "estimate_time_offset",
    "speed_profile",
]

GRID_DT = 1e-3  # [s] resampling step of the speed profiles
SMOOTH_S = 0.02  # [s] box filter and difference span of the speed profiles
REFINE_POINTS = 1500  # robot rows used by the registration refinement (evenly spaced)
# Lowest minima of the scan that are refined: a path that repeats itself makes basins of
# similar depth one period apart; the true one and its neighbours on either side.
CANDIDATES = 3
# Residual over noise above which the offset is questioned: an uncalibrated arm's absolute
# error (~1 mm, ISO 9283 accuracy of industrial arms) is ~100 times a tracker's ~10 µm
# noise; more than that is more than a nominal model leaves.
NOISE_RATIO = 100.0


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
        max_offset: [s] the largest |offset| the cross-correlation searched.
        jumps: steps of the offset inside the streams (:mod:`~hybrid_pk.data.clock_jump`).
        noise_mm: RMS length [mm] of the residual's noise that the rows show at ``offset``
            (:func:`~hybrid_pk.data.clock_jump.noise_rms`); NaN if not estimated.
        rivals: other minima of the registration residual that the data do not exclude
            (:mod:`~hybrid_pk.data.offset_evidence`).
        interval: [s] the offsets around ``offset`` that the data do not exclude (a
            likelihood ratio under 100; :mod:`~hybrid_pk.data.offset_evidence`); an end
            is infinite where the residual stays flat to the end of the search; NaN: not
            computed.
        sample_s: [s] the robot stream's sampling period (median step of its stamps).
        drift: the clocks' rate difference fitted at ``offset``
            (:mod:`~hybrid_pk.data.clock_drift`); None: not fitted (not where the offset
            jumps: a jump would pass for a drift).
    """

    offset: float
    coarse: float
    correlation: float
    residual_mm: float
    coarse_residual_mm: float
    bounds: tuple[float, float]
    n_rows: int
    max_offset: float = math.inf
    jumps: tuple[ClockJump, ...] = ()
    noise_mm: float = math.nan
    rivals: tuple[Rival, ...] = ()
    interval: tuple[float, float] = (math.nan, math.nan)
    sample_s: float = math.nan
    drift: ClockDrift | None = None

    @property
    def determined(self) -> bool:
        """No rival basin, and the interval within one robot sample of the offset either
        side (beyond, a row's tracker pose is uncertain by more than the time between
        two rows). True where the interval was not computed."""
        lo, hi = self.interval
        wide = max(self.offset - lo, hi - self.offset) > self.sample_s  # NaN: False
        return not self.rivals and not wide

    def summary(self) -> str:
        """One line for humans; says when the offset lies beyond ``max_offset``."""
        before = (
            f"{self.coarse_residual_mm:.3f} -> "
            if math.isfinite(self.coarse_residual_mm)
            else "(at the coarse offset these rows leave the tracker stream) "
        )
        line = (
            f"time offset {1e3 * self.offset:.3f} ms (tracker = robot + offset): speed "
            f"correlation {self.correlation:.3f} at {1e3 * self.coarse:.1f} ms, registration "
            f"residual {before}{self.residual_mm:.3f} mm RMS ({self.n_rows} rows)"
        )
        if self.interval_text():
            ratio = f"likelihood ratio {LIKELIHOOD_RATIO:g}:1"
            line += f"; the noise allows {self.interval_text()} ({ratio})"
        if not self.bounds[0] <= self.coarse <= self.bounds[1]:  # a broad peak, shifted
            line += "; the registration residual's scan placed it away from the correlation's peak"
        if abs(self.offset) > self.max_offset:
            line += (
                f"; note: beyond the {self.max_offset:g} s searched by the speed "
                "correlation (max_offset): the registration search walked out to it; "
                "check the residual against the tracker's noise"
            )
        return line

    def residual_warning(self, source: str) -> str:
        """One line when ``residual_mm`` exceeds :data:`NOISE_RATIO` times ``noise_mm``
        (naming ``source``, the streams); empty otherwise."""
        if not (self.residual_mm > NOISE_RATIO * self.noise_mm):  # NaN noise: no test
            return ""
        return (
            f"{source}: the registration residual at the time offset, {self.residual_mm:.3f} "
            f"mm RMS, is {self.residual_mm / self.noise_mm:.0f} times the noise the streams "
            f"show ({1e3 * self.noise_mm:.1f} µm RMS, second differences along the path; "
            f"warning above {NOISE_RATIO:g}x): a wrong offset (beyond --max-offset, or "
            "another basin of the residual) or a nominal model far off the robot; give "
            "the offset with --offset to compare"
        )

    def ambiguity_warning(self, source: str) -> str:
        """One line when the offset is not :attr:`determined` (naming ``source``, the
        streams); empty otherwise."""
        if self.determined:
            return ""
        lo, hi = self.interval
        outside = [r for r in self.rivals if not lo <= r.offset <= hi]
        parts = [f"{self.interval_text()} fit the streams about as well as {_ms(self.offset)}"]
        compared = [_rival_text(r) for r in outside if math.isfinite(r.d_chi2)]
        if compared:
            parts.append(f"so do {', '.join(compared)}")
        unknown = [_ms(r.offset) for r in outside if not math.isfinite(r.d_chi2)]
        if unknown:
            parts.append(f"{' and '.join(unknown)} share too few samples with it to compare")
        return (
            f"{source}: the time offset is not determined: {'; '.join(parts)} (the data "
            f"favour it by a likelihood ratio under {LIKELIHOOD_RATIO:g}:1, against the "
            "noise or the residual, whichever is larger; a robot sample is "
            f"{_ms(self.sample_s)}); a longer stream whose path turns and changes speed "
            "decides, or give the offset with --offset"
        )

    def interval_text(self) -> str:
        """The interval in words (``offsets from A to B ms``), or empty where it was not
        computed; as many decimals as show its width to two digits."""
        lo, hi = self.interval
        if math.isnan(lo):
            return ""
        if math.isinf(lo) and math.isinf(hi):
            return "all the offsets searched"
        width = 1e3 * (hi - lo) if math.isfinite(hi - lo) else 1.0
        digits = min(max(1, 1 - math.floor(math.log10(max(width, 1e-9)))), 6)
        if math.isinf(lo):
            return f"offsets up to {_ms(hi, digits)}"
        if math.isinf(hi):
            return f"offsets from {_ms(lo, digits)} on"
        return f"offsets from {1e3 * lo:.{digits}f} to {_ms(hi, digits)}"


def _ms(t: float, digits: int | None = None) -> str:
    if digits is None:
        digits = 3 if abs(t) < 0.01 else 1
    return f"{1e3 * t:.{digits}f} ms"


def _rival_text(r: Rival) -> str:
    ratio = math.exp(min(r.d_chi2, 700) / 2)  # d_chi2 = 2 ln(ratio)
    return (
        f"{_ms(r.offset)} ({1e3 * r.residual_mm:.1f} against {1e3 * r.best_residual_mm:.1f} "
        f"µm RMS on the {r.rows} tracker samples both cover, ratio {ratio:.3g}:1)"
    )


def _lowest_minima(scan: np.ndarray, count: int) -> list[int]:
    """The indices of the ``count`` lowest local minima of ``scan`` (NaN: no value)."""
    value = np.where(np.isfinite(scan), scan, np.inf)
    pad = np.concatenate([[np.inf], value, [np.inf]])
    found = np.flatnonzero(np.isfinite(value) & (value <= pad[:-2]) & (value <= pad[2:]))
    return [int(i) for i in found[np.argsort(value[found])][:count]]


def _checked_streams(robot_t, q, tracker_t, position, quat):
    """``(t_r, q, t_m, position, quat)`` as checked float64 arrays of matching lengths."""
    t_r = stream_times(robot_t, "robot t")
    t_m = stream_times(tracker_t, "tracker t")
    q = checked_array(q, "q", (np.asarray(q).shape[-1],))
    if len(q) != len(t_r):
        raise DataError(f"q has {len(q)} rows but robot t has {len(t_r)}")
    pos = checked_array(position, "position", (3,))
    if len(pos) != len(t_m):
        raise DataError(f"position has {len(pos)} rows but tracker t has {len(t_m)}")
    quat_np = None if quat is None else checked_array(quat, "quat", (4,))
    if quat_np is not None and len(quat_np) != len(t_m):
        raise DataError(f"quat has {len(quat_np)} rows but tracker t has {len(t_m)}")
    return t_r, q, t_m, pos, quat_np


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
    """Offset between a robot joint stream and a tracker stream (:mod:`~hybrid_pk.data.streams`).

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
        DataError: a bad max_offset, shapes or times, streams that never overlap, a robot
            that does not move (no speed to correlate), too few rows overlapping the tracker.
    """
    if not 0 < max_offset < math.inf:  # a search half-width: -1 or NaN has no grid
        raise DataError(f"max_offset must be a finite time > 0 s, got {max_offset!r}")
    t_r, q, t_m, pos, quat_np = _checked_streams(robot_t, q, tracker_t, position, quat)
    with torch.no_grad():
        T_all = robot.fk(torch.as_tensor(q, dtype=robot.dtype)).double()
    search = OffsetSearch(
        t_r, T_all, t_m, pos, quat_np, smooth=smooth, grid_dt=grid_dt, refine_points=refine_points
    )
    # Coarse 1: flange speed (the tool offset is not known yet) against point speed.
    v_r = search.robot_speed()
    if not np.isfinite(v_r).any() or float(np.nanstd(v_r)) < 1e-6:
        raise DataError("the robot stream does not move: no speed profile to correlate")
    lag0, _ = search.correlate(v_r, 0.0, max_offset)
    # Coarse 2: with the tool offset of a registration at lag0, the model's point speed
    # has the tracker's shape, so the correlation peak is no longer biased.
    frames = search.registered(lag0, search.rows_near(lag0, 0.0))
    v_point = search.robot_speed(frames.p_X)
    coarse, corr = search.correlate(v_point, lag0, min(max_offset, 10 * refine_window))
    # The speed of a slow path correlates over a broad peak that a far tool point moves
    # by up to the whole search (0.96 s for 0.23 s true): scan the registration residual
    # over all of it, one grid step per refinement window, and refine the lowest minima.
    lags = np.linspace(-max_offset, max_offset, 2 * math.ceil(max_offset / refine_window) + 1)
    scan, poses = search.scan(lags, coarse, frames.pose)
    centres = [(lags[i], refine_window, poses[i]) for i in _lowest_minima(scan, CANDIDATES)]
    # and the correlation's value, its window covering the two coarse stages' disagreement
    # (its search may walk beyond max_offset, where the scan does not reach)
    if all(abs(coarse - c) > refine_window for c, _, _ in centres):
        centres.append((coarse, max(refine_window, 1.5 * abs(coarse - lag0)), None))
    refined = _refined(search, centres)
    best = min(range(len(refined)), key=lambda i: refined[i][0].fun)
    res, (lo, hi), pick, frames = refined[best]
    pose = frames.fit(search.points(float(res.x), pick))  # the registration at the offset
    jumps, noise = search.check(float(res.x), pose)
    return OffsetEstimate(
        offset=float(res.x),
        coarse=float(coarse),
        correlation=corr,
        residual_mm=float(res.fun),
        coarse_residual_mm=search.cost(coarse, pick, frames),
        bounds=(float(lo), float(hi)),
        n_rows=len(pick),
        max_offset=float(max_offset),
        jumps=jumps,
        noise_mm=1e3 * noise,
        rivals=rivals(search, refined, best, noise, refine_window),
        interval=interval(search, refined[best], noise, max_offset, refine_window),
        sample_s=float(np.median(np.diff(t_r))),
        # a jump would pass for a drift: its parts, imported apart, are each fitted then
        drift=None if jumps else fit_drift(search, res.x, pick, pose, noise),
    )


def _refined(search: OffsetSearch, centres: list[tuple]) -> list[tuple]:
    """Each candidate ``(centre, half-width, scan pose or None)`` refined
    (:meth:`OffsetSearch.refine`); one whose window leaves under 10 robot rows
    overlapping the tracker (the end of the search on a short stream) is dropped, too few
    rows to judge it; the first such error where none is left."""
    found, refused = [], None
    for centre, half_width, pose in centres:
        try:
            found.append(search.refine(float(centre), half_width, pose))
        except DataError as exc:
            refused = refused or exc
    if not found:
        raise refused
    return found


def check_clock_jumps(
    robot_t: Any, q: Any, tracker_t: Any, position: Any, robot: Any, offset: float, quat: Any = None
) -> tuple[ClockJump, ...]:
    """Steps of a known ``offset`` [s] inside the streams (:mod:`~hybrid_pk.data.clock_jump`);
    the arguments as in :func:`estimate_time_offset`. :func:`estimate_time_offset` runs the
    same test at its own estimate (``OffsetEstimate.jumps``)."""
    near = _rows_at(robot_t, q, tracker_t, position, robot, offset, quat)
    return () if near is None else near[0].check(float(offset), near[2])[0]


def check_offset(
    robot_t: Any, q: Any, tracker_t: Any, position: Any, robot: Any, offset: float, quat: Any = None
) -> tuple[tuple[ClockJump, ...], ClockDrift | None]:
    """``(jumps, drift)`` at a known ``offset`` [s]: the steps of the offset inside the
    streams (:mod:`~hybrid_pk.data.clock_jump`) and, where there are none, the clocks'
    drift (:mod:`~hybrid_pk.data.clock_drift`; a jump would pass for one); the arguments
    as in :func:`estimate_time_offset`, which does both at its own estimate. ``((), None)``
    where under 10 rows overlap (synchronise says why)."""
    near = _rows_at(robot_t, q, tracker_t, position, robot, offset, quat)
    if near is None:
        return (), None
    search, pick, pose = near
    jumps, noise = search.check(float(offset), pose)
    return jumps, None if jumps else fit_drift(search, float(offset), pick, pose, noise)


def _rows_at(robot_t, q, tracker_t, position, robot, offset, quat):
    """``(search, rows, registration)`` of the checked streams at ``offset``; None where
    under 10 robot rows overlap the tracker there."""
    t_r, q, t_m, pos, quat_np = _checked_streams(robot_t, q, tracker_t, position, quat)
    with torch.no_grad():
        T_all = robot.fk(torch.as_tensor(q, dtype=robot.dtype)).double()
    search = OffsetSearch(
        t_r, T_all, t_m, pos, quat_np, smooth=SMOOTH_S, grid_dt=GRID_DT, refine_points=REFINE_POINTS
    )
    try:
        pick = search.rows_near(float(offset), 0.0)
    except DataError:
        return None
    return search, pick, search.registered(float(offset), pick).fit(search.points(offset, pick))

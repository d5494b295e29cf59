"""A drift of the two clocks: the time offset changing steadily along the streams.

The offset of :mod:`hybrid_pk.data.streams` is one constant, but two free-running clocks
differ in rate (quartz oscillators by 10-100 ppm: 6 ms over 2 minutes at 50 ppm). The
model here is::

    tracker time = robot time + offset + rate (robot time - t_mid)

``t_mid`` the middle of the robot stream. At the estimated offset, one Gauss-Newton fit
of the registration (base frame, tool point) with the offset and the rate, on the
refinement's rows, gives the rate and its standard error (residual std times the root of
the inverse normal matrix's diagonal element, as for the clock jumps' parts).

The nominal model's own error also leans the offset along the path (with the tests'
0.3 mrad joint offset: -23 to +67 ppm on 12 s of UR10 path, 1-3 ppm on one or two
minutes, |z| up to 27), so significance alone is no rule. A drift is reported when it is
significant (two-sided, :data:`~hybrid_pk.data.clock_jump.ALPHA`), moves the offset
across the streams by more than one robot sample, the bound an offset is determined to
(:attr:`~hybrid_pk.data.time_offset.OffsetEstimate.determined`), so that the table's rows
at the ends are paired with tracker poses more than the time between two rows away, *and*
explains most of the registration residual above the noise (:data:`MAJORITY`): a pose
error of the model leaves a misfit that a drift barely changes. ``import streams`` then
synchronises the table with the fitted offset and rate
(:func:`~hybrid_pk.data.streams.synchronise`'s ``rate``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hybrid_pk.data.clock_jump import ALPHA, tracker_motion
from hybrid_pk.data.interpolation import interpolate_poses
from hybrid_pk.data.point_frames import PointFrames
from hybrid_pk.distributions import norm_isf

__all__ = ["ClockDrift", "fit_drift"]

ITERATIONS = 10  # Gauss-Newton steps: quadratic near the optimum, a few reach it
# The share of the residual above the noise a drift must explain to be named: most of it.
# A nominal model's error depends on the pose, not the time: a fitted drift removed 1-2 %
# of such misfits in the tests' streams (0.3-5 deg off at the shoulder), 95-100 % of a
# clock drift's.
MAJORITY = 0.5


@dataclass(frozen=True)
class ClockDrift:
    """The clock rate difference fitted at an offset.

    Attributes:
        rate: [s/s] d offset / d robot time (1e-6 = 1 ppm).
        std: [s/s] its standard error.
        span: [s] the robot stream's duration.
        sample_s: [s] its sampling period.
        offset: [s] the offset at ``middle``, fitted with the rate.
        middle: [s] the robot time the rate is counted from (the stream's middle).
        residual_mm: RMS registration residual [mm] at the offset alone.
        drift_residual_mm: the same with the drift fitted.
        noise_mm: the streams' noise [mm] (RMS length), NaN: unknown.
    """

    rate: float
    std: float
    span: float
    sample_s: float
    offset: float = math.nan
    middle: float = math.nan
    residual_mm: float = math.nan
    drift_residual_mm: float = math.nan
    noise_mm: float = math.nan

    @property
    def change(self) -> float:
        """[s] the offset's change across the streams, ``|rate| x span``."""
        return abs(self.rate) * self.span

    @property
    def explained(self) -> float:
        """The share of the residual's excess over the noise (mean squares) that the
        drift removes; 0 where there is no excess or the noise is unknown."""
        before, after = self.residual_mm**2, self.drift_residual_mm**2
        excess = before - self.noise_mm**2
        return (before - after) / excess if excess > 0 else 0.0  # NaN noise: 0

    @property
    def matters(self) -> bool:
        """Significant (two-sided at ALPHA), changing the offset across the streams by
        more than one robot sample, and explaining most of the residual above the noise
        (:data:`MAJORITY`)."""
        significant = abs(self.rate) > norm_isf(ALPHA / 2) * self.std
        return bool(significant and self.change > self.sample_s and self.explained > MAJORITY)

    def warning(self, source: str, corrected: bool = False) -> str:
        """One line when the drift :attr:`matters` (naming ``source``); empty otherwise.
        ``corrected``: the table was synchronised with it (else: how to split)."""
        if not self.matters:
            return ""
        head = (
            f"{source}: the clocks drift: the time offset changes by {1e3 * self.change:.1f} "
            f"ms over the streams' {self.span:.0f} s (clock rate {1e6 * self.rate:+.1f} ± "
            f"{1e6 * self.std:.2g} ppm, |z| {abs(self.rate) / self.std:.0f}; the registration "
            f"residual {1e3 * self.residual_mm:.0f} -> {1e3 * self.drift_residual_mm:.0f} µm RMS "
            f"with it, noise {1e3 * self.noise_mm:.0f} µm), more than a robot sample "
            f"({1e3 * self.sample_s:.1f} ms)"
        )
        if corrected:
            return (
                f"{head}: the table is synchronised with it, tracker = robot + "
                f"{1e3 * self.offset:.3f} ms + rate x (robot t - {self.middle:.3f} s); "
                "--clock-drift none keeps one offset"
            )
        part = self.sample_s / abs(self.rate)
        return (
            f"{head}: one offset pairs the rows at the ends with poses up to "
            f"{0.5e3 * self.change:.1f} ms away; split the streams into parts shorter than "
            f"{part:.0f} s and import each, or let --clock-drift auto correct it"
        )


def fit_drift(search, offset: float, pick: np.ndarray, pose: tuple, noise_m: float) -> ClockDrift:
    """The rate at ``offset`` on the robot rows ``pick`` of ``search``
    (:class:`~hybrid_pk.data.offset_search.OffsetSearch`), the registration started at
    ``pose`` (fitted at ``offset``); ``noise_m``: the streams' noise [m] (RMS length)."""
    t_r, t_m, pos = search.t_r, search.t_m, search.pos
    t = t_r[pick] - 0.5 * (t_r[0] + t_r[-1])
    frames, (R_B, p_B, p_X) = PointFrames(search.T_all[pick], pose), pose
    span, sample = float(t_r[-1] - t_r[0]), float(np.median(np.diff(t_r)))
    h = 0.5 * sample  # the tracker's velocity over a robot period
    shift, normal, ms0 = np.array([offset, 0.0]), None, math.nan
    for _ in range(ITERATIONS):
        at = t_r[pick] + shift[0] + shift[1] * t
        m, v, ok = tracker_motion(t_m, pos, at, h, search.max_gap)
        v, r = v[ok], (frames.points(R_B, p_B, p_X) - m)[ok]
        if normal is None:
            ms0 = float((r * r).sum(-1).mean())
        J = np.zeros((len(r), 3, 11))
        J[:, :, :9] = frames.jacobian(R_B, p_X)[ok]
        J[:, :, 9], J[:, :, 10] = -v, -v * t[ok, None]  # r = f - m(t + offset + rate t)
        Jf = J.reshape(-1, 11)
        normal = Jf.T @ Jf
        try:
            step = -np.linalg.solve(normal, Jf.T @ r.reshape(-1))
        except np.linalg.LinAlgError:  # no motion that tells a rate from the frames
            return ClockDrift(math.nan, math.nan, span, sample)
        R_B, p_B, p_X = frames.update(R_B, p_B, p_X, step)
        shift = shift + step[9:]
        if abs(step[9]) < 1e-9 and abs(step[10]) * abs(t).max() < 1e-9:  # [s]
            break
    at = t_r[pick] + shift[0] + shift[1] * t
    m, _, ok = interpolate_poses(t_m, pos, None, at, search.max_gap)
    r = (frames.points(R_B, p_B, p_X) - m)[ok]
    s2 = float((r * r).sum()) / max(r.size - 11, 1)
    std = math.sqrt(s2 * float(np.linalg.inv(normal)[10, 10]))
    rms = (1e3 * math.sqrt(ms0), 1e3 * math.sqrt(float((r * r).sum(-1).mean())))
    middle = 0.5 * float(t_r[0] + t_r[-1])
    return ClockDrift(
        float(shift[1]), std, span, sample, float(shift[0]), middle, *rms, 1e3 * noise_m
    )

"""What the streams show of the time offset: its likelihood interval and rival basins.

The registration residual, profiled over the frames (re-registered at each offset), is
what the streams say about the offset. Relative to the estimate it reads as::

    d_chi2(offset) = 3 K (ms(offset) - ms_best) / max(noise^2, ms_best)

``ms``: the mean squared residual length [m^2] on the same ``K`` tracker samples (at
most one per robot sample: a tracker's filtering correlates its noise over a few of its
own samples, which must not count as independent evidence); ``noise``:
the RMS length of the streams' noise (model-free, :func:`~hybrid_pk.data.clock_jump.
noise_rms`). The larger of the noise and the estimate's own residual is the scale, so a
difference that the model's misfit could make is not counted as evidence. Offsets whose
``d_chi2`` stays below ``2 ln 100`` are not excluded: the data favour the estimate by a
likelihood ratio under 100 ("decisive" on Jeffreys' scale).

- The **interval**: walking out from the estimate on each side (warm-started
  registrations, so the walk follows the valley of the frames), the offsets where
  ``d_chi2`` first reaches the bound. On a long path that turns and changes speed it is
  a fraction of a millisecond; on a short, nearly straight piece a rigid change of frames
  carries the path onto itself shifted in time, the residual stays flat and the interval
  spans tens or hundreds of milliseconds (the nominal model's own error, not the clocks,
  then places the minimum).
- **Rivals**: every other refined minimum of the search, farther from the estimate than
  the scan's step, compared on the rows that overlap the tracker at both offsets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hybrid_pk.data.offset_search import evenly

__all__ = ["LIKELIHOOD_RATIO", "Rival", "interval", "rivals"]

# The likelihood ratio the data must give the estimate over another offset: 100 is
# "decisive" on Jeffreys' scale of evidence (d_chi2 = 2 ln 100 = 9.2).
LIKELIHOOD_RATIO = 100.0
BOUND = 2 * math.log(LIKELIHOOD_RATIO)
MIN_COMMON_ROWS = 10  # as the refinement: fewer samples fit too many offsets to compare
# First step of the interval's walk [s], doubled until the bound is passed: a tenth of a
# microsecond, under any interval a tracker's noise leaves (0.01 ms on 12 s of path).
FIRST_STEP = 1e-7
BISECTIONS = 8  # the edge to 1/256 of its last doubling: under 1 % of the interval


@dataclass(frozen=True)
class Rival:
    """A refined minimum of the registration residual that the data do not exclude.

    Attributes:
        offset: [s] the rival offset.
        residual_mm: RMS registration residual [mm] at ``offset`` on the common rows.
        best_residual_mm: the estimate's, on the same rows.
        rows: tracker samples inside the robot stream at both offsets (compared on at
            most the refinement's number of them).
        d_chi2: the evidence for the estimate, ``2 ln`` of the likelihood ratio; NaN when
            under :data:`MIN_COMMON_ROWS` rows are common (nothing to compare).
    """

    offset: float
    residual_mm: float
    best_residual_mm: float
    rows: int
    d_chi2: float


class _Profile:
    """``d_chi2`` of offsets against the estimate ``found`` (a refined minimum), on fixed
    tracker samples: the data stay the same samples at every offset, the model moves (the
    flange poses interpolated at the samples' robot times, :meth:`OffsetSearch.flange_at`).
    Interpolating the tracker at the robot rows instead would draw other noise at each
    offset (a tracker sample every 0.3 ms) and make a jagged residual of many sharp,
    noise-made minima."""

    def __init__(self, search, found: tuple, noise_m: float) -> None:
        res, _, _, frames = found
        self.search, self.best = search, float(res.x)
        inside = np.flatnonzero(search.covered(self.best))
        count = min(search.refine_points, _robot_rows(search, self.best))
        self.samples = evenly(inside, count)
        self.pose, self.ms = search.sample_registration(self.best, self.samples, frames.pose)
        self.scale = max(noise_m**2, self.ms) if math.isfinite(noise_m) else math.inf

    def d_chi2(self, offset: float, pose: tuple, cold: bool) -> tuple[float, tuple]:
        """``(d_chi2, registration)`` at ``offset`` from ``pose`` (with ``cold``, and from
        the closed form); NaN where under :data:`MIN_COMMON_ROWS` of the samples stay
        inside the robot stream."""
        samples = self.samples[self.search.covered(offset, self.samples)]
        if len(samples) < MIN_COMMON_ROWS:
            return math.nan, pose
        ms_best = self.ms
        if len(samples) < len(self.samples):
            ms_best = self.search.sample_registration(self.best, samples, self.pose)[1]
        pose, ms = self.search.sample_registration(offset, samples, pose, cold)
        return 3 * len(samples) * (ms - ms_best) / self.scale, pose

    def edge(self, direction: int, limit: float, near: float) -> float:
        """The offset on side ``direction`` (+1, -1) where ``d_chi2`` reaches the bound;
        ``direction * inf`` where it does not within ``limit`` [s] of the estimate or
        before the samples leave the robot stream. Each registration is warm-started at
        the last one inside; one more than ``near`` [s] from it also from the closed form
        (a move the scan's warm start does not make in one step)."""
        inner, outer, pose, step = 0.0, math.nan, self.pose, FIRST_STEP
        while step <= limit:
            value, moved = self.d_chi2(self.best + direction * step, pose, step - inner > near)
            if not math.isfinite(value):
                break
            if value >= BOUND:
                outer = step
                break
            inner, pose, step = step, moved, 2 * step
        if math.isnan(outer):
            return direction * math.inf
        for _ in range(BISECTIONS):
            mid = 0.5 * (inner + outer)
            value, moved = self.d_chi2(self.best + direction * mid, pose, mid - inner > near)
            if math.isfinite(value) and value < BOUND:
                inner, pose = mid, moved
            else:
                outer = mid
        return self.best + direction * 0.5 * (inner + outer)


def interval(
    search, found: tuple, noise_m: float, limit: float, near: float
) -> tuple[float, float]:
    """``(lo, hi)`` [s]: the offsets around the refined minimum ``found`` that the data
    do not exclude (module docstring); an end is infinite where the residual stays within
    the bound for ``limit`` [s] or until the streams stop overlapping. ``near`` [s]: the
    scan's step, the longest move a warm-started registration alone follows."""
    if search.covered(float(found[0].x)).sum() < MIN_COMMON_ROWS:
        return -math.inf, math.inf  # a tracker slower than that has nothing to compare
    profile = _Profile(search, found, noise_m)
    if not math.isfinite(profile.scale):
        return -math.inf, math.inf  # no noise scale: nothing is excluded
    return profile.edge(-1, limit, near), profile.edge(+1, limit, near)


def rivals(search, refined: list[tuple], best: int, noise_m: float, step: float) -> tuple:
    """The refined minima (``(result, bounds, pick, frames)`` of
    :meth:`~hybrid_pk.data.offset_search.OffsetSearch.refine`) that the data do not
    exclude against ``refined[best]``, weakest evidence first. ``noise_m``: the streams'
    noise [m] (RMS length; not finite: unknown, nothing is excluded); ``step`` [s]: the
    scan's step, within which two minima are one basin."""
    offset = float(refined[best][0].x)
    seen, out = [offset], []
    for found in sorted(refined, key=lambda f: f[0].fun):
        other = float(found[0].x)
        if min(abs(other - s) for s in seen) <= step:
            continue  # the same basin, reached from another start
        seen.append(other)
        rival = _compared(search, (offset, other), (refined[best], found), noise_m)
        if not rival.d_chi2 >= BOUND:  # NaN: not excluded
            out.append(rival)
    return tuple(sorted(out, key=lambda r: r.d_chi2 if math.isfinite(r.d_chi2) else -math.inf))


def _compared(search, offsets: tuple[float, float], found: tuple, noise_m: float) -> Rival:
    """The rival ``offsets[1]`` against the estimate ``offsets[0]`` on the tracker samples
    inside the robot stream at both, each registration started from its refinement's
    (``found``) and the closed form."""
    common = np.flatnonzero(search.covered(offsets[0]) & search.covered(offsets[1]))
    if len(common) < MIN_COMMON_ROWS:
        return Rival(offsets[1], math.nan, math.nan, len(common), math.nan)
    count = min(search.refine_points, *(_robot_rows(search, o) for o in offsets))
    samples = evenly(common, count)
    ms = [
        search.sample_registration(offset, samples, frames.pose)[1]
        for offset, (_, _, _, frames) in zip(offsets, found, strict=True)
    ]
    scale = max(noise_m**2, ms[0]) if math.isfinite(noise_m) else math.inf
    d_chi2 = 3 * len(samples) * (ms[1] - ms[0]) / scale
    return Rival(offsets[1], 1e3 * math.sqrt(ms[1]), 1e3 * math.sqrt(ms[0]), len(common), d_chi2)


def _robot_rows(search, offset: float) -> int:
    """Robot rows overlapping the tracker at ``offset``: at most one tracker sample per
    robot sample is compared, so that a tracker's own filtering (its noise correlated
    over a few of its samples) does not count one error many times (10 at least)."""
    return max(len(search.usable(offset, 0.0)), MIN_COMMON_ROWS)

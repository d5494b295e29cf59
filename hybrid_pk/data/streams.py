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
   - scan: the speed of a slow path correlates over a broad peak that the tool point's
     distance from the flange can move by most of the search (0.96 s for 0.23 s true),
     so the registration residual is also scanned over all of ``±max_offset`` (one step
     per refinement window, few rows, warm-started fits); its lowest minima are refined
     like the correlation's value, and the lowest refined residual is the estimate.
     ``OffsetEstimate.residual_warning`` is one line when that residual exceeds 100
     times the noise the rows show (:func:`~hybrid_pk.data.clock_jump.noise_rms`).
     The scan's registration at each lag is the better of a warm start and the closed
     form: on a short path the registration has several local minima.
   - evidence: the offsets the noise allows (``OffsetEstimate.interval``) and the other
     minima that fit about as well (``rivals``), from the residual profiled on fixed
     tracker samples (:mod:`~hybrid_pk.data.offset_evidence`);
     ``OffsetEstimate.ambiguity_warning`` is one line when the offset is not
     determined to one robot sample.

2. :func:`synchronise` interpolates the tracker stream at the robot times: positions
   linearly, orientations by SLERP (at 3 kHz the tracker moves ~0.1 mm between
   samples). Robot rows outside the tracker's span or inside a tracker gap (beam
   break) are left out and reported. The result keeps ``t`` (robot clock).

A clock rate difference (drift) of the two devices is fitted at the offset
(:mod:`hybrid_pk.data.clock_drift`, or at a given offset: :func:`check_offset`);
:func:`synchronise` takes it (``rate``), and ``import streams`` applies it where it moves
the offset across the streams by more than one robot sample. A step of the offset
inside the streams (a clock jump) is tested for at the estimate (or at a given offset:
:func:`check_clock_jumps`) and reported with the row and the offsets of both parts
(:mod:`hybrid_pk.data.clock_jump`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hybrid_pk.data.clock_drift import ClockDrift
from hybrid_pk.data.clock_jump import ClockJump
from hybrid_pk.data.interpolation import (
    checked_array,
    interpolate_poses,
    stream_times,
)
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.data.time_offset import (
    OffsetEstimate,
    check_clock_jumps,
    check_offset,
    estimate_time_offset,
    speed_profile,
)
from hybrid_pk.errors import DataError

__all__ = [
    "ClockDrift",
    "ClockJump",
    "OffsetEstimate",
    "SyncResult",
    "check_clock_jumps",
    "check_offset",
    "estimate_time_offset",
    "interpolate_poses",
    "speed_profile",
    "synchronise",
]


@dataclass(frozen=True)
class SyncResult:
    """Result of :func:`synchronise`.

    Attributes:
        data: one row per kept robot sample; ``t`` on the robot clock.
        outside: 1-based robot rows left out: their tracker time is outside the
            tracker stream.
        in_gap: 1-based robot rows left out: their tracker time falls in a gap.
        offset: [s] the offset used (at ``middle`` where ``rate`` is not 0).
        rate: the clocks' drift used, d offset / d robot time (0: one offset).
        middle: [s] the robot time ``rate`` is counted from.
    """

    data: MeasuredData
    outside: tuple[int, ...]
    in_gap: tuple[int, ...]
    offset: float
    rate: float = 0.0
    middle: float = 0.0

    def summary(self) -> str:
        """Short human summary."""
        line = f"synchronised {self.data.n} rows at offset {1e3 * self.offset:.3f} ms"
        if self.rate:
            line += f" (at robot t {self.middle:.3f} s, drifting {1e6 * self.rate:+.1f} ppm)"
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
    rate: float = 0.0,
    middle: float | None = None,
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
        rate: a drift of the clocks (:mod:`~hybrid_pk.data.clock_drift`): tracker time =
            robot time + offset + rate (robot time - middle).
        middle: [s] default the middle of the robot stream.
    """
    t_r = stream_times(robot_t, "robot t")
    t_m = stream_times(tracker_t, "tracker t")
    q = checked_array(q, "q", (np.asarray(q).shape[-1],))
    pos = checked_array(position, "position", (3,))
    quat_np = None if quat is None else checked_array(quat, "quat", (4,))
    if len(q) != len(t_r) or len(pos) != len(t_m):
        raise DataError("q must have one row per robot time and position one per tracker time")
    rows = np.arange(1, len(t_r) + 1) if robot_rows is None else np.asarray(robot_rows)
    middle = 0.5 * float(t_r[0] + t_r[-1]) if middle is None else float(middle)
    query = t_r + float(offset) + float(rate) * (t_r - middle)
    p, qq, valid = interpolate_poses(t_m, pos, quat_np, query, max_gap)
    inside = (query >= t_m[0]) & (query <= t_m[-1])
    temp = None
    if tracker_temperature is not None:
        temp = np.interp(query, t_m, checked_array(tracker_temperature, "tracker temperature"))
    elif temperature is not None:
        temp = checked_array(temperature, "temperature")
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
        float(rate),
        middle,
    )

"""Clock jumps inside a pair of streams: the time offset steps between two rows.

The offset of :mod:`hybrid_pk.data.streams` is one constant. A clock that jumps inside
a recording (a resynchronisation, a sample dropped while its stamp ran on) puts the
rows after the jump on another offset; the one-offset registration only gets worse
(0.03 -> 0.3-0.5 mm RMS for a one-sample jump at 110 Hz) and the table is wrong after it.

Test. At the offset ``δ`` and the registered frames, robot row ``k`` has the position
residual ``r_k = f_k - m(t_k + δ)`` [m] (model point minus tracker point, tracker frame)
and the tracker point's velocity ``v_k = dm/dt`` [m/s]. If the offset changes by ``Δ``
from row ``j`` on, ``r`` steps by ``v_k Δ`` at ``j``. A model error moves ``r``
smoothly along the path (``q`` is continuous), noise is white. So for every row ``j``
the :data:`WINDOW` rows on either side are fitted, by weighted least squares, with a
straight line per coordinate plus the step ``[k >= j] v_k Δ_j``;
``z_j = Δ_j / std(Δ_j)``.

- Noise: ``σ_k² = σ_p² + σ_t² |v_k|²`` (tracker noise; time-stamp jitter, which moves a
  point along its motion), fitted to the second differences of ``r`` along ``v`` (their
  variance is ``6 σ²``; robust medians, so the jump itself does not count).
- Empirical null (Efron 2004): if the |z| of all rows spread more than a standard normal
  (their median above 0.674), they are divided by that ratio, so noise that is not
  white widens the null instead of raising alarms.
- Rule: the row of the largest ``|z_j|`` is a jump if it exceeds the two-sided normal
  quantile at ``ALPHA / m`` (Bonferroni over the ``m`` rows tried).

After each jump found, one Gauss-Newton fit of the shared base frame, tool point and one
offset per part (all rows) gives each part's offset and its standard error (residual std
times the root of its diagonal element of the inverse normal matrix); the test is then
repeated on the residuals at those offsets, so a large jump does not leave a part on a
wrong offset whose residual would look like more jumps (binary segmentation), up to
:data:`MAX_JUMPS`. A jump stays reported only if its two parts' offsets also differ by
more than the bound times the std of their difference (a step found at a wrong starting
offset, where the fit of both parts lands on one value, does not).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import correlate1d
from scipy.optimize import nnls

from hybrid_pk.data.interpolation import interpolate_poses
from hybrid_pk.data.point_frames import PointFrames
from hybrid_pk.distributions import norm_isf

__all__ = [
    "ALPHA",
    "MAX_JUMPS",
    "WINDOW",
    "ClockJump",
    "find_clock_jumps",
    "noise_rms",
    "step_scores",
    "tracker_motion",
]

# Rows on either side of a candidate jump: 2 x 16 rows x 3 coordinates = 96 equations
# for 7 unknowns, over 0.3 s at 110 Hz, short enough that a model error is a straight
# line in it (it changes with the pose: seconds).
WINDOW = 16
ALPHA = 1e-3  # chance of a false warning in one import without a jump
MAX_JUMPS = 5  # a stream with more is re-imported in parts, and each part is tested again
NOISE_BINS = 8  # speed classes of the noise fit: two unknowns, each class a robust median
_CHI2_1_MEDIAN = 0.454936  # median of a chi-square variable with one degree of freedom
_NORMAL_MAD = 0.674490  # median of |N(0, 1)|
# [m] a laser tracker's resolution (interferometer ~0.1 µm): a smaller noise estimate comes
# from noise-free data, where the rounding of the arithmetic would pass for a jump
SIGMA_FLOOR = 1e-7


@dataclass(frozen=True)
class ClockJump:
    """One step of the time offset inside the streams.

    Attributes:
        index: 0-based robot row of the first sample after the jump.
        t: [s] its robot time.
        step: [s] the local estimate of the change of offset (after - before).
        z: the step over its standard error (after the empirical-null scaling).
        threshold: the |z| the rule asks for.
        tried: rows tried (the Bonferroni count).
        before: ``(offset, std)`` [s] of the part before the jump.
        after: ``(offset, std)`` [s] of the part from the jump on.
        part_rows: ``(first, last)`` 0-based rows of the part before and of the part after.
    """

    index: int
    t: float
    step: float
    z: float
    threshold: float
    tried: int
    before: tuple[float, float]
    after: tuple[float, float]
    part_rows: tuple[tuple[int, int], tuple[int, int]]

    def summary(self, source: str = "robot stream", rows: np.ndarray | None = None) -> str:
        """One line naming ``source``, the row (file rows from ``rows``) and the offsets."""
        row = (lambda k: int(rows[k])) if rows is not None else (lambda k: k + 1)
        (a0, a1), (b0, b1) = self.part_rows
        return (
            f"{source}, row {row(self.index)} (t {self.t:.4f} s): the time offset jumps "
            f"from {_ms(*self.before)} (rows {row(a0)}-{row(a1)}) to {_ms(*self.after)} "
            f"(rows {row(b0)}-{row(b1)}): local step {1e3 * self.step:+.3f} ms, "
            f"|z| {abs(self.z):.1f} > {self.threshold:.2f} (two-sided, Bonferroni over "
            f"{self.tried} rows, alpha {ALPHA:g}); a clock jump in either stream: one "
            "offset does not fit both parts, split the streams there"
        )


def _ms(value: float, std: float) -> str:
    return f"{1e3 * value:.3f} ± {1e3 * std:.2g} ms"


def noise_variance(r: np.ndarray, v: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``(N,)`` variance [m²] of the residual along the motion, ``σ_p² + σ_t² |v_k|²``.

    Fitted (non-negative least squares) to the medians of the squared second differences
    along ``v`` in :data:`NOISE_BINS` speed classes; no row gets less than the slowest
    class shows (the line may cross zero below the speeds the data reach).
    """
    speed2 = (v * v).sum(-1)
    unit = v / np.maximum(np.sqrt(speed2), 1e-300)[:, None]
    d2 = r[2:] - 2 * r[1:-1] + r[:-2]
    inner = ok[2:] & ok[1:-1] & ok[:-2]
    e2 = ((unit[1:-1] * d2).sum(-1) ** 2 / 6)[inner]
    x = speed2[1:-1][inner]
    if x.size < 2 * NOISE_BINS:  # too few rows in a row of three: nothing is tried
        return np.full(len(r), np.inf)
    classes = np.array_split(np.argsort(x), NOISE_BINS)
    m = np.array([np.median(e2[c]) for c in classes]) / _CHI2_1_MEDIAN
    xb = np.array([x[c].mean() for c in classes])
    (sp2, st2), _ = nnls(np.stack([np.ones(NOISE_BINS), xb], -1), m)
    return np.maximum(np.maximum(sp2 + st2 * speed2, m.min()), SIGMA_FLOOR**2)


def step_scores(
    r: np.ndarray, v: np.ndarray, weight: np.ndarray, window: int = WINDOW
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local step ``Δ_j`` [s] of the offset at every row, its ``z``, and the rows tried.

    Args:
        r: ``(N, 3)`` residuals [m], model minus tracker.
        v: ``(N, 3)`` velocities [m/s] of the tracker point (``dr/d offset = -v``).
        weight: ``(N,)`` inverse noise variance [1/m²]; 0 leaves a row out.
        window: rows on either side.

    Returns:
        ``(step (N,), z (N,), tried (N,) bool)``; row ``j`` is tried when each side has
        at least half a window of rows.
    """
    tau = np.arange(-window, window, dtype=float)  # row j sits at tau = 0
    right = (tau >= 0).astype(float)
    used = weight > 0
    r, v = np.where(used[:, None], r, 0.0), np.where(used[:, None], v, 0.0)

    def win(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:  # sum_k kernel[k - j] x_k
        return correlate1d(x, kernel, mode="constant", cval=0.0)

    s0, s1, s2 = (win(weight, tau**p) for p in range(3))
    det = s0 * s2 - s1 * s1
    inv_det = np.divide(1.0, det, out=np.zeros_like(det), where=det > 0)

    def through_line(a0, a1, b0, b1):  # a^T G^-1 b with G the line's normal matrix
        return (a0 * (s2 * b0 - s1 * b1) + a1 * (s0 * b1 - s1 * b0)) * inv_det

    num = win(weight * (v * r).sum(-1), right)
    den = win(weight * (v * v).sum(-1), right)
    for c in range(3):
        a0, a1 = win(weight * v[:, c], right), win(weight * v[:, c], tau * right)
        b0, b1 = win(weight * r[:, c], np.ones_like(tau)), win(weight * r[:, c], tau)
        num -= through_line(a0, a1, b0, b1)
        den -= through_line(a0, a1, a0, a1)
    count = used.astype(float)
    tried = (win(count, 1.0 - right) >= window / 2) & (win(count, right) >= window / 2) & (den > 0)
    den = np.where(tried, den, 1.0)
    return np.where(tried, num / den, 0.0), np.where(tried, num / np.sqrt(den), 0.0), tried


def _part_offsets(
    frames: PointFrames,
    pose: tuple,
    measure: Callable,
    v: np.ndarray,
    part: np.ndarray,
    offsets: np.ndarray,
):
    """Gauss-Newton on the shared base frame, tool point and one offset per part
    (``part (K,)``: each row's part). Returns the offsets [s], their standard errors
    (residual std x root of the inverse normal matrix's diagonal) and the pose."""
    R_B, p_B, p_X = pose
    K, n = len(part), 9 + len(offsets)
    rows = np.arange(K)
    for _ in range(10):  # quadratic near the optimum: a few steps reach it
        r = frames.points(R_B, p_B, p_X) - measure(offsets[part])
        J = np.zeros((K, 3, n))
        J[:, :, :9] = frames.jacobian(R_B, p_X)
        J[rows, :, 9 + part] = -v  # r = f - m(t + offset): dr/d offset = -dm/dt
        Jf = J.reshape(-1, n)
        N = Jf.T @ Jf
        step = -np.linalg.solve(N, Jf.T @ r.reshape(-1))
        R_B, p_B, p_X = frames.update(R_B, p_B, p_X, step)
        offsets = offsets + step[9:]
        if float(np.abs(step[9:]).max()) < 1e-9:  # [s]: far below any offset's std
            break
    r = frames.points(R_B, p_B, p_X) - measure(offsets[part])
    s2 = float((r * r).sum()) / max(3 * K - n, 1)
    return offsets, np.sqrt(s2 * np.diag(np.linalg.inv(N))[9:]), (R_B, p_B, p_X)


def tracker_motion(tracker_t, position, at: np.ndarray, h: float, max_gap: float):
    """``(point (K, 3) [m], velocity (K, 3) [m/s], valid (K,))`` of the tracker stream at
    times ``at``: interpolated, and its central difference over ``± h`` [s]; valid where
    all three reads are (NaN elsewhere)."""
    m, _, ok = interpolate_poses(tracker_t, position, None, at, max_gap)
    ahead, _, ok_a = interpolate_poses(tracker_t, position, None, at + h, max_gap)
    back, _, ok_b = interpolate_poses(tracker_t, position, None, at - h, max_gap)
    return m, (ahead - back) / (2 * h), ok & ok_a & ok_b


class _JumpSearch:
    """The streams, the residuals at one offset per row, and the step test on them."""

    def __init__(self, robot_t, T_end, tracker_t, position, max_gap) -> None:
        self.t_r, self.T_end, self.t_m, self.pos = robot_t, T_end, tracker_t, position
        self.max_gap = max_gap
        # dr/d offset = -dm/dt: the tracker's velocity over one robot period, which a jump
        # of the robot clock leaves smooth (the model's, from the robot rows, would break)
        self.h = 0.5 * float(np.median(np.diff(robot_t)))

    def residuals(self, row_offset: np.ndarray, pose: tuple):
        """``(r (N, 3), v (N, 3), ok (N,))``: model minus tracker point [m], the tracker
        point's velocity [m/s], and the rows whose three tracker reads are valid."""
        m, v, ok = tracker_motion(self.t_m, self.pos, self.t_r + row_offset, self.h, self.max_gap)
        f = PointFrames(self.T_end, pose).points(*pose)
        return np.where(ok[:, None], f - m, 0.0), np.where(ok[:, None], v, 0.0), ok

    def scores(self, r: np.ndarray, v: np.ndarray, ok: np.ndarray):
        """``(step, z, tried)`` of every row, ``z`` after the empirical-null scaling."""
        weight = np.where(ok, 1.0 / noise_variance(r, v, ok), 0.0)
        step, z, tried = step_scores(r, v, weight)
        if tried.any():
            z /= max(float(np.median(np.abs(z[tried]))) / _NORMAL_MAD, 1.0)
        return step, z, tried

    def refit(self, cuts: list[int], start: np.ndarray, pose: tuple, v, ok):
        """Offsets, standard errors and pose of the parts between ``cuts``."""
        keep = np.flatnonzero(ok)
        part = np.searchsorted(np.asarray(cuts), keep, side="right")
        frames = PointFrames(self.T_end[keep], pose)
        t = self.t_r[keep]

        def measure(offsets: np.ndarray) -> np.ndarray:
            """Tracker points of the kept rows; one that leaves the stream counts as fitted."""
            p, _, inside = interpolate_poses(self.t_m, self.pos, None, t + offsets)
            return np.where(inside[:, None], p, frames.points(*frames.pose))

        return _part_offsets(frames, pose, measure, v[keep], part, start)

    def prune(self, cuts: list[int], found: dict, offsets, std, pose):
        """Drops (from ``cuts``, in place) the jumps whose parts' offsets do not differ by
        more than the bound times the std of the difference, weakest first, refitting
        after each. A jump found on a wrong starting offset is one: the fit of both parts
        moves them to the same value."""
        while cuts:
            ratio = np.abs(np.diff(offsets)) / np.hypot(std[:-1], std[1:])
            bound = np.array([found[c][2] for c in cuts])
            i = int(np.argmin(ratio / bound))
            if ratio[i] > bound[i]:
                break
            del cuts[i]
            offsets, std = np.delete(offsets, i + 1), np.delete(std, i + 1)
            part = np.searchsorted(np.asarray(cuts, dtype=int), np.arange(len(self.t_r)), "right")
            _, v, ok = self.residuals(offsets[part], pose)
            if cuts:
                offsets, std, pose = self.refit(cuts, offsets, pose, v, ok)
        return offsets, std


def noise_rms(
    streams: tuple[np.ndarray, torch.Tensor, np.ndarray, np.ndarray],
    offset: float,
    pose: tuple[np.ndarray, np.ndarray, np.ndarray],
    max_gap: float,
) -> float:
    """[m] RMS length of the noise of one residual vector that the rows show at ``offset``
    (``streams = (robot_t, T_end, tracker_t, position)`` and the rest as in
    :func:`find_clock_jumps`): ``sqrt(3 mean σ_k²)`` of the noise model above, white in
    three coordinates; inf with too few rows to tell."""
    search = _JumpSearch(*streams, max_gap)
    r, v, ok = search.residuals(np.full(len(streams[0]), float(offset)), pose)
    if not ok.any():
        return float("inf")
    return float(np.sqrt(3 * noise_variance(r, v, ok)[ok].mean()))


def find_clock_jumps(
    robot_t: np.ndarray,
    T_end: torch.Tensor,
    tracker_t: np.ndarray,
    position: np.ndarray,
    offset: float,
    pose: tuple[np.ndarray, np.ndarray, np.ndarray],
    max_gap: float,
) -> tuple[ClockJump, ...]:
    """Steps of the time offset inside the streams (see the module docstring).

    Args:
        robot_t: ``(N,)`` robot times [s].
        T_end: ``(N, 4, 4)`` nominal flange poses of the robot rows.
        tracker_t: ``(M,)`` tracker times [s]; ``position`` ``(M, 3)`` [m].
        offset: [s] the one offset (tracker time = robot time + offset).
        pose: ``(R_B, p_B, p_X)`` registered at ``offset``
            (:class:`~hybrid_pk.data.point_frames.PointFrames`).
        max_gap: [s] a tracker gap longer than this leaves a row out.

    Returns:
        The jumps found (at most :data:`MAX_JUMPS`), in row order; empty without one or
        with too few rows to try.
    """
    n = len(robot_t)
    search = _JumpSearch(robot_t, T_end, tracker_t, position, max_gap)
    cuts: list[int] = []
    found: dict[int, tuple[float, float, float, int]] = {}
    # the test linearises about the offset: start at the least-squares one of all rows
    _, v, ok = search.residuals(np.full(n, float(offset)), pose)
    if ok.sum() < 4 * WINDOW:
        return ()
    offsets, std, pose = search.refit(cuts, np.array([float(offset)]), pose, v, ok)
    for _ in range(MAX_JUMPS):
        part = np.searchsorted(np.asarray(cuts, dtype=int), np.arange(n), side="right")
        r, v, ok = search.residuals(offsets[part], pose)
        if ok.sum() < 4 * WINDOW:
            break
        step, z, tried = search.scores(r, v, ok)
        for c in cuts:  # a window holds one jump: none is tried beside one found
            tried[max(c - WINDOW, 0) : c + WINDOW + 1] = False
        m = int(tried.sum())
        if m == 0:
            break
        threshold = norm_isf(ALPHA / (2 * m))
        j = int(np.argmax(np.abs(z) * tried))
        if abs(z[j]) <= threshold:
            break
        found[j] = (float(step[j]), float(z[j]), threshold, m)
        i = int(np.searchsorted(cuts, j))  # the part that j splits
        cuts.insert(i, j)
        start = np.insert(offsets, i + 1, offsets[i] + step[j])
        offsets, std, pose = search.refit(cuts, start, pose, v, ok)
    offsets, std = search.prune(cuts, found, offsets, std, pose)
    bounds = [0, *cuts, n]
    return tuple(
        ClockJump(
            index=j,
            t=float(robot_t[j]),
            step=found[j][0],
            z=found[j][1],
            threshold=found[j][2],
            tried=found[j][3],
            before=(float(offsets[i]), float(std[i])),
            after=(float(offsets[i + 1]), float(std[i + 1])),
            part_rows=((bounds[i], j - 1), (j, bounds[i + 2] - 1)),
        )
        for i, j in enumerate(cuts)
    )

"""Joint trajectories of virtual measurement campaigns.

Every trajectory returns commanded joint values ``q (N, dof)`` [rad, m for prismatic]
within the URDF limits, in acquisition order:

- ``random``: uniform within the limits shrunk by a 2 % margin (the paper's virtual
  data, section 4.1);
- ``continuous``: a smooth joint path, a few random sinusoids per joint, sampled at
  10 Hz, with time stamps ``t (N,)`` [s];
- ``iso-cube``: the five poses P1..P5 of ISO 9283 in the cube's diagonal plane, visited
  in the standard's cycle P1 → P5 → P4 → P3 → P2 and repeated (pose accuracy AP and
  repeatability RP need repeated poses); the paper's validation trajectory;
- ``zigzag``: a Cartesian serpentine raster through the same cube at a fixed tool
  orientation; the paper's training trajectory (section 4.2).

The cube is a property of the robot (the same for every seed): axis-aligned with the
root frame, in front of the shoulder, side 0.3-0.5 of the reach (the largest that a
well-conditioned arm reaches; RX160: 0.55 m, UR10: 0.67 m), tool pointing down or
tilted 30° (:func:`iso_cube`). Cartesian targets are turned into joints by a small
damped least-squares solver on the nominal model, continued from one fixed elbow-up
seed (private; the product's IK module comes later).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import so3_exp, so3_log
from hybrid_pk.robot import Robot

__all__ = [
    "TRAJECTORIES",
    "IsoCube",
    "Trajectory",
    "continuous_trajectory",
    "iso_cube",
    "iso_cube_trajectory",
    "joint_box",
    "make_trajectory",
    "random_trajectory",
    "zigzag_trajectory",
]

TRAJECTORIES = ("random", "continuous", "iso-cube", "zigzag")

LIMIT_MARGIN = 0.02  # fraction of each joint range kept free at both ends
SAMPLE_RATE_HZ = 10.0  # of the continuous trajectory
ISO_CYCLE = (1, 5, 4, 3, 2)  # ISO 9283 test cycle P1 → P5 → P4 → P3 → P2 (→ P1 ...)
ISO_CORNER_FRACTION = 0.1  # P2..P5 lie 10 % of the plane diagonal away from its corners
CUBE_SIDES = (0.5, 0.45, 0.4, 0.35, 0.3)  # cube side / reach, largest first
CUBE_CENTRES = (0.55, 0.45)  # horizontal distance of the centre from the shoulder / reach
CUBE_TILTS_DEG = (0.0, 30.0, -30.0)  # tool tilt from pointing down, about the root y axis
IK_TOLERANCE = 1e-6  # [m] and [rad]: a target not reached this well is rejected
_PATH_STEP = 0.1  # [m] largest Cartesian step of the continuation from the seed
_MAX_JOINT_STEP = 0.3  # [rad] largest joint step of one damped least-squares iteration
_N_SEED_CANDIDATES = 256  # random starts of the search for the seed configuration
_MIN_SINGULAR_VALUE = 0.05  # of J (m/rad, rad/rad) over the cube: away from singularities
_GEOMETRY_SEED = 0  # the cube is a property of the robot, not of the campaign seed


class Trajectory(NamedTuple):
    """Commanded joint values in acquisition order.

    Attributes:
        q: ``(N, dof)`` joint values [rad, m for prismatic joints].
        t: ``(N,)`` time stamps [s], or None (static measurements).
        pose: ``(N,)`` long, ISO 9283 pose number 1..5 of each row (``iso-cube``), or None.
    """

    q: Tensor
    t: Tensor | None = None
    pose: Tensor | None = None


class IsoCube(NamedTuple):
    """The ISO 9283 test cube of a robot, in its root frame.

    Attributes:
        centre: ``(3,)`` [m] cube centre = pose P1.
        side: cube side [m].
        rotation: ``(3, 3)`` fixed orientation of the end link (tool down or tilted 30°).
        points: ``(5, 3)`` [m] positions of P1..P5 (row k is P(k+1)).
        q: ``(5, dof)`` joint values reaching P1..P5 on the nominal model [rad].
        q_centre: ``(dof,)`` the fixed elbow-up seed configuration at P1 [rad].
    """

    centre: Tensor
    side: float
    rotation: Tensor
    points: Tensor
    q: Tensor
    q_centre: Tensor


def _check_n(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise HybridPKError(f"number of samples must be a positive integer, got {n!r}")
    return n


def joint_box(robot: Robot, margin: float = LIMIT_MARGIN) -> tuple[Tensor, Tensor]:
    """Joint limits shrunk by ``margin`` of each range; unlimited joints use ±pi.

    Returns:
        ``(lower, upper)``, each ``(dof,)`` [rad or m].
    """
    lo, hi = robot.joint_limits
    lo = torch.where(torch.isfinite(lo), lo, -math.pi).to(robot.dtype)
    hi = torch.where(torch.isfinite(hi), hi, math.pi).to(robot.dtype)
    pad = margin * (hi - lo)
    return lo + pad, hi - pad


def random_trajectory(robot: Robot, n: int, generator: torch.Generator) -> Trajectory:
    """``n`` configurations uniform within the limits (2 % margin), in random order."""
    lo, hi = joint_box(robot)
    u = torch.rand(_check_n(n), robot.dof, generator=generator, dtype=robot.dtype)
    return Trajectory(lo + u * (hi - lo))


def continuous_trajectory(
    robot: Robot,
    n: int,
    generator: torch.Generator,
    rate_hz: float = SAMPLE_RATE_HZ,
    n_waves: int = 3,
) -> Trajectory:
    """A smooth joint path: per joint a sum of ``n_waves`` random sinusoids.

    Frequencies are 0.005-0.05 Hz, so a joint sweeps its range in tens of seconds;
    the sum is normalised into the limits (2 % margin).

    Args:
        rate_hz: sampling rate [Hz]; ``t = k / rate_hz`` [s].
    """
    n = _check_n(n)
    lo, hi = joint_box(robot)
    dt = robot.dtype
    t = torch.arange(n, dtype=dt) / rate_hz  # (N,) [s]
    shape = (robot.dof, n_waves)
    freq = 0.005 + 0.045 * torch.rand(shape, generator=generator, dtype=dt)  # [Hz]
    phase = 2 * math.pi * torch.rand(shape, generator=generator, dtype=dt)
    amp = 0.3 + 0.7 * torch.rand(shape, generator=generator, dtype=dt)
    waves = amp * torch.sin(2 * math.pi * freq * t[:, None, None] + phase)  # (N, dof, waves)
    s = waves.sum(-1) / amp.sum(-1)  # (N, dof) in [-1, 1]
    return Trajectory((lo + hi) / 2 + s * (hi - lo) / 2, t=t)


# ----------------------------------------------------------------------------- Cartesian


def _dls(
    robot: Robot,
    p_target: Tensor,
    R_target: Tensor | None,
    q: Tensor,
    n_iter: int,
    damping2: float = 1e-8,
) -> tuple[Tensor, Tensor, Tensor]:
    """Damped least-squares iterations on a batch; rows stop when converged.

    Returns:
        ``(q (M, dof), pos_err (M,) [m], rot_err (M,) [rad])`` at the returned ``q``.
    """
    lo, hi = joint_box(robot, 0.0)
    use_rot = R_target is not None and robot.dof >= 6
    for it in range(n_iter + 1):
        T = robot.fk(q)
        e = p_target - T[:, :3, 3]
        pos_err = e.norm(dim=-1)
        rot_err = torch.zeros_like(pos_err)
        if use_rot:
            w = so3_log(R_target @ T[:, :3, :3].transpose(-1, -2))
            rot_err = w.norm(dim=-1)
            e = torch.cat([e, w], -1)
        done = (pos_err < 1e-3 * IK_TOLERANCE) & (rot_err < 1e-3 * IK_TOLERANCE)
        if it == n_iter or bool(done.all()):
            break
        J = robot.jacobian(q)
        if not use_rot:
            J = J[:, :3, :]
        A = J @ J.transpose(-1, -2) + damping2 * torch.eye(J.shape[-2], dtype=J.dtype)
        dq = (J.transpose(-1, -2) @ torch.linalg.solve(A, e[..., None]))[..., 0]
        big = dq.abs().amax(-1, keepdim=True).clamp_min(1e-300)
        dq = dq * torch.clamp(_MAX_JOINT_STEP / big, max=1.0)
        q = torch.where(done[:, None], q, torch.minimum(torch.maximum(q + dq, lo), hi))
    return q, pos_err, rot_err


def _solve_positions(
    robot: Robot,
    p_target: Tensor,
    R_target: Tensor | None,
    q_init: Tensor,
    *,
    what: str = "target",
    max_iter: int = 50,
) -> Tensor:
    """Internal damped least-squares IK on the nominal model (not the product's IK).

    Solves every row of the batch from its own initial guess; joints stay within the
    URDF limits. Raises unless every target is reached to ``IK_TOLERANCE``.

    Args:
        p_target: ``(M, 3)`` end-link positions in the root frame [m].
        R_target: ``(3, 3)`` end-link orientation shared by all targets, or None for
            position only (always position only for fewer than 6 joints).
        q_init: ``(M, dof)`` initial joint values [rad].
        what: name of the targets in the error message.

    Returns:
        ``(M, dof)`` joint values [rad].
    """
    q, pos_err, rot_err = _dls(robot, p_target, R_target, q_init, max_iter)
    bad = (pos_err > IK_TOLERANCE) | (rot_err > IK_TOLERANCE)
    if bool(bad.any()):
        k = int(bad.nonzero()[0])
        xyz = ", ".join(f"{v:.4f}" for v in p_target[k].tolist())
        raise HybridPKError(
            f"{robot.name}: {what} at ({xyz}) m is not reachable with the nominal model "
            f"(residual {float(pos_err[k]) * 1e3:.3g} mm, "
            f"{math.degrees(float(rot_err[k])):.3g} deg after {max_iter} iterations)"
        )
    return q


def _reach_from(
    robot: Robot, q_seed: Tensor, points: Tensor, R: Tensor | None, what: str
) -> Tensor:
    """Joint values ``(M, dof)`` reaching ``points (M, 3)`` [m], continued from ``q_seed``.

    All targets start at the seed's position and move to their own in steps of at most
    ``_PATH_STEP`` (a few warm-started iterations per step, the whole batch at once),
    so every solution is on the seed's IK branch; then each is solved to tolerance.
    """
    M = points.shape[0]
    p0 = robot.fk(q_seed)[:3, 3]
    q = q_seed.expand(M, robot.dof).clone()
    k = max(1, math.ceil(float((points - p0).norm(dim=-1).max()) / _PATH_STEP))
    for s in range(1, k + 1):
        q = _dls(robot, p0 + (points - p0) * (s / k), R, q, n_iter=3)[0]
    return _solve_positions(robot, points, R, q, what=what)


def _wrap_revolute(robot: Robot, q: Tensor) -> Tensor:
    """Revolute joints whose range holds [-pi, pi] wrapped into it (the same pose)."""
    lo, hi = robot.joint_limits
    wrap = robot.revolute & (lo <= -math.pi) & (hi >= math.pi)
    return torch.where(wrap, torch.remainder(q + math.pi, 2 * math.pi) - math.pi, q)


def _elbow_up(robot: Robot, q: Tensor) -> Tensor:
    """``(M,)`` bool: the elbow (joint 3) lies above the shoulder (2) → wrist (5) line."""
    f = robot.link_frames(q)[..., :3, 3]
    s, e, w = f[..., 1, :], f[..., 2, :], f[..., min(4, robot.dof - 1), :]
    d = w - s
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=q.dtype)
    n = up - (d @ up)[..., None] * d
    return ((e - s) * n).sum(-1) > 1e-6


def iso_cube(robot: Robot) -> IsoCube:
    """The robot's ISO 9283 cube and the joint values of its poses P1..P5.

    A deterministic search, so a robot always gets the same cube: the side is the
    largest of ``CUBE_SIDES`` x reach (reach: the largest shoulder-to-flange distance)
    for which a 5 x 5 x 5 grid over the cube is reachable from one elbow-up seed at the
    centre with a well-conditioned Jacobian (smallest singular value at least
    ``_MIN_SINGULAR_VALUE`` everywhere). Set-ups tried for each side, in order: centre
    ``CUBE_CENTRES`` x reach in front of the shoulder (root +x) at shoulder height;
    tool pointing down, then tilted ±30° about the root y axis. Cached per geometry.

    Raises:
        HybridPKError: if the robot has fewer than 3 joints or no cube fits.
    """
    if robot.dof < 3:
        raise HybridPKError(f"{robot.name}: Cartesian trajectories need at least 3 joints")
    key = _geometry_key(robot)
    if key not in _CUBE_CACHE:
        if len(_CUBE_CACHE) > 8:  # fitted robots have new geometries; keep the cache small
            _CUBE_CACHE.clear()
        with torch.no_grad():
            _CUBE_CACHE[key] = _find_cube(robot)
    return _CUBE_CACHE[key]


_CUBE_CACHE: dict[tuple, IsoCube] = {}


def _geometry_key(robot: Robot) -> tuple:
    params = (robot.origin_xyz, robot.origin_rotvec, robot.axis, robot.lower, robot.upper)
    values = tuple(float(v) for p in params for v in p.detach().reshape(-1))
    return (robot.spec.urdf_path, robot.end_link, robot.dtype, values)


def _find_cube(robot: Robot) -> IsoCube:
    dt = robot.dtype
    gen = torch.Generator().manual_seed(_GEOMETRY_SEED)
    lo, hi = joint_box(robot)
    q_s = lo + torch.rand(1024, robot.dof, generator=gen, dtype=dt) * (hi - lo)
    frames = robot.link_frames(q_s)
    reach = float((frames[:, -1, :3, 3] - frames[:, 1, :3, 3]).norm(dim=-1).max())
    shoulder = robot.link_frames(torch.zeros(robot.dof, dtype=dt))[1, :3, 3]
    down = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dt))  # end-link z along -z
    g = torch.linspace(-0.5, 0.5, 5, dtype=dt)
    grid = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    seeds: dict[tuple[float, float], tuple[Tensor, Tensor, Tensor | None]] = {}
    for side_of_reach in CUBE_SIDES:
        side = side_of_reach * reach
        for c in CUBE_CENTRES:
            for tilt in CUBE_TILTS_DEG:
                if (c, tilt) not in seeds:
                    centre = shoulder + torch.tensor([c * reach, 0.0, 0.0], dtype=dt)
                    rot = so3_exp(torch.tensor([0.0, math.radians(tilt), 0.0], dtype=dt)) @ down
                    q0 = _seed_configuration(robot, centre, rot, q_s[:_N_SEED_CANDIDATES])
                    seeds[(c, tilt)] = (centre, rot, q0)
                centre, rot, q0 = seeds[(c, tilt)]
                if q0 is None:
                    continue
                try:
                    q = _reach_from(robot, q0, centre + side * grid, rot, "cube grid point")
                except HybridPKError:
                    continue
                sv = torch.linalg.svdvals(robot.jacobian(q))[:, -1]
                if float(sv.min()) < _MIN_SINGULAR_VALUE:
                    continue
                points = centre + _iso_points(side).to(dt)
                q_iso = _reach_from(robot, q0, points[1:], rot, "ISO pose")
                return IsoCube(centre, side, rot, points, torch.cat([q0[None], q_iso]), q0)
    raise HybridPKError(
        f"{robot.name}: no ISO 9283 cube of side >= {CUBE_SIDES[-1]:.2f} x reach "
        f"({reach:.2f} m) is reachable with a well-conditioned wrist"
    )


def _iso_points(side: float) -> Tensor:
    """``(5, 3)`` [m] offsets of P1..P5 from the cube centre.

    The test plane is the cube's diagonal plane through the edge at (y, z) = (-h, -h)
    and the opposite edge at (+h, +h); P2..P5 lie on its two diagonals,
    ``ISO_CORNER_FRACTION`` of the diagonal's length from the plane's corners.
    """
    h = side / 2
    corners = torch.tensor(
        [[h, h, h], [-h, h, h], [-h, -h, -h], [h, -h, -h]], dtype=torch.float64
    )  # plane corners next to P2, P3, P4, P5
    # A point 10 % of the diagonal from a corner is 80 % of the way from the centre.
    f = 1 - 2 * ISO_CORNER_FRACTION
    return torch.cat([torch.zeros(1, 3, dtype=torch.float64), f * corners])


def _seed_configuration(robot: Robot, p: Tensor, R: Tensor, candidates: Tensor) -> Tensor | None:
    """The fixed elbow-up configuration reaching ``(p, R)``, or None.

    Every candidate is solved in one batch. Among converged elbow-up solutions with
    joints at least 10 % of their range from the limits, the best conditioned (largest
    smallest singular value of J) wins.
    """
    M = candidates.shape[0]
    q, pos_err, rot_err = _dls(robot, p.expand(M, 3), R, candidates, 60, damping2=1e-4)
    ok = (pos_err < IK_TOLERANCE) & (rot_err < IK_TOLERANCE)
    if not bool(ok.any()):
        return None
    q = _wrap_revolute(robot, q[ok])
    lo, hi = joint_box(robot, 0.0)
    u = (q - lo) / (hi - lo)  # (M, dof) position in the range, 0..1
    good = _elbow_up(robot, q) & (torch.minimum(u, 1 - u).amin(-1) > 0.1)
    if not bool(good.any()):
        return None
    sv = torch.where(good, torch.linalg.svdvals(robot.jacobian(q))[:, -1], -1.0)
    best = q[int(sv.argmax())][None]
    return _solve_positions(robot, p[None], R, best, what="cube centre")[0]


def iso_cube_trajectory(robot: Robot, n: int) -> Trajectory:
    """ISO 9283 poses in the cycle P1, P5, P4, P3, P2, repeated to fill ``n`` rows."""
    n = _check_n(n)
    cube = iso_cube(robot)
    order = torch.tensor(ISO_CYCLE, dtype=torch.long).repeat(math.ceil(n / len(ISO_CYCLE)))[:n]
    return Trajectory(cube.q[order - 1].clone(), pose=order)


def zigzag_trajectory(robot: Robot, n: int) -> Trajectory:
    """A serpentine raster through the ISO cube at the cube's fixed tool orientation.

    ``m`` horizontal layers (bottom to top), each ``m`` lines along x stepping in y
    (alternating direction so the path is continuous), ``m = clip(round(n^(1/3)), 2, 8)``;
    the ``n`` rows are equally spaced along the path's length.
    """
    n = _check_n(n)
    cube = iso_cube(robot)
    m = int(min(8, max(2, round(n ** (1 / 3)))))
    h = cube.side / 2
    levels = torch.linspace(-h, h, m, dtype=torch.float64)
    corners = []
    for k, z in enumerate(levels.tolist()):
        ys = levels if k % 2 == 0 else levels.flip(0)
        for y in ys.tolist():
            xs = (-h, h) if len(corners) % 4 == 0 else (h, -h)
            corners += [[xs[0], y, z], [xs[1], y, z]]
    poly = cube.centre + torch.tensor(corners, dtype=torch.float64)  # (K, 3) polyline [m]
    seg = (poly[1:] - poly[:-1]).norm(dim=-1)
    s = torch.cat([torch.zeros(1, dtype=seg.dtype), seg.cumsum(0)])  # arc length [m]
    u = torch.linspace(0.0, float(s[-1]), n, dtype=torch.float64)
    idx = torch.searchsorted(s, u, right=True).clamp(1, len(s) - 1)
    w = ((u - s[idx - 1]) / (s[idx] - s[idx - 1]).clamp_min(1e-12))[:, None]
    points = poly[idx - 1] + w * (poly[idx] - poly[idx - 1])
    with torch.no_grad():
        q = _reach_from(robot, cube.q_centre, points, cube.rotation, "zigzag point")
    return Trajectory(q)


def make_trajectory(robot: Robot, kind: str, n: int, generator: torch.Generator) -> Trajectory:
    """Trajectory ``kind`` (one of :data:`TRAJECTORIES`) with ``n`` rows."""
    if kind == "random":
        return random_trajectory(robot, n, generator)
    if kind == "continuous":
        return continuous_trajectory(robot, n, generator)
    if kind == "iso-cube":
        return iso_cube_trajectory(robot, n)
    if kind == "zigzag":
        return zigzag_trajectory(robot, n)
    raise HybridPKError(f"unknown trajectory {kind!r}; choose one of {', '.join(TRAJECTORIES)}")

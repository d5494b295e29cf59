"""Virtual measurement campaigns: a robot with hidden errors, measured by a tracker.

One campaign (Ojer et al. 2024, section 4.1, generalised):

1. commanded joints ``q (N, dof)`` from a trajectory (``trajectories.py``);
2. conditions per row: payload [kg] (always), a smooth warm-up temperature drift [°C]
   (unless switched off), the approach direction of every joint from the acquisition
   order (backlash);
3. unknown frames drawn from the seed: a laser tracker 2-4 m from the robot at any
   yaw with a small tilt (``T_meas_root``) and a tool 50-200 mm from the flange with
   any rotation (``T_end_point``); identity when the frames are known. With a
   mounting (``mounting.py``: ceiling, wall, tilted base, any gravity) the tracker
   stands level and the base frame carries the mount rotation, and gravity in the
   robot frame follows the mount;
4. true poses ``T_meas_root · fk(q_true, params_true) · T_end_point`` from
   :class:`~hybrid_pk.effects.ExtendedModel` with the injected effects;
5. Gaussian measurement noise: per position coordinate ``noise_mm`` [mm]; orientation
   ``R · exp(w)`` with ``w`` per axis ``noise_deg`` [deg].

Every random draw comes from ``seed`` through independent streams (trajectory, frames,
payload, noise), so the same seed gives the same campaign and no global RNG is used.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from hybrid_pk.data.cells import ABSOLUTE_ZERO_C, MAX_PAYLOAD_KG, MAX_TEMPERATURE_C
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, Effect, ExtendedModel, Gravity, approach_direction
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.metrics import error_stats, pose_error
from hybrid_pk.geometry import (
    matrix_to_quat,
    quat_to_matrix,
    so3_exp,
    transform,
    transform_inverse,
)
from hybrid_pk.robot import Robot
from hybrid_pk.simulate.effect_specs import effect_entry, is_hidden_spec, parse_effects
from hybrid_pk.simulate.mounting import Mount, mount_from_gravity, parse_mount
from hybrid_pk.simulate.trajectories import TRAJECTORIES, Trajectory, iso_cube, make_trajectory

__all__ = ["SIMULATED_SOURCE", "random_frames", "simulate_campaign", "warm_up"]

SIMULATED_SOURCE = "<simulated>"  # MeasuredData.sources of a campaign not yet written
TRACKER_DISTANCE_M = (2.0, 4.0)  # horizontal distance of the tracker from the robot [m]
TRACKER_HEIGHT_M = (-0.5, 1.0)  # height of the tracker above the robot root [m]
TRACKER_TILT_DEG = 2.0  # largest roll/pitch of the tracker frame [deg]
TOOL_LENGTH_M = (0.05, 0.2)  # distance of the measured point from the flange [m]
TOOL_CONE_DEG = 60.0  # largest angle of the tool offset from the flange z axis [deg]
PAYLOAD_BLOCKS = 8  # a payload range is measured in this many blocks of rows
_CHUNK = 4096  # rows per model evaluation (progress bar steps)
_STREAMS = ("trajectory", "frames", "payload", "noise")


def _streams(seed: int) -> dict[str, torch.Generator]:
    """Independent torch generators per purpose, spawned from ``seed``."""
    children = np.random.SeedSequence(int(seed)).spawn(len(_STREAMS))
    return {
        name: torch.Generator().manual_seed(int(child.generate_state(1, np.uint64)[0] >> 1))
        for name, child in zip(_STREAMS, children, strict=True)
    }


def _uniform(gen: torch.Generator, lo: float, hi: float, dtype: torch.dtype) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=gen, dtype=dtype))


def random_frames(
    generator: torch.Generator, dtype: torch.dtype = torch.float64, level: bool = False
) -> tuple[Tensor, Tensor]:
    """A tracker somewhere in the room and a tool on the flange.

    The tracker stands ``TRACKER_DISTANCE_M`` from the robot root (any azimuth), at
    ``TRACKER_HEIGHT_M``, with any yaw and up to ``TRACKER_TILT_DEG`` roll and pitch.
    The measured point lies ``TOOL_LENGTH_M`` from the flange, within
    ``TOOL_CONE_DEG`` of its z axis; the tool frame has a uniformly random rotation.
    ``level``: no roll or pitch (the draws are made all the same, so the other frames
    of a seed do not change).

    Returns:
        ``(T_meas_root, T_end_point)``, each ``(4, 4)`` [m].
    """
    g = generator
    dist = _uniform(g, *TRACKER_DISTANCE_M, dtype)
    azimuth = _uniform(g, 0.0, 2 * math.pi, dtype)
    height = _uniform(g, *TRACKER_HEIGHT_M, dtype)
    p_root_meas = torch.tensor(
        [dist * math.cos(azimuth), dist * math.sin(azimuth), height], dtype=dtype
    )
    tilt = math.radians(TRACKER_TILT_DEG)
    roll, pitch = (_uniform(g, -tilt, tilt, dtype) for _ in range(2))
    if level:
        roll = pitch = 0.0
    yaw = _uniform(g, -math.pi, math.pi, dtype)
    R_root_meas = (
        so3_exp(torch.tensor([0.0, 0.0, yaw], dtype=dtype))
        @ so3_exp(torch.tensor([0.0, pitch, 0.0], dtype=dtype))
        @ so3_exp(torch.tensor([roll, 0.0, 0.0], dtype=dtype))
    )
    T_meas_root = transform_inverse(transform(R_root_meas, p_root_meas))

    length = _uniform(g, *TOOL_LENGTH_M, dtype)
    cos_cone = _uniform(g, math.cos(math.radians(TOOL_CONE_DEG)), 1.0, dtype)
    phi = _uniform(g, 0.0, 2 * math.pi, dtype)
    sin_cone = math.sqrt(1 - cos_cone**2)
    offset = length * torch.tensor(
        [sin_cone * math.cos(phi), sin_cone * math.sin(phi), cos_cone], dtype=dtype
    )
    quat = torch.randn(4, generator=g, dtype=dtype)  # uniform on SO(3) once normalised
    T_end_point = transform(quat_to_matrix(quat), offset)
    return T_meas_root, T_end_point


def warm_up(n: int, lo: float, hi: float, dtype: torch.dtype = torch.float64) -> Tensor:
    """``(n,)`` [°C]: a warm-up from ``lo`` to ``hi`` over the campaign (exponential, 1/3)."""
    s = torch.linspace(0.0, 1.0, n, dtype=dtype) if n > 1 else torch.zeros(1, dtype=dtype)
    return lo + (hi - lo) * (1 - torch.exp(-3 * s)) / (1 - math.exp(-3))


def _payloads(n: int, payload: float, payload_range, gen, dtype) -> Tensor:
    """``(n,)`` [kg]: constant, or blocks of rows at levels spread over the range."""
    if payload_range is None:
        return torch.full((n,), float(payload), dtype=dtype)
    lo, hi = payload_range
    blocks = min(PAYLOAD_BLOCKS, n)
    levels = torch.linspace(lo, hi, blocks, dtype=dtype)[torch.randperm(blocks, generator=gen)]
    block_of_row = torch.arange(n) * blocks // n
    return levels[block_of_row]


def _frame_arg(T: Tensor, drawn: Tensor, name: str) -> Tensor:
    """A given frame: a ``(4, 4)`` transform, or a ``(3,)`` translation with the drawn
    rotation."""
    T = torch.as_tensor(T, dtype=drawn.dtype)
    if T.shape == (3,):
        T = transform(drawn[:3, :3], T)
    if T.shape != (4, 4) or not bool(torch.isfinite(T).all()):
        raise HybridPKError(
            f"{name} must be a finite (4, 4) transform or (3,) translation [m], "
            f"got shape {tuple(T.shape)}"
        )
    R = T[:3, :3]
    if float((R.T @ R - torch.eye(3, dtype=R.dtype)).abs().max()) > 1e-6:
        raise HybridPKError(f"{name}: the rotation part of the transform is not orthonormal")
    return T


def _check_args(
    n, seed, noise_mm, noise_deg, trajectory, payload, payload_range, temperature_range
):
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise HybridPKError(f"n must be a positive number of rows, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise HybridPKError(f"seed must be an integer >= 0, got {seed!r}")
    for name, v in (("noise_mm", noise_mm), ("noise_deg", noise_deg), ("payload", payload)):
        if not (math.isfinite(v) and v >= 0):
            raise HybridPKError(f"{name} must be a finite number >= 0, got {v}")
    if trajectory not in (*TRAJECTORIES, "poses"):
        raise HybridPKError(
            f"unknown trajectory {trajectory!r}; choose one of {', '.join(TRAJECTORIES)}"
        )
    if payload_range is not None:
        lo, hi = payload_range
        if not (0 <= lo <= hi and math.isfinite(hi)):
            raise HybridPKError(f"payload range must be 0 <= LO <= HI [kg], got {lo}, {hi}")
        if payload:
            raise HybridPKError("give a payload or a payload range, not both")
    top = max(payload, payload_range[1] if payload_range else 0.0)
    if top > MAX_PAYLOAD_KG:  # a table that no reader would take back
        raise HybridPKError(f"payload {top:g} kg: no arm carries more than {MAX_PAYLOAD_KG:g} kg")
    if temperature_range is not None:
        lo, hi = temperature_range
        if not (
            math.isfinite(lo)
            and math.isfinite(hi)
            and ABSOLUTE_ZERO_C <= lo <= hi <= MAX_TEMPERATURE_C
        ):
            raise HybridPKError(
                f"temperature range must be {ABSOLUTE_ZERO_C:g} <= LO <= HI <= "
                f"{MAX_TEMPERATURE_C:g} [°C], got {lo}, {hi}"
            )


def _mounting(mount) -> Mount | None:
    if mount is None or isinstance(mount, Mount):
        return mount
    if isinstance(mount, Gravity):
        return mount_from_gravity(mount)
    return parse_mount(mount)


def _check_poses(robot: Robot, poses: Tensor, n: int | None) -> Tensor:
    q = torch.as_tensor(poses).to(robot.dtype)
    if q.ndim != 2 or q.shape[1] != robot.dof or q.shape[0] == 0:
        raise HybridPKError(f"poses must be (N, {robot.dof}) joint values, got {tuple(q.shape)}")
    if n is not None and n != q.shape[0]:
        raise HybridPKError(f"n = {n} but {q.shape[0]} poses were given; give one or the other")
    if not bool(torch.isfinite(q).all()):
        raise HybridPKError("poses must be finite joint values")
    return q


def simulate_campaign(
    robot: Robot,
    n: int | None,
    effects: str | Sequence[Effect],
    *,
    poses: Tensor | None = None,
    noise_mm: float,
    noise_deg: float = 0.0,
    trajectory: str = "random",
    payload: float = 0.0,
    payload_range: tuple[float, float] | None = None,
    temperature_range: tuple[float, float] | None = (20.0, 28.0),
    position_only: bool = False,
    known_frames: bool = False,
    mount: str | Mount | Gravity | None = None,
    seed: int = 0,
    progress: bool = False,
    base: Tensor | None = None,
    tool: Tensor | None = None,
) -> tuple[MeasuredData, dict]:
    """Simulate a measurement campaign of ``robot`` with hidden error effects.

    Args:
        robot: the nominal robot; the campaign measures it with ``effects`` added.
        n: number of rows N (None with ``poses``: one row per pose).
        effects: effects to inject, or an ``--effects`` text (:func:`parse_effects`).
        poses: ``(N, dof)`` commanded joints [rad, m] to measure at, in this order
            (e.g. a planned campaign), instead of a ``trajectory``.
        noise_mm: std of the Gaussian noise of each position coordinate [mm].
        noise_deg: std of the noise rotation vector, per axis [deg].
        trajectory: one of ``random``, ``continuous``, ``iso-cube``, ``zigzag``.
        payload: mass at the flange [kg], the same for every row.
        payload_range: ``(lo, hi)`` [kg]: blocks of rows at payloads spread over it.
        temperature_range: ``(start, end)`` [°C] of a warm-up drift over the campaign;
            None writes no temperature column.
        position_only: write no orientation (``qw..qz``).
        known_frames: measure in the robot root frame at the flange (identity frames).
        mount: ``--mount`` text (``ceiling``, ``wall``, ``tilt:DEG[,AZ]``, ``floor``), a
            :class:`Mount` or a root-frame :class:`Gravity`: the tracker is then level,
            the truth base frame holds the mount rotation. None: upright, the tracker
            tilted up to ``TRACKER_TILT_DEG`` (as before mountings existed).
        seed: every random draw comes from it.
        progress: show a progress bar on stderr when it takes more than 2 s.
        base, tool: true ``T_meas_root`` / ``T_end_point`` instead of the drawn ones:
            ``(4, 4)``, or a ``(3,)`` translation [m] with the drawn rotation.

    Returns:
        ``(data, truth)``: the measured table (float64, one file index, source
        ``"<simulated>"``) and the truth dict written as ``FILE.truth.json``.

    Raises:
        HybridPKError: bad arguments, an effect whose condition is missing, or a
            Cartesian trajectory the robot cannot reach.
    """
    if poses is not None:
        poses = _check_poses(robot, poses, n)
        n, trajectory = poses.shape[0], "poses"
    _check_args(n, seed, noise_mm, noise_deg, trajectory, payload, payload_range, temperature_range)
    n = int(n)
    streams = _streams(seed)
    spec = effects if isinstance(effects, str) else None
    mean_payload = payload if payload_range is None else sum(payload_range) / 2
    mounting = _mounting(mount)
    gravity = Gravity() if mounting is None else mounting.gravity
    effects = _effects(robot, effects, seed, mean_payload, gravity, temperature_range)

    dt = robot.dtype
    with torch.no_grad():
        traj = _commanded(robot, poses, trajectory, n, streams["trajectory"])
        q = traj.q.to(dt)
        base, tool = _true_frames(streams["frames"], dt, mounting, known_frames, base, tool)
        cond = _conditions(q, payload, payload_range, temperature_range, streams["payload"])
        true_model = ExtendedModel(robot, effects, base=base, tool=tool, gravity=gravity)
        nominal_model = ExtendedModel(robot, [], base=base, tool=tool)
        T_true, T_nominal = _true_and_nominal(true_model, nominal_model, q, cond, progress)
        position, quat = _measure(T_true, noise_mm, noise_deg, position_only, streams["noise"])

    data = _table(robot, q, position, quat, traj.t, cond)
    truth = {
        "robot": robot.name,
        "n": n,
        "seed": int(seed),
        "trajectory": trajectory,
        "noise_mm": float(noise_mm),
        "noise_deg": float(noise_deg),
        "payload": float(mean_payload),
        "payload_range": _float_list(payload_range),
        "temperature_range": _float_list(temperature_range),
        "position_only": bool(position_only),
        "known_frames": bool(known_frames),
        "mount": None if mounting is None else mounting.to_dict(),
        "gravity": list(gravity.vector),
        "effects_spec": spec,
        "effects_hidden": bool(spec is not None and is_hidden_spec(spec)),
        **_truth_of_model(robot, effects, base, tool, T_true, T_nominal, trajectory),
    }
    return data, truth


def _commanded(robot: Robot, poses: Tensor | None, trajectory: str, n: int, gen) -> Trajectory:
    """The commanded rows: the given ``poses`` in order, else a drawn ``trajectory``."""
    if poses is None:
        return make_trajectory(robot, trajectory, n, gen)
    return Trajectory(poses)


def _conditions(q: Tensor, payload, payload_range, temperature_range, gen) -> Conditions:
    """The campaign's conditions of rows ``q``: payloads (blocks over a range), the
    warm-up temperature drift and the approach directions."""
    n, dt = q.shape[0], q.dtype
    return Conditions(
        payload=_payloads(n, payload, payload_range, gen, dt),
        temperature=None if temperature_range is None else warm_up(n, *temperature_range, dt),
        direction=approach_direction(q),
    )


def _float_list(values: tuple[float, float] | None) -> list[float] | None:
    """A range argument as plain floats for the truth dict (None stays None)."""
    return None if values is None else [float(v) for v in values]


def _true_frames(gen, dtype, mounting: Mount | None, known_frames: bool, base, tool):
    """The truth ``(T_meas_root, T_end_point)``: drawn (turned by the mounting), the
    identity with ``known_frames``, or the given ``base`` / ``tool``."""
    drawn_base, drawn_tool = random_frames(gen, dtype, level=mounting is not None)
    if mounting is not None:  # T_meas_root = T_meas_world · T_world_root
        mount_rotation = transform(mounting.rotation.to(dtype), torch.zeros(3, dtype=dtype))
        drawn_base = drawn_base @ mount_rotation
    if known_frames:
        drawn_base = drawn_tool = torch.eye(4, dtype=dtype)
    base = drawn_base if base is None else _frame_arg(base, drawn_base, "base")
    tool = drawn_tool if tool is None else _frame_arg(tool, drawn_tool, "tool")
    return base, tool


def _measure(T_true: Tensor, noise_mm: float, noise_deg: float, position_only: bool, gen):
    """Measured ``(position (N, 3), quat (N, 4) or None)``: the true poses with Gaussian
    position noise and a Gaussian noise rotation, drawn from ``gen``."""
    n, dt = T_true.shape[0], T_true.dtype
    position = T_true[:, :3, 3] + 1e-3 * noise_mm * torch.randn(n, 3, generator=gen, dtype=dt)
    w = math.radians(noise_deg) * torch.randn(n, 3, generator=gen, dtype=dt)
    quat = None if position_only else matrix_to_quat(T_true[:, :3, :3] @ so3_exp(w))
    return position, quat


def _effects(robot, effects, seed, payload, gravity, temperature_range) -> list[Effect]:
    """The effects to inject (an ``--effects`` text parsed), checked for their conditions."""
    if isinstance(effects, str):
        effects = parse_effects(robot, effects, seed=seed, payload=payload, gravity=gravity)
    effects = list(effects)
    for e in effects:
        if e.needs == "temperature" and temperature_range is None:
            raise HybridPKError(f"{e.label} needs a temperature; give a temperature range")
    return effects


def _table(robot, q, position, quat, t, cond: Conditions) -> MeasuredData:
    """The simulated rows as one measured file."""
    n = q.shape[0]
    return MeasuredData(
        q=q,
        position=position,
        quat=quat,
        joint_names=tuple(robot.joint_names),
        file_index=torch.zeros(n, dtype=torch.long),
        rows=torch.arange(1, n + 1),
        sources=(SIMULATED_SOURCE,),
        t=t,
        temperature=cond.temperature,
        payload=cond.payload,
    )


def _true_and_nominal(true_model, nominal_model, q: Tensor, cond: Conditions, progress: bool):
    """Poses ``(N, 4, 4)`` of the robot with its effects and of the nominal one."""
    n, dt = q.shape[0], q.dtype
    T_true = torch.empty(n, 4, 4, dtype=dt)
    T_nominal = torch.empty(n, 4, 4, dtype=dt)
    with tqdm(
        total=n, desc="simulate", unit="row", delay=2.0, file=sys.stderr, disable=not progress
    ) as bar:
        for start in range(0, n, _CHUNK):
            rows = slice(start, min(start + _CHUNK, n))
            T_true[rows] = true_model(q[rows], cond.subset(rows))
            T_nominal[rows] = nominal_model(q[rows])
            bar.update(rows.stop - rows.start)
    return T_true, T_nominal


def _truth_of_model(robot, effects, base, tool, T_true, T_nominal, trajectory) -> dict:
    """Effects, frames, dataset error (and ISO cube) entries of the truth JSON."""
    err = pose_error(T_true, T_nominal)
    truth = {
        "effects": [effect_entry(e) for e in effects],
        "base_frame": base.to(torch.float64).tolist(),
        "tool_frame": tool.to(torch.float64).tolist(),
        "dataset_error": {
            "position_mm": error_stats(err.position_mm).to_dict(),
            "orientation_deg": error_stats(err.orientation_deg).to_dict(),
        },
    }
    if trajectory in ("iso-cube", "zigzag"):
        cube = iso_cube(robot)
        truth["iso_cube"] = {
            "centre": cube.centre.tolist(),
            "side": float(cube.side),
            "rotation": cube.rotation.tolist(),
            "points": cube.points.tolist(),  # P1..P5 of the end link, root frame [m]
        }
    return truth

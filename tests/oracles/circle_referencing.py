"""Initial base and tool frames: the paper's referencing, and registration of any table.

Two ways to a first estimate of ``T_meas_root`` (where the tracker stands) and
``T_end_point`` (where the target sits on the flange); the least-squares fit
(:func:`hybrid_pk.calibration.fit.fit`) starts from either.

**Referencing by circles** (Ojer et al. 2024, section 4.2, after their ref. [38]):
move single joints one at a time while the tracker records the target. Each sweep
traces a circle: its plane's normal is the joint axis and its centre lies on it
(:func:`fit_circle`). The axes of two non-parallel joints (joints 1 and 2) measured
in the tracker frame, matched with the same axes of the nominal model in the robot
root frame, fix the rigid base frame (:func:`base_from_axes`): directions give the
rotation, the two axis lines the translation (where the paper intersects axis 1
with a measured base plane, the second axis does the same job here, so no plane
measurement is needed). The paper finds the tool frame from sweeps of joints 5 and
6; with the base known the tool follows directly from every measured sweep point by
least squares (:func:`tool_from_base`), which uses the same data.

Use it when a campaign starts with dedicated sweeps (the usual metrology
procedure): it needs no orientation data, few points (~10 per sweep), and it gives
frames before any calibration table exists. :func:`find_single_joint_sweeps` picks
such sweeps out of a table.

**Closed-form registration** (:func:`registration_guess`): from any table with
poses spread over the workspace, solve ``T_meas_i ≈ B F_i X`` in closed form (hand-eye
rotation by Kabsch for full poses; alternating Kabsch for positions only, see
:mod:`hybrid_pk.geometry.registration`). Use it for every table without sweeps,
per file when the tracker moved between files. Both give a start within a few mm and
a fraction of a degree of the optimum on real data, which is all LM needs: an
identity start, by contrast, can converge to the tool rotation flipped by 180°.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.errors import DataError
from hybrid_pk.geometry import quat_to_matrix, transform
from hybrid_pk.geometry.registration import kabsch, register_frames

__all__ = [
    "Circle",
    "FrameGuess",
    "JointSweep",
    "Referencing",
    "base_from_axes",
    "find_single_joint_sweeps",
    "fit_circle",
    "reference_from_sweeps",
    "registration_guess",
    "tool_from_base",
]


@dataclass(frozen=True)
class Circle:
    """A circle in space fitted to points.

    Attributes:
        centre: ``(3,)`` [m], on the rotation axis.
        normal: ``(3,)`` unit normal of the plane = axis direction (sign: right-hand
            rule with the point order, when known).
        radius: [m].
        rms_mm: RMS distance of the points from the circle [mm].
        arc_deg: angle spanned by the points about the centre [deg].
    """

    centre: np.ndarray
    normal: np.ndarray
    radius: float
    rms_mm: float
    arc_deg: float


def fit_circle(points: Any, iterations: int = 20) -> Circle:
    """Least-squares circle through ``points (K, 3)`` [m], K >= 3.

    The plane is the total-least-squares plane (SVD); in it an algebraic circle fit
    (Kåsa) starts a Gauss-Newton fit of the geometric distances, which is unbiased on
    short arcs. The normal is oriented so that the points turn positively about it in
    their given order.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise DataError(f"a circle needs (K >= 3, 3) points, got shape {p.shape}")
    mean = p.mean(0)
    _, s, Vt = np.linalg.svd(p - mean, full_matrices=False)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise DataError("the points lie on a line: the joint did not turn (no circle)")
    e1, e2, n = Vt[0], Vt[1], Vt[2]
    uv = np.stack([(p - mean) @ e1, (p - mean) @ e2], -1)
    # Kåsa: u² + v² = 2 a u + 2 b v + c
    A = np.column_stack([2 * uv, np.ones(len(uv))])
    a, b, c = np.linalg.lstsq(A, (uv**2).sum(-1), rcond=None)[0]
    centre2, radius = np.array([a, b]), float(np.sqrt(max(c + a * a + b * b, 0.0)))
    for _ in range(iterations):  # geometric fit: r_k = |uv_k - centre| - radius
        d = uv - centre2
        dist = np.linalg.norm(d, axis=-1).clip(min=1e-300)
        J = np.column_stack([-d / dist[:, None], -np.ones(len(d))])
        step = np.linalg.lstsq(J, -(dist - radius), rcond=None)[0]
        centre2, radius = centre2 + step[:2], radius + step[2]
        if np.abs(step).max() < 1e-15:
            break
    centre = mean + centre2[0] * e1 + centre2[1] * e2
    rel = p - centre
    in_plane = rel - np.outer(rel @ n, n)
    res = np.sqrt((np.linalg.norm(in_plane, axis=-1) - radius) ** 2 + (rel @ n) ** 2)
    turn = np.cross(rel[:-1], rel[1:]) @ n
    if turn.sum() < 0:
        n = -n
    ang = np.arctan2(
        np.cross(in_plane[:-1], in_plane[1:]) @ n, (in_plane[:-1] * in_plane[1:]).sum(-1)
    )
    return Circle(
        centre, n, abs(radius), 1e3 * float(np.sqrt((res**2).mean())), float(np.degrees(ang.sum()))
    )


@dataclass(frozen=True)
class JointSweep:
    """Measured points while one joint turns and the others stand still.

    Attributes:
        joint: the swept joint's name.
        q: ``(K, dof)`` joint values of the sweep [rad], in acquisition order.
        position: ``(K, 3)`` measured points in the tracker frame [m].
        quat: ``(K, 4)`` measured orientations ``(w, x, y, z)``, or None.
    """

    joint: str
    q: Tensor
    position: Tensor
    quat: Tensor | None = None


def find_single_joint_sweeps(
    data: MeasuredData, *, min_rows: int = 5, tol: float = 1e-9, min_turn: float = 0.1
) -> list[JointSweep]:
    """Runs of consecutive rows (one file) where only one joint changes.

    Args:
        data: measured rows in acquisition order.
        min_rows: shortest run kept.
        tol: [rad] change below which a joint counts as standing still.
        min_turn: [rad] smallest range the moving joint must span.
    """
    q = data.q.numpy()
    if data.n < min_rows:
        return []
    moving = np.abs(np.diff(q, axis=0)) > tol  # (N-1, dof)
    single = (moving.sum(-1) == 1) & (np.diff(data.file_index.numpy()) == 0)
    which = np.where(single, moving.argmax(-1), -1)
    sweeps, start = [], 0
    for k in range(1, len(which) + 1):
        if k == len(which) or which[k] != which[start] or which[start] < 0:
            stop = k  # steps start..stop-1 -> rows start..stop
            j = which[start]
            rows = np.arange(start, stop + 1)
            if j >= 0 and len(rows) >= min_rows and np.ptp(q[rows, j]) >= min_turn:
                sweeps.append(
                    JointSweep(
                        data.joint_names[j],
                        data.q[rows],
                        data.position[rows],
                        None if data.quat is None else data.quat[rows],
                    )
                )
            start = k
    return sweeps


def _model_axis(robot, joint: str, q: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Point on and direction of ``joint``'s axis at configuration ``q`` (root frame)."""
    names = list(robot.joint_names)
    if joint not in names:
        raise DataError(f"unknown joint {joint!r}; joints: {', '.join(names)}")
    i = names.index(joint)
    with torch.no_grad():
        frames = robot.link_frames(q.to(robot.dtype))
        axis = robot.axis[i] / robot.axis[i].norm()
        d = frames[i, :3, :3] @ axis.to(frames.dtype)
    return frames[i, :3, 3].double().numpy(), d.double().numpy()


def base_from_axes(
    measured: Sequence[tuple[np.ndarray, np.ndarray]],
    model: Sequence[tuple[np.ndarray, np.ndarray]],
) -> Tensor:
    """Rigid ``T_meas_root (4, 4)`` mapping model axis lines onto measured ones.

    Args:
        measured: ``(point, direction)`` of each axis in the tracker frame [m].
        model: the same axes in the robot root frame.

    The rotation aligns the directions (Kabsch, no translation); the translation puts
    every model line on its measured line in least squares. Needs two non-parallel
    axes.
    """
    if len(measured) != len(model) or len(measured) < 2:
        raise DataError("the base frame needs the axes of at least two joints")
    dm = torch.as_tensor(np.stack([d for _, d in measured]))
    dr = torch.as_tensor(np.stack([d for _, d in model]))
    cross = torch.linalg.cross(dr[:, None], dr[None], dim=-1).norm(dim=-1).max()
    if float(cross) < 0.1:
        raise DataError("the swept joint axes are (nearly) parallel: sweep two crossing axes")
    R, _ = kabsch(dr, dm, with_translation=False)
    R = R.numpy()
    lhs, rhs = np.zeros((3, 3)), np.zeros(3)
    for (c_m, n_m), (o_r, _) in zip(measured, model, strict=True):
        P = np.eye(3) - np.outer(n_m, n_m)  # distance from the measured line
        lhs += P
        rhs += P @ (c_m - R @ o_r)
    p = np.linalg.solve(lhs, rhs)
    return transform(torch.as_tensor(R), torch.as_tensor(p))


def tool_from_base(
    robot, base: Tensor, q: Tensor, position: Tensor, quat: Tensor | None = None
) -> Tensor:
    """``T_end_point (4, 4)`` by least squares given the base frame.

    ``p_X = mean_i (B F_i)^-1 p_i`` (exact least squares: rigid maps keep distances);
    the rotation is the chordal mean of ``(R_B R_F_i)^T R_i`` (identity without
    orientation data).
    """
    with torch.no_grad():
        F = base.to(robot.dtype) @ robot.fk(q.to(robot.dtype))
    R_F, p_F = F[:, :3, :3], F[:, :3, 3]
    local = ((position.to(F.dtype) - p_F)[:, None, :] @ R_F)[:, 0]  # R_F^T (p - p_F)
    R_X = torch.eye(3, dtype=F.dtype)
    if quat is not None:
        M = (R_F.transpose(-1, -2) @ quat_to_matrix(quat.to(F.dtype))).sum(0)
        U, _, Vt = torch.linalg.svd(M)
        D = torch.diag(torch.tensor([1.0, 1.0, float(torch.linalg.det(U @ Vt))], dtype=F.dtype))
        R_X = U @ D @ Vt
    return transform(R_X, local.mean(0))


@dataclass(frozen=True)
class Referencing:
    """Result of :func:`reference_from_sweeps`.

    Attributes:
        base: ``(4, 4)`` ``T_meas_root`` [m].
        tool: ``(4, 4)`` ``T_end_point`` [m].
        circles: the circle fitted to each sweep, in order.
        joints: the swept joint of each circle.
    """

    base: Tensor
    tool: Tensor
    circles: tuple[Circle, ...]
    joints: tuple[str, ...]

    def lines(self) -> list[str]:
        """One line per sweep: radius, arc, fit residual."""
        return [
            f"{j}: circle radius {1e3 * c.radius:.2f} mm over {c.arc_deg:.1f} deg, "
            f"residual {c.rms_mm:.4f} mm RMS"
            for j, c in zip(self.joints, self.circles, strict=True)
        ]


def reference_from_sweeps(
    robot, sweeps: Sequence[JointSweep], base_joints: Sequence[str] | None = None
) -> Referencing:
    """Base frame from the circles of single-joint sweeps, tool frame from all points.

    Args:
        robot: nominal robot (its axes in the root frame are the reference).
        sweeps: measured single-joint sweeps (e.g. joints 1 and 2, optionally 5, 6).
        base_joints: joints whose axes fix the base (default: the first two joints of
            the chain among the swept ones). Only their sweeps enter the base frame;
            further joints (later in the chain) carry more kinematic error.
    """
    if not sweeps:
        raise DataError("no single-joint sweeps given")
    names = list(robot.joint_names)
    swept = sorted({s.joint for s in sweeps}, key=names.index)
    base_joints = list(base_joints) if base_joints is not None else swept[:2]
    circles, measured, model = [], [], []
    for sw in sweeps:
        q_sorted = sw.q[:, names.index(sw.joint)]
        order = torch.argsort(q_sorted)  # increasing joint value: normal = +axis
        circle = fit_circle(sw.position[order].numpy())
        circles.append(circle)
        if sw.joint in base_joints:
            measured.append((circle.centre, circle.normal))
            model.append(_model_axis(robot, sw.joint, sw.q[0]))
    base = base_from_axes(measured, model)
    q = torch.cat([s.q for s in sweeps])
    pos = torch.cat([s.position for s in sweeps])
    quats = [s.quat for s in sweeps]
    quat = None if any(x is None for x in quats) else torch.cat(quats)
    tool = tool_from_base(robot, base, q, pos, quat)
    return Referencing(base, tool, tuple(circles), tuple(s.joint for s in sweeps))


@dataclass(frozen=True)
class FrameGuess:
    """Closed-form frames: ``base (G, 4, 4)`` and ``tool (G, 4, 4)``, one set per file
    (``G`` files) or one for all (``G = 1``)."""

    base: Tensor
    tool: Tensor


def registration_guess(data: MeasuredData, robot, frames_per_file: bool = False) -> FrameGuess:
    """Closed-form base and tool frames of any table (module docstring).

    Args:
        data: measured rows (positions, optional orientations).
        robot: nominal robot (or anything with ``fk``): flange poses ``F_i``.
        frames_per_file: one frame set per file (tracker moved / tool re-mounted).
    """
    with torch.no_grad():
        T_end = robot.fk(data.q.to(robot.dtype)).double()
    R_meas = None if data.quat is None else quat_to_matrix(data.quat)
    groups = range(len(data.sources)) if frames_per_file else [None]
    bases, tools = [], []
    for g in groups:
        rows = slice(None) if g is None else data.file_index == g
        if g is not None and not bool(rows.any()):
            raise DataError("no rows of this file", file=data.sources[g])
        base, tool = register_frames(
            T_end[rows], data.position[rows], None if R_meas is None else R_meas[rows]
        )
        bases.append(base)
        tools.append(tool)
    return FrameGuess(torch.stack(bases), torch.stack(tools))

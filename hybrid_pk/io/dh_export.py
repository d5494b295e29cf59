"""The geometric part of a model as a DH or modified-DH table (conventions:
:mod:`hybrid_pk.robot.dh`), the same numbers that ``Robot.from_dh`` reads.

What the table carries: the model's kinematic parameters with every geometric effect
(link lengths, axis misalignments, thermal expansion at the reference temperature, so
the identity) and the joint offsets folded into ``theta`` (``d`` for a prismatic joint):
the table at commanded ``q`` gives ``fk(q + offsets)`` of the calibrated geometry,
``base`` (root link -> frame 0) and ``flange`` (frame ``n`` -> end link) included.

Construction. Each joint's axis is a line at the commanded zero; line 0 is the root's
``z`` axis and line ``n+1`` the end link's ``z`` axis. Between consecutive lines ``k``
and ``k+1`` the table needs one *normal*: a foot ``f`` on line ``k``, a unit ``x``
perpendicular to it, ``a`` along ``x`` to line ``k+1``, then ``Rx(alpha) Ry(beta)`` turns
``z`` onto line ``k+1``:

- lines more than 45° apart: the common normal (``beta = 0``), plain DH;
- closer to parallel: Hayati's normal (the common normal runs off to infinity there,
  and the conditioning of plain DH falls below Hayati's at 45°): ``f`` is the foot of a
  reference point, ``x`` points to where line ``k+1`` crosses the plane through ``f``
  normal to line ``k``, ``beta`` tilts about ``y``.

The free choices (the sign of ``x``, ``f`` on parallel lines, ``x`` on coincident ones)
follow the model's own frames: frame 0 as close as possible to the root, frame ``n`` to
the end link, frame ``k`` in between to the URDF frame of the joint it would be
(``mdh``: joint ``k``, ``dh``: joint ``k+1``), so a robot built by ``Robot.from_dh``
exports its own table back. MDH frame ``k`` is the
normal's frame at ``f``, DH frame ``k`` the same frame moved by ``Tx(a) Rx(alpha)
Ry(beta)`` onto line ``k+1``; ``theta_i, d_i`` go from DH frame ``i-1`` to MDH frame
``i``, both on line ``i``. The DH and MDH tables hold the same numbers, grouped apart.

Masses. Where the robot's moving links have mass, each row also holds its segment's
inertial (mass, centre of mass, inertia about it) in table frame ``i`` — the frame
``hybrid-pk import dh`` attaches row ``i``'s inertial to: ``dh`` frame ``i`` (the end of
row ``i``, on line ``i+1``), ``mdh`` frame ``i`` (on line ``i``); both move with joint
``i`` only, as segment ``i`` does. Read back, the table gives the same statics
(``gravity_torques``). The root link's mass carries no joint load and has no row; masses on
off-chain joints that a chain joint drives (:attr:`ChainSpec.branches`) ride on another
axis than their row's and are not written (:func:`inertial_note` says so).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
import yaml

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.effects.joint import JointOffset
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import matrix_to_rpy
from hybrid_pk.output_file import write_text
from hybrid_pk.robot.dh import rot, trans
from hybrid_pk.robot.dh_table import CONVENTIONS, INERTIA_COLUMNS, DHTable

__all__ = ["frame_entry", "geometric_model", "inertial_note", "model_dh_table"]
__all__ += ["table_changes", "write_dh_yaml", "zero_frames"]

# Below this length [m] two lines count as crossing (a = 0): far below any machining
# tolerance, far above the float64 rounding of metre-sized chains (1e-16 m).
_COINCIDENT = 1e-12
# A reference x within 1e-4 rad of perpendicular to a normal does not tell which way the
# normal points (a table's pi/2 written as 1.5708 is 4e-6 rad off a tie: round-off would
# decide it): such a normal points from one axis to the next instead.
_TIE = 1e-4
# A table cell that moved less than a nanometre / nanoradian from the nominal robot's is
# the round-off of the two extractions, not the calibration (whose stds are micrometres).
_CHANGED = 1e-9
# Written values are rounded to decimal places beyond which only the round-off of
# turning the chain's frames is left, no measurable quantity (0.42, not 0.4199999999999998;
# 0, not 6.6e-20): lengths [m] and angles [rad] to 12 (_COINCIDENT: a picometre, a
# picoradian), inertias [kg m^2] to 15 (1 g at 1 um; an arm link's is above 1e-6).
_DIGITS, _INERTIA_DIGITS = 12, 15


def geometric_model(model: ExtendedModel) -> ExtendedModel:
    """The model with only what a geometric table carries: its geometric effects and
    joint offsets (same robot and frames)."""
    keep = [e for e in model.effects if e.stage == "geometry" or isinstance(e, JointOffset)]
    return model.with_effects(keep)


def zero_frames(model: ExtendedModel) -> tuple[np.ndarray, np.ndarray]:
    """``(frames (n+1, 4, 4), axes (n, 3))`` at commanded zero of the geometric part:
    frame ``i < n`` is chain joint ``i+1``'s frame, ``n`` the end link; axes unit, in the
    root frame."""
    model = geometric_model(model)  # joint offsets only: q0 is what they make of zero
    robot = model.robot
    if robot.has_mimic:
        mimic = [name for name in robot.chain_joint_names if name not in robot.joint_names]
        raise HybridPKError(
            f"{robot.name}: a DH table has one row per joint; this chain has mimic joints "
            f"({', '.join(mimic)}): export it as a URDF"
        )
    temp = torch.tensor(REFERENCE_TEMPERATURE, dtype=robot.dtype)
    with torch.no_grad():
        params = model.kinematic_params(Conditions(temperature=temp))
        params = type(params)(*(t.detach().to(torch.float64) for t in params))
        q0 = torch.zeros(robot.dof, dtype=torch.float64)
        q0 = model.kinematic_joint_values(q0)  # the joint offsets
        frames = robot.link_frames(q0, params).numpy()
    n = robot.chain_dof
    local = params.axis.numpy()
    local = local / np.linalg.norm(local, axis=-1, keepdims=True)
    axes = np.einsum("nij,nj->ni", frames[:n, :3, :3], local)
    return frames, axes


def _normal(pA, zA, pB, zB, ref_point, ref_x, sign_x) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Normal from line A to line B: ``(foot f on A, unit x, (a, alpha, beta))``; ``x``
    points along ``sign_x`` unless that is (nearly) perpendicular to it: then from A
    towards B (``a >= 0``, the textbooks' rule)."""
    c = np.cross(zA, zB)
    s, cos = np.linalg.norm(c), float(zA @ zB)
    if s > abs(cos):  # plain DH: the common normal
        w = pA - pB
        b, d, e = cos, float(zA @ w), float(zB @ w)
        t = (b * e - d) / (1 - b * b)  # foot on A of the shortest segment between lines
        f = pA + t * zA
        x = c / s
        if x @ sign_x < -_TIE or (abs(x @ sign_x) <= _TIE and x @ (pB - pA) < 0):
            x = -x
        g = pB + ((f - pB) @ zB) * zB  # foot on B: same a for either end of the segment
        beta_free = False
    else:  # Hayati: foot of the reference point, x towards line B in the plane normal to A
        f = pA + ((ref_point - pA) @ zA) * zA
        g = pB + (zA @ (f - pB)) / cos * zB
        v = g - f
        if np.linalg.norm(v) > _COINCIDENT:
            x = v / np.linalg.norm(v)
            if x @ sign_x < -_TIE:
                x = -x
        else:
            x = _perpendicular(zA, ref_x)
        beta_free = True
    a = float(x @ (g - f))
    y = np.cross(zA, x)
    beta = math.asin(max(-1.0, min(1.0, float(zB @ x)))) if beta_free else 0.0
    alpha = math.atan2(-float(zB @ y), float(zB @ zA))
    return f, x, (a, alpha, beta)


def _perpendicular(z: np.ndarray, hint: np.ndarray) -> np.ndarray:
    """Unit vector normal to ``z``, as close as possible to ``hint``."""
    for h in (hint, np.array([1.0, 0, 0]), np.array([0, 1.0, 0])):
        v = h - (h @ z) * z
        if np.linalg.norm(v) > 1e-6:
            return v / np.linalg.norm(v)
    raise AssertionError("unreachable: x and y cannot both be parallel to z")


def _frame(origin, x, z) -> np.ndarray:
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, origin
    return T


def _table_frames(model: ExtendedModel, convention: str, guide: list | None = None) -> tuple:
    """``(frames, M, G, normals)``: the zero frames, per normal ``k`` the frame at its foot
    on line ``k`` (``M``), the one at its end (``G``) and ``(a, alpha, beta)``. ``guide``:
    the ``x`` of another table's normals (the nominal robot's), whose directions these
    keep; else the reference frames' ``x`` decide them."""
    frames, axes = zero_frames(model)
    n = model.robot.chain_dof
    root, end = np.eye(4), frames[n]
    points = [root[:3, 3], *frames[:n, :3, 3], end[:3, 3]]
    lines = list(zip(points, [root[:3, 2], *axes, end[:3, 2]], strict=True))
    joint_frames = [root, *frames[:n], end]  # reference frame on line k (joint k's)
    M, G, normals = [], [], []
    for k in range(n + 1):
        # The root frames the first normal and the end link the last (frame 0 at the
        # base, frame n at the flange, as makers' tables have them); in between, the
        # joint whose URDF frame the convention's frame k would be.
        inner = joint_frames[k] if convention == "mdh" else joint_frames[k + 1]
        ref = root if k == 0 else end if k == n else inner
        sign = ref[:3, 0] if guide is None else guide[k]
        f, x, nrm = _normal(*lines[k], *lines[k + 1], ref[:3, 3], ref[:3, 0], sign)
        M.append(_frame(f, x, lines[k][1]))
        G.append(M[-1] @ trans("x", nrm[0]) @ rot("x", nrm[1]) @ rot("y", nrm[2]))
        normals.append(nrm)
    return frames, M, G, normals


def model_dh_table(model: ExtendedModel, convention: str) -> DHTable:
    """The geometric part of ``model`` as a ``"dh"`` or ``"mdh"`` table (module docstring)."""
    if convention not in CONVENTIONS:
        raise HybridPKError(f"convention {convention!r}: give dh or mdh")
    robot = model.robot
    n = robot.chain_dof
    guide = None
    if geometric_model(model).effects:  # each normal points as in the nominal robot's table
        _, nominal, _, _ = _table_frames(ExtendedModel(robot), convention)
        guide = [T[:3, 0] for T in nominal]
    frames, M, G, normals = _table_frames(model, convention, guide)
    end = frames[n]
    rows = []
    for i in range(1, n + 1):
        step = np.linalg.solve(G[i - 1], M[i])  # Rz(theta) Tz(d) along line i
        theta, d = math.atan2(step[1, 0], step[0, 0]), float(step[2, 3])
        a, alpha, beta = normals[i] if convention == "dh" else normals[i - 1]
        rows.append([a, alpha, d, theta, beta])
    lower, upper = robot.joint_limits
    table_frames = G if convention == "dh" else M
    if convention == "dh":
        base, flange = G[0], np.linalg.solve(G[n], end)
    else:
        base, flange = M[0], np.linalg.solve(M[n], end)
    return DHTable(
        convention=convention,
        rows=np.array(rows),
        names=list(robot.chain_joint_names),
        types=list(robot.chain_joint_types),
        lower=lower.detach().to(torch.float64).numpy().copy(),
        upper=upper.detach().to(torch.float64).numpy().copy(),
        base=base,
        flange=flange,
        name=robot.name,
        inertial=_inertials(robot, frames, table_frames),
    )


def _inertials(robot, frames: np.ndarray, table_frames: list) -> np.ndarray | None:
    """``(n, 10)`` per row ``mass, com (3), ixx ixy ixz iyy iyz izz`` of segment ``i`` in
    table frame ``i`` (``frames[i-1]``: the segment's own frame, at the same commanded
    zero as ``table_frames``), or None where the table cannot carry the statics."""
    mass = robot.segment_mass.detach().to(torch.float64).numpy()
    com = robot.segment_com.detach().to(torch.float64).numpy()
    if not mass[1:].sum() > 0 or robot.spec.branches:
        return None
    rows = np.zeros((robot.chain_dof, len(INERTIA_COLUMNS)))
    for i in range(1, robot.chain_dof + 1):
        if mass[i] <= 0:
            continue  # a massless segment: an empty row (no <inertial>)
        X = np.linalg.solve(table_frames[i], frames[i - 1])  # segment -> table frame i
        R = X[:3, :3]
        inertia = R @ robot.spec.segment_inertia[i] @ R.T
        rows[i - 1] = [mass[i], *(R @ com[i] + X[:3, 3]), *inertia[np.triu_indices(3)]]
    return rows


def inertial_note(robot) -> str | None:
    """The export summary's line on the links' masses (None: the robot has none)."""
    moving = float(robot.segment_mass[1:].sum())
    if not moving > 0:
        return None
    if robot.spec.branches:
        names = ", ".join(b.joint for b in robot.spec.branches)
        return (
            "the table carries the geometry, not the links' masses: a mass off the chain "
            f"(on {names}, driven by a chain joint) turns about an axis no row has, so no "
            "row holds a mass; keep the URDF (--format urdf) for compliance or deflection "
            "effects"
        )
    root = float(robot.segment_mass[0])
    fixed = f"; the root link's {root:.4g} kg carries no joint load and has no row" if root else ""
    return (
        f"link masses written: each row's mass, centre of mass and inertia in its frame i "
        f"({moving:.4g} kg moving), read back by hybrid-pk import dh{fixed}"
    )


def table_changes(model: ExtendedModel, table: DHTable) -> list[str]:
    """Lines naming every cell of ``table`` (``model``'s, :func:`model_dh_table`) that
    differs from the nominal robot's table in the same convention: the numbers a
    controller's table has to take, with their change [m, rad]."""
    nominal = model_dh_table(ExtendedModel(model.robot), table.convention)
    diff = table.rows - nominal.rows
    diff[:, [1, 3, 4]] = (diff[:, [1, 3, 4]] + math.pi) % (2 * math.pi) - math.pi
    lines = []
    for i, name in enumerate(table.names):
        cells = [
            f"{key} {_plain(nominal.rows[i, k], _DIGITS):.9g} -> "
            f"{_plain(table.rows[i, k], _DIGITS):.9g} ({diff[i, k]:+.3g})"
            for k, key in enumerate(("a", "alpha", "d", "theta", "beta"))
            if abs(diff[i, k]) > _CHANGED
        ]
        lines += [f"  {name}: {', '.join(cells)}"] if cells else []
    for key in ("base", "flange"):
        moved = np.abs(getattr(table, key) - getattr(nominal, key)).max()
        lines += [f"  {key}: moved (up to {moved:.3g} in its matrix)"] if moved > _CHANGED else []
    if not lines:
        return [f"unchanged from the nominal {model.robot.name}'s {table.convention} table"]
    head = f"changed from the nominal {model.robot.name}'s {table.convention} table [m, rad]:"
    return [head, *lines]


def frame_entry(T: np.ndarray) -> dict:
    """``{xyz: [m], rpy: [rad]}`` (URDF roll-pitch-yaw) of a ``(4, 4)`` transform."""
    rpy = matrix_to_rpy(torch.as_tensor(T[:3, :3], dtype=torch.float64)).tolist()
    return {
        "xyz": [_plain(v, _DIGITS) for v in T[:3, 3]],
        "rpy": [_plain(v, _DIGITS) for v in rpy],
    }


def _plain(x: float, digits: int | None = None) -> float:
    """A Python float, never -0.0, rounded to ``digits`` decimal places if given."""
    return (float(x) if digits is None else round(float(x), digits)) + 0.0


def write_dh_yaml(table: DHTable, path: str | os.PathLike, header: list[str] = ()) -> Path:
    """Write ``table`` as YAML that ``Robot.from_dh`` / ``hybrid-pk import dh`` read back.

    Args:
        header: comment lines written first (the export summary).
    """
    path = Path(path)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise HybridPKError(
            f"{path}: a DH export is YAML (.yaml): the rows with the base and flange frames "
            "that a calibrated chain needs beside them"
        )
    rows = []
    for i, name in enumerate(table.names):
        a, alpha, d, theta, beta = (_plain(v, _DIGITS) for v in table.rows[i])
        row = {"name": name, "a": a, "alpha": alpha, "d": d, "theta": theta, "beta": beta}
        row.update(type=table.types[i], lower=_plain(table.lower[i]))
        row["upper"] = _plain(table.upper[i])
        if table.inertial is not None:
            digits = (None, *(_DIGITS,) * 3, *(_INERTIA_DIGITS,) * 6)  # the mass as given
            values = (_plain(v, k) for v, k in zip(table.inertial[i], digits, strict=True))
            row.update(zip(INERTIA_COLUMNS, values, strict=True))
        rows.append(row)
    doc = {
        "convention": table.convention,
        "name": table.name,
        "base": frame_entry(table.base),
        "flange": frame_entry(table.flange),
        "joints": rows,
    }
    text = "".join(f"# {line}\n" if line else "#\n" for line in header)
    text += yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    return write_text(path, text)

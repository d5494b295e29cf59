"""The geometric part of a UR arm's model as the kinematics YAML that Universal Robots'
ROS description and driver read (``ur_description``'s ``kinematics_params`` file).

Format: under ``kinematics``, one entry per joint, ``shoulder, upper_arm, forearm,
wrist_1, wrist_2, wrist_3``, each ``x y z`` [m] and ``roll pitch yaw`` [rad] (URDF
fixed-axis ``Rz(yaw) Ry(pitch) Rx(roll)``): the origin of that joint in the frame of the
link before it, the joint turning about its own ``z``; the first is relative to
``base_link_inertia`` (the controller's base frame, DH frame 0; ``ur_description`` puts
it at ``base_link · Rz(pi)``), and ``tool0`` is the frame of ``wrist_3_link``. So
``T(q) = E_1 Rz(q_1) E_2 Rz(q_2) … E_6 Rz(q_6)``. A ``hash`` string identifies the
calibration (``calib_`` and digits; here derived from the written numbers).

Here ``E_i`` is row ``i`` of the model's modified-DH table
(:mod:`hybrid_pk.io.dh_export`: ``Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d)``, the
joint's motion after it), the table's base folded into ``shoulder``. The model's root
link is taken as ``base_link_inertia`` (a robot built from UR's DH table), or as
``base_link`` when asked (a model on one of ``ur_description``'s URDFs). The table's
flange transform is folded into ``wrist_3`` as far as it commutes with the last joint's
turn (a twist about and a shift along its axis); what remains (a flange off or tilted
from the last axis) cannot be written in this format: it is returned, listed in the
summary and written under the extra top-level key ``hybrid_pk_tool0``
(``wrist_3_link -> tool0``), which UR's description does not read.
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import numpy as np
import torch
import yaml

from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import so3_log
from hybrid_pk.io.dh_export import frame_entry, model_dh_table, zero_frames
from hybrid_pk.output_file import write_text
from hybrid_pk.robot.dh import dh_row_parts, rot, trans

__all__ = ["UR_JOINTS", "UR_ROOTS", "guess_ur_root", "not_ur_layout", "ur_kinematics"]
__all__ += ["write_ur_calibration"]

# [m or rad] a residual below this is rounding, not a flange off the last axis: of the
# construction (float64) or of the URDF's own text (12-digit angles: 5e-12 rad); no
# robot or instrument resolves a nanometre or a nanoradian.
_ROUNDING = 1e-9
UR_ROOTS = ("base_link_inertia", "base_link")
UR_JOINTS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
# A UR arm's consecutive axes (1-2, 2-3, 3-4, 4-5, 5-6): shoulder, elbow and wrist 1
# parallel, every other pair perpendicular.
_UR_PARALLEL = (False, True, True, False, False)


def ur_kinematics(
    model: ExtendedModel, root: str = "base_link_inertia"
) -> tuple[list[np.ndarray], np.ndarray]:
    """``(E_1..E_6 as (4, 4), residual wrist_3_link -> end link (4, 4))``.

    Args:
        root: what the model's root link is in UR's description: ``base_link_inertia``
            (the controller's base frame, DH frame 0: a robot built from UR's DH table)
            or ``base_link`` (the ROS-Industrial base, turned by pi about ``z``: the
            URDFs of ``ur_description``, such as the shipped ``ur10``).
    """
    if root not in UR_ROOTS:
        raise HybridPKError(f"root {root!r}: give one of {', '.join(UR_ROOTS)}")
    _check_six_revolute(model)
    table = model_dh_table(model, "mdh")
    entries = [dh_row_parts("mdh", row, False)[0] for row in table.rows]
    # ur_description: base_link_inertia = base_link · Rz(pi).
    to_root = np.eye(4) if root == "base_link_inertia" else rot("z", -math.pi)
    entries[0] = to_root @ table.base @ entries[0]
    F = table.flange
    twist = math.atan2(F[1, 0], F[0, 0]) if np.hypot(F[0, 2], F[1, 2]) < 1e-9 else 0.0
    along = rot("z", twist) @ trans("z", float(F[2, 3]))  # commutes with Rz(q_6)
    entries[-1] = entries[-1] @ along
    return entries, np.linalg.solve(along, F)


def guess_ur_root(model: ExtendedModel) -> tuple[str, float]:
    """``(root, x)``: what the model's root link is in UR's description, from its
    geometry, and the flange's x [m] at zero joints that tells. UR's DH table has a2, a3
    < 0: at zero joints the stretched arm lies along -x of DH frame 0
    (``base_link_inertia``), so along +x of ``base_link`` (turned by pi about ``z``)."""
    with torch.no_grad():
        zero = torch.zeros(1, model.robot.dof, dtype=torch.float64)
        x = float(model.robot.fk(zero)[0, 0, 3])
    return (UR_ROOTS[1] if x > 0 else UR_ROOTS[0]), x


def _check_six_revolute(model: ExtendedModel) -> None:
    robot = model.robot
    types, names = robot.chain_joint_types, robot.chain_joint_names
    if len(types) != len(UR_JOINTS) or robot.has_mimic or "prismatic" in types:
        mimic = " (mimic joints follow others)" if robot.has_mimic else ""
        raise HybridPKError(
            f"{robot.name}: the UR calibration format holds 6 revolute joints; this chain "
            f"has {', '.join(f'{n} ({t})' for n, t in zip(names, types, strict=True))}{mimic}"
        )


def not_ur_layout(model: ExtendedModel) -> str | None:
    """None for a 6-axis chain laid out as a UR arm (axes 2, 3 and 4 parallel, the other
    consecutive pairs not), else what differs. A pair counts as parallel within 45°, the
    split the DH export makes between plain DH and Hayati's parameters.

    Raises:
        HybridPKError: not a chain of 6 revolute joints.
    """
    _check_six_revolute(model)
    _, axes = zero_frames(model)
    pairs = []
    for k in range(len(axes) - 1):
        cos = abs(float(axes[k] @ axes[k + 1]))
        pairs.append(float(np.linalg.norm(np.cross(axes[k], axes[k + 1]))) <= cos)
    if tuple(pairs) == _UR_PARALLEL:
        return None
    seen = ", ".join(f"{k + 1}-{k + 2}" for k, par in enumerate(pairs) if par) or "none"
    return f"parallel consecutive axes: {seen}; a UR arm's: 2-3, 3-4"


def _entry(T: np.ndarray) -> dict:
    e = frame_entry(T)
    return dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), e["xyz"] + e["rpy"], strict=True))


def write_ur_calibration(
    model: ExtendedModel,
    path: str | os.PathLike,
    header: list[str] = (),
    root: str = "base_link_inertia",
) -> tuple[Path, str | None]:
    """Write the UR kinematics YAML (``header``: comment lines first; ``root``: see
    :func:`ur_kinematics`).

    Returns:
        The path, and a line saying what the format could not hold (None when nothing).
    """
    path = Path(path)
    entries, residual = ur_kinematics(model, root)
    kin = {name: _entry(T) for name, T in zip(UR_JOINTS, entries, strict=True)}
    numbers = repr([list(v.values()) for v in kin.values()]).encode("utf-8")
    kin["hash"] = f"calib_{int(hashlib.sha256(numbers).hexdigest()[:15], 16)}"
    doc, note = {"kinematics": kin}, None
    if np.abs(residual - np.eye(4)).max() > _ROUNDING:
        doc["hybrid_pk_tool0"] = frame_entry(residual)
        shift = np.linalg.norm(residual[:3, 3]) * 1000
        tilt = float(so3_log(torch.as_tensor(residual[:3, :3])).norm())
        note = (
            f"tool0 is {shift:.4g} mm off / {tilt * 1000:.4g} mrad tilted from wrist_3's axis: "
            "that transform is written under hybrid_pk_tool0, which UR's description does not read"
        )
    text = "".join(f"# {line}\n" if line else "#\n" for line in header)
    text += yaml.safe_dump(doc, sort_keys=False, width=100)
    return write_text(path, text), note

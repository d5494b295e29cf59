"""URDF -> :class:`ChainSpec`, the plain-number description of one serial chain.

pytorch-kinematics builds the serial chain (root to end link, joint order, joint
types); yourdfpy supplies the numbers at full float64 precision (pk parses origins
in float32) and the inertials, which pk does not read.

Segments: segment 0 is everything rigidly attached to the root link; segment ``i``
(1..dof) is everything that moves with actuated joint ``i``. Fixed joints along the
chain are folded into the origins, so the chain alternates
``origin[0] · joint_1 · origin[1] · joint_2 · … · joint_dof · origin[dof]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytorch_kinematics as pk
import yourdfpy

from hybrid_pk.errors import InvalidFrame, RobotModelError

__all__ = ["ChainSpec", "load_chain_spec", "resolve_urdf"]

_MOVABLE = ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class ChainSpec:
    """Numbers of one serial chain, all float64 numpy arrays.

    Attributes:
        name: robot name from the URDF.
        urdf_path: file it was read from.
        root_link, end_link: chain ends.
        joint_names: actuated joints in chain order, ``dof`` of them.
        joint_types: ``"revolute" | "continuous" | "prismatic"`` per joint.
        lower, upper: ``(dof,)`` joint limits [rad or m]; ``±inf`` for continuous joints.
        origins: ``(dof + 1, 4, 4)``; ``origins[i]`` maps segment ``i`` to the frame of
            joint ``i + 1`` before its motion; ``origins[dof]`` maps the last segment to
            the end link.
        axes: ``(dof, 3)`` unit joint axes in their joint frames.
        segment_mass: ``(dof + 1,)`` [kg] mass rigidly attached to each segment.
        segment_com: ``(dof + 1, 3)`` [m] centre of mass of each segment in its frame
            (zero where the segment has no mass).
        ignored_mass: [kg] mass on off-chain movable branches, not in the statics.
    """

    name: str
    urdf_path: str
    root_link: str
    end_link: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    origins: np.ndarray
    axes: np.ndarray
    segment_mass: np.ndarray
    segment_com: np.ndarray
    ignored_mass: float = 0.0

    @property
    def dof(self) -> int:
        return len(self.joint_names)


def _shipped_dirs() -> list[Path]:
    here = Path(__file__).resolve().parent.parent
    return [here / "_urdf", here.parent / "urdf"]  # wheel install, then source checkout


def shipped_robots() -> dict[str, Path]:
    """Names of the robots shipped in ``urdf/`` -> their files."""
    found: dict[str, Path] = {}
    for d in _shipped_dirs():
        if d.is_dir():
            for f in sorted(d.glob("*.urdf")):
                found.setdefault(f.stem, f)
    return found


def resolve_urdf(robot: str | Path) -> Path:
    """A URDF path, or the name of a shipped robot (``"rx160"``, ``"ur10"``), -> path."""
    p = Path(robot)
    if p.suffix.lower() == ".urdf" or p.exists():
        if not p.is_file():
            raise RobotModelError(f"URDF file not found: {p}")
        return p
    shipped = shipped_robots()
    if str(robot) in shipped:
        return shipped[str(robot)]
    raise RobotModelError(
        f"unknown robot {str(robot)!r}: give a URDF path or a shipped robot name "
        f"({', '.join(shipped) or 'none found'})"
    )


def _joint_limits(joint: yourdfpy.Joint) -> tuple[float, float]:
    if joint.type == "continuous":
        return -np.inf, np.inf
    lim = joint.limit
    if lim is None or lim.lower is None or lim.upper is None:
        raise RobotModelError(f"joint {joint.name!r} ({joint.type}) has no <limit lower/upper>")
    if not lim.lower < lim.upper:
        raise RobotModelError(
            f"joint {joint.name!r}: lower limit {lim.lower} is not below upper limit {lim.upper}"
        )
    return float(lim.lower), float(lim.upper)


def _origin(joint: yourdfpy.Joint) -> np.ndarray:
    return np.eye(4) if joint.origin is None else np.asarray(joint.origin, dtype=np.float64)


def load_chain_spec(urdf: str | Path, end_link: str | None = None) -> ChainSpec:
    """Read a URDF into a :class:`ChainSpec` for the chain root -> ``end_link``.

    Args:
        urdf: path of a URDF file, or a shipped robot name.
        end_link: link the chain ends at; default the URDF's single leaf link.
    """
    path = resolve_urdf(urdf)
    try:
        model = yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=False)
    except Exception as exc:  # yourdfpy raises bare lxml/ValueErrors
        raise RobotModelError(f"{path}: cannot parse URDF: {exc}") from exc

    children = {j.child: j for j in model.robot.joints}
    kids: dict[str, list[str]] = {}
    for j in model.robot.joints:
        kids.setdefault(j.parent, []).append(j.child)
    links = [link.name for link in model.robot.links]
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise RobotModelError(f"{path}: expected one root link, found {roots}")
    root = roots[0]
    leaves = [n for n in links if n not in kids]
    if end_link is None:
        if len(leaves) != 1:
            raise RobotModelError(
                f"{path}: the URDF has {len(leaves)} leaf links ({', '.join(leaves)}); "
                "choose one with --end-link"
            )
        end_link = leaves[0]
    elif end_link not in links:
        raise InvalidFrame(end_link, links)

    # pytorch-kinematics decides the serial path and joint order.
    chain = pk.build_serial_chain_from_urdf(path.read_bytes(), end_link, root)
    names = list(chain.get_joint_parameter_names())
    path_links: list[str] = []
    link = end_link
    while link != root:
        path_links.append(link)
        link = children[link].parent
    path_links.append(root)
    path_links.reverse()
    path_joints = [children[n] for n in path_links[1:]]
    movable = [j for j in path_joints if j.type in _MOVABLE]
    if [j.name for j in movable] != names:
        raise RobotModelError(f"{path}: chain joints disagree between parsers: {names}")
    unsupported = [j for j in path_joints if j.type not in (*_MOVABLE, "fixed")]
    if unsupported:
        raise RobotModelError(
            f"{path}: joint {unsupported[0].name!r} has unsupported type {unsupported[0].type!r}"
        )
    if not movable:
        raise RobotModelError(f"{path}: no actuated joint between {root!r} and {end_link!r}")

    # Fold fixed joints into origins; remember which segment each chain link is in and
    # the transform from that segment's frame to the link.
    dof = len(movable)
    origins = np.zeros((dof + 1, 4, 4))
    axes = np.zeros((dof, 3))
    lower, upper = np.zeros(dof), np.zeros(dof)
    seg_of: dict[str, tuple[int, np.ndarray]] = {root: (0, np.eye(4))}
    acc, seg = np.eye(4), 0
    for j in path_joints:
        acc = acc @ _origin(j)
        if j.type == "fixed":
            seg_of[j.child] = (seg, acc.copy())
            continue
        origins[seg] = acc
        axis = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), dtype=np.float64)
        norm = np.linalg.norm(axis)
        if norm < 1e-12:
            raise RobotModelError(f"{path}: joint {j.name!r} has a zero axis")
        axes[seg] = axis / norm
        lower[seg], upper[seg] = _joint_limits(j)
        seg += 1
        acc = np.eye(4)
        seg_of[j.child] = (seg, acc.copy())
    origins[dof] = acc

    # Statics: every link rigidly attached to a chain segment (fixed joints only).
    mass = np.zeros(dof + 1)
    moment = np.zeros((dof + 1, 3))
    ignored = 0.0
    stack = list(seg_of)
    while stack:
        parent = stack.pop()
        for child in kids.get(parent, []):
            if child in seg_of:
                continue
            j = children[child]
            if j.type == "fixed" and parent in seg_of:
                s, T = seg_of[parent]
                seg_of[child] = (s, T @ _origin(j))
                stack.append(child)
    for name in links:
        inertial = model.link_map[name].inertial
        m = 0.0 if inertial is None or inertial.mass is None else float(inertial.mass)
        if m == 0.0:
            continue
        if name not in seg_of:
            ignored += m
            continue
        s, T = seg_of[name]
        c_link = np.zeros(3) if inertial.origin is None else np.asarray(inertial.origin)[:3, 3]
        mass[s] += m
        moment[s] += m * (T[:3, :3] @ c_link + T[:3, 3])
    com = np.divide(moment, mass[:, None], out=np.zeros_like(moment), where=mass[:, None] > 0)

    return ChainSpec(
        name=model.robot.name,
        urdf_path=str(path),
        root_link=root,
        end_link=end_link,
        joint_names=tuple(names),
        joint_types=tuple(j.type for j in movable),
        lower=lower,
        upper=upper,
        origins=origins,
        axes=axes,
        segment_mass=mass,
        segment_com=com,
        ignored_mass=ignored,
    )

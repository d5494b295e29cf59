"""URDF -> :class:`ChainSpec`, the plain-number description of one serial chain.

pytorch-kinematics builds the serial chain (root to end link, joint order); yourdfpy
supplies every number at full float64 precision (pk parses origins in float32), the
inertials and the ``<mimic>`` tags, which pk does not read. The path is walked once,
by pk; yourdfpy's joints are looked up by name along it.

Segments: segment 0 is everything rigidly attached to the root link; segment ``i``
(1..n_chain) is everything that moves with chain joint ``i``. Fixed joints along the
chain are folded into the origins, so the chain alternates
``origin[0] · joint_1 · origin[1] · joint_2 · … · joint_n · origin[n]``.

Mimic joints: every movable joint of the chain follows one *independent* joint (itself,
or the leader its ``<mimic>`` tags lead to, which may sit off the chain):
``q_chain[i] = multiplier[i] · q[source[i]] + offset[i]``. The robot's joints (data
columns, limits, IK variables) are the independent ones, in the order their first
chain joint appears.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from lxml import etree

from hybrid_pk.errors import InvalidFrame, RobotModelError
from hybrid_pk.robot.spec_cache import cached_spec, keep_spec

if TYPE_CHECKING:  # the readers are imported where a URDF is read (spec_cache)
    import yourdfpy

__all__ = ["BranchBody", "ChainSpec", "load_chain_spec", "resolve_urdf", "shipped_robots"]

_MOVABLE = ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class BranchBody:
    """Mass on an off-chain joint driven by a robot joint (e.g. a mimic leader's link).

    Attributes:
        joint: name of the off-chain joint; ``joint_type`` its URDF type.
        segment: chain segment its parent link is rigidly attached to.
        origin: ``(4, 4)`` segment frame -> joint frame before the joint's motion.
        axis: ``(3,)`` unit axis in the joint frame.
        source, multiplier, offset: ``q_joint = multiplier · q[source] + offset``.
        mass: [kg] everything rigidly attached after the joint; ``com`` ``(3,)`` [m] its
            centre of mass in the joint's child frame.
    """

    joint: str
    joint_type: str
    segment: int
    origin: np.ndarray
    axis: np.ndarray
    source: int
    multiplier: float
    offset: float
    mass: float
    com: np.ndarray


@dataclass(frozen=True)
class ChainSpec:
    """Numbers of one serial chain, all float64 numpy arrays.

    Attributes:
        name: robot name from the URDF.
        urdf_path: file it was read from.
        root_link, end_link: chain ends.
        joint_names: the robot's independent joints, ``dof`` of them.
        joint_types: ``"revolute" | "continuous" | "prismatic"`` per independent joint.
        lower, upper: ``(dof,)`` joint limits [rad or m]; ``±inf`` for continuous joints.
        chain_joint_names, chain_joint_types: movable joints on the chain, in chain
            order, ``n_chain`` of them (mimic joints included).
        source, multiplier, offset: ``(n_chain,)`` the coupling
            ``q_chain[i] = multiplier[i] · q[source[i]] + offset[i]``.
        origins: ``(n_chain + 1, 4, 4)``; ``origins[i]`` maps segment ``i`` to the frame
            of chain joint ``i + 1`` before its motion; ``origins[n_chain]`` maps the
            last segment to the end link.
        axes: ``(n_chain, 3)`` unit joint axes in their joint frames.
        segment_mass: ``(n_chain + 1,)`` [kg] mass rigidly attached to each segment.
        segment_com: ``(n_chain + 1, 3)`` [m] centre of mass of each segment in its
            frame (zero where the segment has no mass).
        segment_inertia: ``(n_chain + 1, 3, 3)`` [kg m²] inertia of each segment about
            its centre of mass, in its frame's axes (the statics read only mass and
            centre of mass; a DH export writes it beside them).
        branches: masses on off-chain joints that robot joints drive.
        ignored_mass: [kg] mass on other off-chain movable branches, not in the statics.
    """

    name: str
    urdf_path: str
    root_link: str
    end_link: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    chain_joint_names: tuple[str, ...]
    chain_joint_types: tuple[str, ...]
    source: np.ndarray
    multiplier: np.ndarray
    offset: np.ndarray
    origins: np.ndarray
    axes: np.ndarray
    segment_mass: np.ndarray
    segment_com: np.ndarray
    branches: tuple[BranchBody, ...] = ()
    ignored_mass: float = 0.0
    segment_inertia: np.ndarray | None = None

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    @property
    def chain_dof(self) -> int:
        return len(self.chain_joint_names)

    @property
    def has_mimic(self) -> bool:
        """True when the chain joints are not simply the robot's joints."""
        return self.joint_names != self.chain_joint_names or bool(
            np.any(self.multiplier != 1) or np.any(self.offset != 0)
        )


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
    if p.suffix.lower() in (".yaml", ".yml", ".csv") and p.is_file():
        raise RobotModelError(
            f"{p} is a table, not a URDF: 'hybrid-pk import dh {p} --out ROBOT.urdf' makes a "
            "URDF of a DH table (Python: Robot.from_dh)"
        )
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


@contextmanager
def _quiet_unknown_attributes():
    """pytorch-kinematics' URDF parser writes a stderr line per attribute or tag it does
    not know (the Panda's ``<dynamics D= K= mu_coulomb= mu_viscous=>``: 28 lines on every
    command; the Z1's ``<hardwareInterface>`` in ``<actuator>``: 6); no part of hybrid_pk
    reads them, so those notes are dropped, any other is passed on."""
    from pytorch_kinematics.urdf_parser_py.xml_reflection import core as _pk_xml

    said = _pk_xml.on_error

    def note(message: str) -> None:
        if not message.startswith(("Unknown attribute", "Unknown tag")):
            said(message)

    _pk_xml.on_error = note
    try:
        yield
    finally:
        _pk_xml.on_error = said


def _check_well_formed(path: Path) -> None:
    """Raise one line naming ``path``, line and column at its first XML syntax error.

    yourdfpy reads a broken file by printing the parser's complaint and retrying with a
    recovering parser, whose partial tree then fails for an unrelated reason (a file
    cut off mid-joint: 'expected one root link'); lxml, the parser yourdfpy uses, is
    asked first so that every file it would complain about is refused here instead.
    """
    try:
        etree.parse(str(path))
    except etree.XMLSyntaxError as exc:
        line, column = exc.position
        reason = exc.msg.split(f", line {line}, column")[0]  # the position is said first
        raise RobotModelError(
            f"{path}, line {line}, column {column}: not well-formed XML "
            f"({reason[:1].lower()}{reason[1:]})"
        ) from None


class _Tree:
    """The URDF's link tree: joints by child link, children by parent link."""

    def __init__(self, path: Path) -> None:
        import yourdfpy

        _check_well_formed(path)
        try:
            model = yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=False)
        except Exception as exc:  # yourdfpy raises bare lxml/ValueErrors
            reason = f"an element lacks its attribute {exc}" if isinstance(exc, KeyError) else exc
            raise RobotModelError(f"{path}: cannot parse URDF: {reason}") from exc
        self.path, self.model = path, model
        self.joint_to = {j.child: j for j in model.robot.joints}
        self.joints_from: dict[str, list[yourdfpy.Joint]] = {}
        for j in model.robot.joints:
            self.joints_from.setdefault(j.parent, []).append(j)
        self.links = [link.name for link in model.robot.links]
        roots = [n for n in self.links if n not in self.joint_to]
        if len(roots) != 1:
            raise RobotModelError(f"{path}: expected one root link, found {roots}")
        self.root = roots[0]

    def end_link(self, end_link: str | None) -> str:
        if end_link is not None:
            if end_link not in self.links:
                raise InvalidFrame(end_link, self.links, file=str(self.path))
            return end_link
        leaves = [n for n in self.links if n not in self.joints_from]
        if len(leaves) != 1:
            raise RobotModelError(
                f"{self.path}: the URDF has {len(leaves)} leaf links ({', '.join(leaves)}); "
                "choose one with --end-link (Python: Robot.from_urdf(path, end_link=...))"
            )
        return leaves[0]

    def path_joints(self, end_link: str) -> list[yourdfpy.Joint]:
        """Joints from the root to ``end_link``, in chain order (pytorch-kinematics' path)."""
        if end_link == self.root:
            raise RobotModelError(f"{self.path}: {end_link!r} is the root link: no joint moves it")
        import pytorch_kinematics as pk

        try:
            with _quiet_unknown_attributes():
                chain = pk.build_serial_chain_from_urdf(self.path.read_bytes(), end_link, self.root)
        except Exception as exc:  # pk raises bare KeyErrors/ValueErrors
            raise RobotModelError(f"{self.path}: no serial chain to {end_link!r}: {exc}") from exc
        frames = chain.get_frame_names(exclude_fixed=False)[1:]  # the root has no joint
        joints = [self.model.joint_map[chain.find_frame(f).joint.name] for f in frames]
        bad = [j for j in joints if j.type not in (*_MOVABLE, "fixed")]
        if bad:
            raise RobotModelError(
                f"{self.path}: joint {bad[0].name!r} has unsupported type {bad[0].type!r}"
            )
        if not any(j.type in _MOVABLE for j in joints):
            raise RobotModelError(
                f"{self.path}: no movable joint between {self.root!r} and {end_link!r}"
            )
        return joints

    def driver(self, joint: yourdfpy.Joint) -> tuple[yourdfpy.Joint, float, float]:
        """``(leader, multiplier, offset)``: ``q_joint = multiplier · q_leader + offset``."""
        mul, off, seen = 1.0, 0.0, [joint.name]
        while joint.mimic is not None:
            leader = self.model.joint_map.get(joint.mimic.joint)
            if leader is None or leader.type not in _MOVABLE:
                what = "has no such joint" if leader is None else f"has it {leader.type}"
                raise RobotModelError(
                    f"{self.path}: joint {joint.name!r} mimics {joint.mimic.joint!r}, but the "
                    f"URDF {what}; a <mimic joint=...> must name a movable joint"
                )
            m = 1.0 if joint.mimic.multiplier is None else float(joint.mimic.multiplier)
            off += mul * (0.0 if joint.mimic.offset is None else float(joint.mimic.offset))
            mul *= m
            if leader.name in seen:
                raise RobotModelError(f"{self.path}: mimic joints form a cycle: {seen}")
            seen.append(leader.name)
            joint = leader
        return joint, mul, off

    def rigid(self, links: dict[str, np.ndarray], stop: set[str]) -> dict[str, np.ndarray]:
        """``links`` (name -> transform from the segment frame) and every link fixed to
        them, not crossing into ``stop``."""
        out, stack = dict(links), list(links)
        while stack:
            parent = stack.pop()
            for j in self.joints_from.get(parent, []):
                if j.type == "fixed" and j.child not in stop and j.child not in out:
                    out[j.child] = out[parent] @ _origin(j)
                    stack.append(j.child)
        return out


def _joint_limits(joint: yourdfpy.Joint) -> tuple[float, float]:
    if joint.type == "continuous":
        return -np.inf, np.inf
    lim = joint.limit
    if lim is None or lim.lower is None or lim.upper is None:
        raise RobotModelError(f"joint {joint.name!r} ({joint.type}) has no <limit lower/upper>")
    if not lim.lower < lim.upper:
        raise RobotModelError(
            f"joint {joint.name!r}: lower limit {lim.lower} is not below upper limit {lim.upper}"
            + (" (0 and 0 are URDF's defaults: write the joint's range)" if lim.upper == 0 else "")
        )
    return float(lim.lower), float(lim.upper)


def _origin(joint: yourdfpy.Joint) -> np.ndarray:
    return np.eye(4) if joint.origin is None else np.asarray(joint.origin, dtype=np.float64)


def _axis(tree: _Tree, joint: yourdfpy.Joint) -> np.ndarray:
    axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), dtype=np.float64)
    if np.linalg.norm(axis) < 1e-12:
        raise RobotModelError(f"{tree.path}: joint {joint.name!r} has a zero axis")
    return axis / np.linalg.norm(axis)


def _mass(tree: _Tree, links: dict[str, np.ndarray]) -> tuple[float, np.ndarray]:
    """Mass [kg] and first moment [kg m] of ``links`` (name -> frame transform)."""
    mass, moment = 0.0, np.zeros(3)
    for name, T in links.items():
        inertial = tree.model.link_map[name].inertial
        m = 0.0 if inertial is None or inertial.mass is None else float(inertial.mass)
        c = np.zeros(3) if inertial is None or inertial.origin is None else inertial.origin[:3, 3]
        mass, moment = mass + m, moment + m * (T[:3, :3] @ c + T[:3, 3])
    return mass, moment


def _inertia(tree: _Tree, links: dict[str, np.ndarray], com: np.ndarray) -> np.ndarray:
    """Inertia [kg m²] of ``links`` (name -> frame transform) about ``com``, in the
    axes ``links`` are given in: each link's tensor turned into them, moved to ``com``
    by the parallel-axis theorem."""
    out = np.zeros((3, 3))
    for name, T in links.items():
        inertial = tree.model.link_map[name].inertial
        if inertial is None or not inertial.mass:
            continue
        F = T if inertial.origin is None else T @ inertial.origin
        own = np.zeros((3, 3)) if inertial.inertia is None else np.asarray(inertial.inertia)
        d = F[:3, 3] - com
        out += F[:3, :3] @ own @ F[:3, :3].T
        out += float(inertial.mass) * ((d @ d) * np.eye(3) - np.outer(d, d))
    return out


def load_chain_spec(urdf: str | Path, end_link: str | None = None) -> ChainSpec:
    """Read a URDF into a :class:`ChainSpec` for the chain root -> ``end_link``.

    Args:
        urdf: path of a URDF file, or a shipped robot name.
        end_link: link the chain ends at; default the URDF's single leaf link.
    """
    path = resolve_urdf(urdf)
    if (spec := cached_spec(path, end_link, ChainSpec, BranchBody)) is not None:
        return spec  # read before (spec_cache): the readers' imports are not paid again
    spec = _read_chain_spec(_Tree(path), end_link)
    keep_spec(path, end_link, spec)
    return spec


def _read_chain_spec(tree: _Tree, end_link: str | None) -> ChainSpec:
    """:func:`load_chain_spec` of the URDF ``tree``."""
    end_link = tree.end_link(end_link)
    path_joints = tree.path_joints(end_link)
    on_chain = {tree.root, *(j.child for j in path_joints)}
    # Fixed joints fold into the origins; each segment maps its links to their frames.
    origins, acc, segments = [], np.eye(4), [{tree.root: np.eye(4)}]
    for j in path_joints:
        acc = acc @ _origin(j)
        if j.type != "fixed":
            origins.append(acc)
            acc, segments = np.eye(4), [*segments, {}]
        segments[-1][j.child] = acc
    origins.append(acc)
    segments = [tree.rigid(s, on_chain) for s in segments]
    chain = [j for j in path_joints if j.type in _MOVABLE]
    drivers = [tree.driver(j) for j in chain]  # (leader, multiplier, offset) each
    leaders = list(dict.fromkeys(leader.name for leader, _, _ in drivers))
    independent = [tree.model.joint_map[n] for n in leaders]
    branches, branch_links = _branches(tree, segments, on_chain, leaders)
    counted = set(branch_links).union(*segments)
    mass, moment = (np.array(v) for v in zip(*(_mass(tree, s) for s in segments), strict=True))
    com = np.divide(moment, mass[:, None], out=np.zeros_like(moment), where=mass[:, None] > 0)
    try:
        limits = np.array([_joint_limits(j) for j in independent]).reshape(-1, 2)
    except RobotModelError as exc:  # name the file, as every other URDF error does
        raise RobotModelError(f"{tree.path}: {exc}") from exc
    return ChainSpec(
        name=tree.model.robot.name,
        urdf_path=str(tree.path),
        root_link=tree.root,
        end_link=end_link,
        joint_names=tuple(leaders),
        joint_types=tuple(j.type for j in independent),
        lower=limits[:, 0].copy(),
        upper=limits[:, 1].copy(),
        chain_joint_names=tuple(j.name for j in chain),
        chain_joint_types=tuple(j.type for j in chain),
        source=np.array([leaders.index(d[0].name) for d in drivers], dtype=np.int64),
        multiplier=np.array([d[1] for d in drivers], dtype=np.float64),
        offset=np.array([d[2] for d in drivers], dtype=np.float64),
        origins=np.stack(origins),
        axes=np.stack([_axis(tree, j) for j in chain]),
        segment_mass=mass,
        segment_com=com,
        branches=tuple(branches),
        ignored_mass=_mass(tree, {n: np.eye(4) for n in tree.links if n not in counted})[0],
        segment_inertia=np.stack(
            [_inertia(tree, s, c) for s, c in zip(segments, com, strict=True)]
        ),
    )


def _branches(
    tree: _Tree, segments: list[dict[str, np.ndarray]], on_chain: set[str], leaders: list[str]
) -> tuple[list[BranchBody], set[str]]:
    """Off-chain joints hanging from a chain segment that follow a robot joint (e.g. a
    mimic leader beside the chain), and the links they carry."""
    out, carried = [], set()
    for s, links in enumerate(segments):
        for link, T in links.items():
            for j in tree.joints_from.get(link, []):
                if j.type not in _MOVABLE or j.child in on_chain:
                    continue
                leader, mul, off = tree.driver(j)
                if leader.name not in leaders:
                    continue  # a joint the data does not hold (a gripper finger): ignored
                body = tree.rigid({j.child: np.eye(4)}, on_chain)
                carried.update(body)
                m, moment = _mass(tree, body)
                com = moment / m if m > 0 else np.zeros(3)
                src = leaders.index(leader.name)
                T_joint, axis = T @ _origin(j), _axis(tree, j)
                out.append(BranchBody(j.name, j.type, s, T_joint, axis, src, mul, off, m, com))
    return out, carried

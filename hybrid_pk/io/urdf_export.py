"""Export the geometric part of a calibrated model as a corrected URDF.

The original URDF text is edited in place (ElementTree, comments kept), so meshes,
inertials and every element hybrid_pk does not model survive unchanged.

Origin ``k`` of the :class:`~hybrid_pk.robot.ChainSpec` is the product of the fixed
joints after chain joint ``k`` and the own ``<origin>`` of movable chain joint ``k + 1``:
``O_k = F_1 ... F_m · J``. A geometric effect changes it to ``O'_k``; writing
``J' = J · (O_k⁻¹ O'_k)`` on the actuated joint changes the product to exactly
``O'_k`` and leaves the fixed joints (and everything hanging off them) alone. The tip
origin (after the last actuated joint) is corrected on the last fixed joint of the
chain.

Folded in: ``link_length``, ``axis_misalignment``, ``thermal_expansion`` (at the
reference temperature, where it is the identity). Joint offsets are listed as
comments (URDF has no offset field), or folded into the joint origin with
``fold_joint_offsets=True`` (then the URDF reads commanded joint values; a mimic
leader's offset is folded into the origin of each of its mimic joints on the chain,
scaled by their multipliers). ``<mimic>`` tags are kept as they are. Every other
effect (compliance, backlash, gear ratio, eccentricity) is listed in a
``<!-- hybrid_pk calibration ... -->`` header; it needs the hybrid_pk model.
"""

from __future__ import annotations

import datetime as _dt
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, Effect, ExtendedModel
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.effects.joint import JointOffset
from hybrid_pk.errors import HybridPKError, RobotModelError
from hybrid_pk.geometry import matrix_to_rpy, rpy_to_matrix, so3_exp, transform
from hybrid_pk.output_file import write_text

__all__ = ["BASE_LINK_NAME", "TOOL_LINK_NAME", "corrected_urdf", "export_urdf"]

BASE_LINK_NAME = "measurement_frame"
TOOL_LINK_NAME = "measured_point"
_F64 = torch.float64


def _num(x: float) -> str:
    """Shortest text that reads back as the same float64 (no ``-0``)."""
    x = float(x)
    return repr(0.0 if x == 0 else x)


def _comment_text(text: str) -> str:
    return " " + text.replace("--", "- -").rstrip() + " "  # '--' may not occur in comments


def _parse_origin(joint: ET.Element) -> Tensor:
    origin = joint.find("origin")
    if origin is None:
        return torch.eye(4, dtype=_F64)
    xyz = [float(v) for v in origin.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in origin.get("rpy", "0 0 0").split()]
    return transform(rpy_to_matrix(torch.tensor(rpy, dtype=_F64)), torch.tensor(xyz, dtype=_F64))


def _set_origin(joint: ET.Element, T: Tensor) -> None:
    origin = joint.find("origin")
    if origin is None:
        origin = ET.SubElement(joint, "origin")
    rpy = matrix_to_rpy(T[:3, :3])
    origin.set("xyz", " ".join(_num(v) for v in T[:3, 3]))
    origin.set("rpy", " ".join(_num(v) for v in rpy))


def _format_value(e: Effect) -> str:
    v = e.report_value()
    text = f"[{', '.join(f'{x:.6g}' for x in v)}]" if isinstance(v, list) else f"{v:.6g}"
    return f"{e.label} = {text} {e.unit}"


def _frame_text(T: Tensor) -> str:
    xyz = " ".join(f"{float(v) + 0.0:.9g}" for v in T[:3, 3])  # + 0.0: no "-0"
    rpy = " ".join(f"{float(v) + 0.0:.9g}" for v in matrix_to_rpy(T[:3, :3]))
    return f'xyz="{xyz}" [m] rpy="{rpy}" [rad]'


def _chain_joints(root: ET.Element, root_link: str, end_link: str) -> list[ET.Element]:
    """Joint elements from ``root_link`` to ``end_link``, in chain order."""
    by_child: dict[str, ET.Element] = {}
    for j in root.findall("joint"):
        child = j.find("child")
        if child is not None:
            by_child[child.get("link", "")] = j
    path, link = [], end_link
    while link != root_link:
        if link not in by_child:
            raise RobotModelError(f"URDF has no joint leading to link {link!r}")
        joint = by_child[link]
        path.append(joint)
        link = joint.find("parent").get("link", "")
    return path[::-1]


def _joint_step(joint_type: str, axis: Tensor, value: float) -> Tensor:
    """``(4, 4)`` motion of a joint by ``value`` [rad or m] about/along ``axis``."""
    a = axis / axis.norm()
    if joint_type == "prismatic":
        return transform(torch.eye(3, dtype=_F64), a * value)
    return transform(so3_exp(a * value), torch.zeros(3, dtype=_F64))


def _corrected_origins(model: ExtendedModel, fold_offsets: bool) -> list[Tensor]:
    """``n_chain + 1`` corrected ChainSpec origins, joint offsets folded when asked."""
    robot = model.robot
    n = robot.chain_dof
    temp = torch.tensor(REFERENCE_TEMPERATURE, dtype=robot.dtype)
    with torch.no_grad():
        params = model.kinematic_params(Conditions(temperature=temp))
        xyz = params.origin_xyz.detach().to(_F64).reshape(n + 1, 3)
        rot = params.origin_rot.detach().to(_F64).reshape(n + 1, 3, 3)
        axes = params.axis.detach().to(_F64).reshape(n, 3)
    origins = [transform(rot[k], xyz[k]) for k in range(n + 1)]
    if fold_offsets:
        spec = robot.spec
        for e in model.effects:
            if e.kind != JointOffset.kind:
                continue
            for i in range(n):  # every chain joint that follows this robot joint
                if int(spec.source[i]) == e.joint_index:
                    delta = float(spec.multiplier[i]) * float(e.value.detach())
                    step = _joint_step(spec.chain_joint_types[i], axes[i], delta)
                    origins[i] = origins[i] @ step
    return origins


def corrected_urdf(
    model: ExtendedModel,
    *,
    include_base: bool = False,
    include_tool: bool = False,
    frame_set: int = 0,
    fold_joint_offsets: bool = False,
) -> str:
    """The corrected URDF of ``model`` as text (see :func:`export_urdf`)."""
    robot = model.robot
    spec = robot.spec
    text = Path(spec.urdf_path).read_text(encoding="utf-8")
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    try:
        root = ET.fromstring(text, parser=parser)
    except ET.ParseError as exc:
        raise RobotModelError(f"{spec.urdf_path}: cannot parse URDF: {exc}") from exc
    if not 0 <= frame_set < model.base.sets:
        raise HybridPKError(f"frame_set {frame_set} not in 0..{model.base.sets - 1}")

    joints = _chain_joints(root, spec.root_link, spec.end_link)
    actuated = {name: i for i, name in enumerate(spec.chain_joint_names)}
    # Segment k's origin is corrected on chain joint k + 1, the tip on the last joint.
    target: dict[int, ET.Element] = {}
    for j in joints:
        if j.get("name") in actuated:
            target[actuated[j.get("name")]] = j
    tip_joint = joints[-1] if joints and joints[-1].get("name") not in actuated else None

    new = _corrected_origins(model, fold_joint_offsets)
    nominal = torch.as_tensor(spec.origins, dtype=_F64)
    changed: list[str] = []
    for k in range(spec.chain_dof + 1):
        if torch.equal(new[k], nominal[k]):
            continue
        joint = target.get(k) if k < spec.chain_dof else tip_joint
        if joint is None:
            raise HybridPKError(
                f"cannot write the corrected tip origin: no fixed joint after "
                f"{spec.chain_joint_names[-1]!r} in the URDF"
            )
        delta = torch.linalg.solve(nominal[k], new[k])  # O_k^-1 O'_k
        _set_origin(joint, _parse_origin(joint) @ delta)
        changed.append(joint.get("name"))

    geometric = [e for e in model.effects if e.stage == "geometry"]
    offsets = [e for e in model.effects if e.kind == JointOffset.kind]
    other = [e for e in model.effects if e.stage != "geometry" and e.kind != JointOffset.kind]
    how = (
        "folded into the joint origin: the URDF reads commanded joint values"
        if fold_joint_offsets
        else "URDF has no offset field: theta_true = theta_commanded + offset"
    )
    by_name = {j.get("name"): j for j in root.findall("joint")}
    for e in offsets:
        joint = by_name[e.joint]  # a mimic leader may sit off the chain
        note = f"hybrid_pk calibration: {_format_value(e)} ({how})"
        root.insert(list(root).index(joint), ET.Comment(_comment_text(note)))

    base = model.base.matrix().detach().to(_F64)[frame_set]
    tool = model.tool.matrix().detach().to(_F64)[frame_set]
    sets = f" (frame set {frame_set} of {model.base.sets})" if model.base.sets > 1 else ""
    stamp = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    lines = [
        "hybrid_pk calibration",
        f"exported {stamp} from {spec.urdf_path}, chain {spec.root_link} -> {spec.end_link}",
        f"geometric effects folded into the joint origins ({', '.join(changed) or 'none'}); "
        f"thermal expansion at the reference temperature {REFERENCE_TEMPERATURE:g} degC:",
        *(f"  {_format_value(e)}" for e in geometric),
        f"joint offsets ({how}):" if offsets else "joint offsets: none",
        *(f"  {_format_value(e)}" for e in offsets),
        "not representable in URDF (use the hybrid_pk model):" if other else "",
        *(f"  {_format_value(e)}" for e in other),
        f"base frame T_measurement_{spec.root_link}{sets}: {_frame_text(base)}"
        + (f" (joint {BASE_LINK_NAME}_joint)" if include_base else " (not included)"),
        f"tool frame T_{spec.end_link}_point{sets}: {_frame_text(tool)}"
        + (f" (joint {TOOL_LINK_NAME}_joint)" if include_tool else " (not included)"),
    ]
    header = "\n    ".join(line for line in lines if line) + "\n"
    root.insert(0, ET.Comment(_comment_text(header)))

    links = {link.get("name") for link in root.findall("link")}
    if include_base:
        _add_fixed(root, links, BASE_LINK_NAME, BASE_LINK_NAME, spec.root_link, base, True)
    if include_tool:
        _add_fixed(root, links, TOOL_LINK_NAME, spec.end_link, TOOL_LINK_NAME, tool, False)
    ET.indent(root, space="  ")
    return _prolog(text) + ET.tostring(root, encoding="unicode") + "\n"


def _prolog(text: str) -> str:
    """What precedes ``<robot`` in the original (declaration, licence comments)."""
    for m in re.finditer(r"<!--.*?-->|<robot\b", text, flags=re.S):
        if m.group(0) == "<robot":
            head = text[: m.start()]
            break
    else:
        head = ""
    if "<?xml" not in head:
        head = '<?xml version="1.0"?>\n' + head
    return head


def _add_fixed(
    root: ET.Element, links: set, new_link: str, parent: str, child: str, T: Tensor, first: bool
) -> None:
    if new_link in links:
        raise HybridPKError(f"the URDF already has a link named {new_link!r}")
    link = ET.Element("link", {"name": new_link})
    joint = ET.Element("joint", {"name": f"{new_link}_joint", "type": "fixed"})
    ET.SubElement(joint, "parent", {"link": parent})
    ET.SubElement(joint, "child", {"link": child})
    _set_origin(joint, T)
    if first:
        root.insert(1, link)
        root.insert(2, joint)
    else:
        root.append(link)
        root.append(joint)


def export_urdf(
    model: ExtendedModel,
    path: str | os.PathLike,
    *,
    include_base: bool = False,
    include_tool: bool = False,
    frame_set: int = 0,
    fold_joint_offsets: bool = False,
) -> Path:
    """Write the corrected URDF of the geometric part of ``model``.

    Loading the result with ``Robot.from_urdf`` gives ``fk(q) == model.end_pose(q)`` for
    a model whose effects are all geometric (at the reference temperature), and also
    with joint offsets when ``fold_joint_offsets``.

    Args:
        model: calibrated model.
        path: output ``.urdf`` file.
        include_base: add link ``measurement_frame`` as the new root, fixed to the robot
            root by the fitted base frame (FK then gives poses in the measurement frame).
        include_tool: add link ``measured_point`` fixed to the end link by the tool frame.
        frame_set: which base/tool frame set to use for models with one set per file.
        fold_joint_offsets: fold joint offsets into the joint origins instead of listing
            them as comments.
    """
    path = Path(path)
    text = corrected_urdf(
        model,
        include_base=include_base,
        include_tool=include_tool,
        frame_set=frame_set,
        fold_joint_offsets=fold_joint_offsets,
    )
    return write_text(path, text)

"""Every URDF of the PyPI package ``example-robot-data`` (dev extra): a serial arm loads
with FK equal to pinocchio's to 1e-12 m, anything else loads or gives one clear line.

Which URDFs are serial arms is read here from the XML alone: a leaf link whose path
from the root holds every movable joint of the file. One test over the whole set.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.errors import RobotModelError
from tests.dh_reader import erd_root

pytestmark = pytest.mark.usefixtures("one_thread")

_FIXED = ("fixed",)


def _serial_end(path: Path) -> str | None:
    """The leaf link whose root path holds every movable joint (longest such path), or
    None when the movable joints branch (legs, two arms, hands)."""
    root = ET.parse(path).getroot()
    joints = [
        (j.get("name"), j.get("type"), j.find("parent").get("link"), j.find("child").get("link"))
        for j in root.findall("joint")
    ]
    by_child = {c: (n, t, p) for n, t, p, c in joints}
    parents = {p for _, _, p, _ in joints}
    movable = {n for n, t, _, _ in joints if t not in _FIXED}
    best = None
    for leaf in sorted({c for _, _, _, c in joints} - parents):
        path, link = [], leaf
        while link in by_child:
            name, _, link = by_child[link]
            path.append(name)
        if movable and movable <= set(path) and (best is None or len(path) > best[0]):
            best = (len(path), leaf)
    return None if best is None else best[1]


def _pin_q(pin, model, robot: Robot, q: np.ndarray) -> np.ndarray:
    """pinocchio's configuration for the robot's joint values ``q`` (mimic joints
    through the robot's coupling; continuous joints as cos, sin; others neutral)."""
    chain = robot.chain_q(torch.as_tensor(q)).numpy()
    out = pin.neutral(model)
    for name, value in zip(robot.chain_joint_names, chain, strict=True):
        j = model.joints[model.getJointId(name)]
        if j.nq == 2:
            out[j.idx_q : j.idx_q + 2] = math.cos(value), math.sin(value)
        else:
            out[j.idx_q] = value
    return out


def test_every_example_robot_data_urdf(pin):
    """Serial arms: FK equal to pinocchio to 1e-12 m at 20 configurations each; every
    other URDF either loads or raises RobotModelError with one line naming the file."""
    files = sorted(erd_root().rglob("*.urdf"))
    assert len(files) > 40  # the package's robots, not an empty folder
    arms, refused = [], []
    for path in files:
        end = _serial_end(path)
        try:
            robot = Robot.from_urdf(path, end_link=end)
        except RobotModelError as exc:
            message = str(exc)
            assert "\n" not in message.strip()
            assert str(path) in message or path.name in message, message
            refused.append(path.name)
            continue
        if end is None:
            continue
        model = pin.buildModelFromUrdf(str(path))
        if model.nq != model.nv and any(model.joints[i].nq > 2 for i in range(1, model.njoints)):
            continue  # a floating joint inside the file: pinocchio's q is not joint values
        data = model.createData()
        frame = model.getFrameId(end)
        q = robot.sample_q(20, torch.Generator().manual_seed(0))
        with torch.no_grad():
            ours = robot.fk(q).numpy()
        for k in range(len(q)):
            pin.framesForwardKinematics(model, data, _pin_q(pin, model, robot, q[k].numpy()))
            assert np.abs(data.oMf[frame].homogeneous - ours[k]).max() < 1e-12, path.name
        arms.append(path.name)
    print(f"{len(arms)} serial arms equal to pinocchio: {', '.join(arms)}")
    print(f"{len(refused)} refused with one line: {', '.join(refused)}")
    assert len(arms) >= 10  # UR3/5/10, panda, kinova, xarm, z1, so100/101, ... are serial


@pytest.mark.parametrize(
    ("folder", "name", "end", "extension"),
    [
        ("panda_description", "panda.urdf", "panda_hand_tcp", 'mu_coulomb="'),
        ("z1_description", "z1.urdf", None, "<hardwareInterface>"),
    ],
)
def test_urdf_loads_without_a_line_per_unknown_attribute_or_tag(
    capfd, folder, name, end, extension
):
    """The Panda's <dynamics D= K= mu_coulomb= mu_viscous=> and the Z1's
    <actuator><hardwareInterface> made the URDF parser of pytorch-kinematics print an
    'Unknown attribute' / 'Unknown tag' line each on stderr on every command."""
    path = erd_root() / folder / "urdf" / name
    assert extension in path.read_text()  # the extensions are still in the file
    robot = Robot.from_urdf(path, end_link=end)
    assert robot.dof >= 6
    err = capfd.readouterr().err
    assert "Unknown" not in err, err[:200]

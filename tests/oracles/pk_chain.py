"""pytorch-kinematics' ``SerialChain`` of a robot: the peer of ``bench/fk.py`` and
``bench/ik.py`` and an oracle of the tests (pytorch-kinematics ignores ``<mimic>``
tags, so it serves robots without mimic joints only)."""

from __future__ import annotations

from pathlib import Path

import torch

from hybrid_pk.robot import Robot

__all__ = ["pk_chain"]


def pk_chain(robot: Robot, dtype: torch.dtype | None = None):
    """The pytorch-kinematics ``SerialChain`` of the robot's URDF, root to end link."""
    import pytorch_kinematics as pk

    data = Path(robot.spec.urdf_path).read_bytes()
    chain = pk.build_serial_chain_from_urdf(data, robot.end_link, robot.root_link)
    return chain.to(dtype=dtype or robot.dtype, device=robot.origin_xyz.device)

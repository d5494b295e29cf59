"""How the simulated robot is mounted: floor, ceiling, wall, a tilted base, or any gravity.

A mounting is the rotation ``R_world_root`` of the robot's root frame in a levelled
world frame (z up). Gravity in the root frame is then ``R_world_root^T (0, 0, -g)``;
the simulated tracker stands level in the world, so the truth base frame
``T_meas_root = T_meas_world · [R_world_root | 0]`` carries the mount rotation (what
``--gravity level-tracker`` recovers from the fitted base frame).

Grammar of ``--mount``::

    floor            upright (identity)
    ceiling          hanging upside down: root z points down (180° about x)
    wall             on a vertical wall: root z horizontal (90° about y)
    tilt:DEG[,AZ]    base tilted by DEG degrees; the root z axis leans towards the
                     world azimuth AZ degrees (default 0, the world x axis)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.effects import Gravity
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import so3_exp
from hybrid_pk.robot import STANDARD_GRAVITY

__all__ = ["MOUNTS", "Mount", "mount_from_gravity", "parse_mount"]

MOUNTS = ("floor", "ceiling", "wall", "tilt:DEG[,AZ]")


@dataclass(frozen=True)
class Mount:
    """A mounting: its text and the rotation of the root frame in the world.

    Attributes:
        spec: the ``--mount`` text (or ``gravity:X,Y,Z`` for a given vector).
        rotation: ``(3, 3)`` ``R_world_root`` (world z up).
        g: magnitude of gravity [m/s²].
    """

    spec: str
    rotation: Tensor
    g: float = STANDARD_GRAVITY

    @property
    def gravity_root(self) -> Tensor:
        """``(3,)`` gravity in the robot root frame [m/s²]."""
        down = torch.tensor([0.0, 0.0, -self.g], dtype=self.rotation.dtype)
        return self.rotation.T @ down

    @property
    def gravity(self) -> Gravity:
        """The truth model's :class:`Gravity` (a root-frame vector)."""
        return Gravity(tuple(float(v) for v in self.gravity_root), "root")

    @property
    def tilt_deg(self) -> float:
        """Angle between the root z axis and the world's vertical [deg]."""
        return math.degrees(math.acos(max(-1.0, min(1.0, float(self.rotation[2, 2])))))

    def to_dict(self) -> dict:
        return {
            "spec": self.spec,
            "rotation": self.rotation.to(torch.float64).tolist(),
            "tilt_deg": self.tilt_deg,
            "gravity_root": [float(v) for v in self.gravity_root],
        }


def _rot(axis: tuple[float, float, float], angle: float) -> Tensor:
    return so3_exp(torch.tensor(axis, dtype=torch.float64) * angle)


def parse_mount(text: str) -> Mount:
    """A :class:`Mount` from ``--mount`` text (see the module grammar).

    Raises:
        HybridPKError: an unknown mounting or a bad angle.
    """
    spec = str(text).strip().lower()
    if spec == "floor":
        return Mount(spec, torch.eye(3, dtype=torch.float64))
    if spec == "ceiling":
        return Mount(spec, _rot((1.0, 0.0, 0.0), math.pi))
    if spec == "wall":
        return Mount(spec, _rot((0.0, 1.0, 0.0), math.pi / 2))
    name, _, arg = spec.partition(":")
    if name == "tilt":
        try:
            values = [float(v) for v in arg.split(",")] if arg.strip() else []
        except ValueError:
            values = []
        if len(values) not in (1, 2) or not all(math.isfinite(v) for v in values):
            raise HybridPKError(
                f"--mount {text!r}: write tilt:DEG or tilt:DEG,AZ (degrees), e.g. tilt:15"
            )
        deg, az = values[0], values[1] if len(values) > 1 else 0.0
        if not 0.0 <= deg <= 180.0:
            raise HybridPKError(f"--mount {text!r}: the tilt must lie in 0..180 degrees")
        a = math.radians(az)
        # z leans towards azimuth a: rotate about the horizontal axis perpendicular to it
        axis = (-math.sin(a), math.cos(a), 0.0)
        return Mount(spec, _rot(axis, math.radians(deg)))
    raise HybridPKError(f"--mount {text!r}: unknown mounting; choose one of {', '.join(MOUNTS)}")


def mount_from_gravity(gravity: Gravity) -> Mount:
    """The mounting with the smallest rotation that gives ``gravity`` (a root-frame
    vector) in the root frame; the yaw about the vertical is free and left zero."""
    if gravity.levelled:
        raise HybridPKError(
            "a simulated campaign needs gravity in the robot's root frame (X,Y,Z) or a "
            "--mount; level-tracker is what calibrate and diagnose assume of real data"
        )
    g = torch.tensor(gravity.vector, dtype=torch.float64)
    norm = float(g.norm())
    down = g / norm  # root-frame direction that must map to world -z
    target = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    axis = torch.linalg.cross(down, target)
    s, c = float(axis.norm()), float(down @ target)
    if s < 1e-12:
        R = torch.eye(3, dtype=torch.float64) if c > 0 else _rot((1.0, 0.0, 0.0), math.pi)
    else:
        R = so3_exp(axis / s * math.atan2(s, c))
    vec = ",".join(f"{v:g}" for v in gravity.vector)
    return Mount(f"gravity:{vec}", R, norm)

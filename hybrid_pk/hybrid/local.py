"""Local deformation networks: one small network per joint, carried to the flange.

A gravity-driven error arises *at* a joint or link: the bearing tilts, the gearbox
twists, the link bends, each by a small motion that depends on the static load there
(force and moment of the arm beyond, in that joint's frame) and perhaps on the joint's
own angle (eccentricity, transmission error). The rest of the arm carries that motion
rigidly to the flange. :class:`LocalFeatures` gives joint ``j``'s network exactly these
inputs, and :class:`LocalHead` composes the flange correction from the joints' small
twists ``(ω_j, v_j)`` (frame ``j``) with the exact lever arms of the chain::

    dp = Σ_j w_j (R_j ω_j × (p_E - p_j) + R_j v_j)        dw = Σ_j w_j R_j ω'_j

(``R_j``, ``p_j``: joint ``j``'s frame; ``p_E``: flange; all in joint 1's axes). The
load at a joint stays inside its training range far more often than the joint angles
do (turning the base or the wrist changes it little), and the lever arms are
geometry, so these networks extrapolate where a network on all joints cannot. Each
joint has its own coverage (``w_j``): a joint whose inputs were never seen falls back
to the base model alone, the others keep correcting.

Joint 1's angle is not an input by default (``local``): the prediction then turns with
joint 1 bit for bit, as for :class:`~hybrid_pk.hybrid.features.PhysicsFeatures`.
``local+q1`` lets joint 1's network read its angle (errors of the base bearing), where
the data covers it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hybrid_pk.errors import HybridPKError
from hybrid_pk.hybrid.features import (
    STANDARD_GRAVITY_VECTOR,
    StandardisedInputs,
    static_wrenches,
)
from hybrid_pk.hybrid.nets import GroupedDenseNet, parse_arch
from hybrid_pk.robot import Robot

__all__ = ["LOCAL_FEATURES", "LocalFeatures", "LocalHead", "LocalSpec"]

LOCAL_FEATURES = 8  # per joint: sin q, cos q (q, 0 if prismatic), force (3), moment (3)


@dataclass(frozen=True)
class LocalSpec:
    """What :class:`LocalFeatures` computes: ``local`` or ``local+q1``.

    Attributes:
        joint_1_angle: joint 1's network reads its angle (breaks the equivariance to q1).
    """

    joint_1_angle: bool = False

    @property
    def label(self) -> str:
        return "local+q1" if self.joint_1_angle else "local"

    @classmethod
    def parse(cls, text: str) -> LocalSpec:
        """``local`` or ``local+q1``.

        Raises:
            HybridPKError: anything else.
        """
        if text.strip() not in ("local", "local+q1"):
            raise HybridPKError(f"network inputs {text!r}: expected local or local+q1")
        return cls(text.strip() == "local+q1")


class LocalFeatures(StandardisedInputs):
    """Per-joint inputs ``(*B, dof, 8)`` and the chain geometry that carries each joint's
    twist to the flange.

    Buffers:
        gravity: ``(3,)`` gravity in the root frame [m/s^2].
        shift, scale: ``(dof, 8)`` standardisation of each joint's inputs.

    Args:
        spec: :class:`LocalSpec`.
        robot: the robot (not stored: passed to :meth:`encode`).
        gravity: gravity in the root frame [m/s^2].
    """

    def __init__(
        self,
        spec: LocalSpec,
        robot: Robot,
        gravity: Tensor | tuple[float, float, float] = STANDARD_GRAVITY_VECTOR,
    ) -> None:
        if robot.has_mimic:
            raise HybridPKError(
                f"network inputs {spec.label}: {robot.name!r} has mimic joints, which the "
                "physics inputs do not handle yet; use the joints inputs (--inputs joints)"
            )
        super().__init__(robot, gravity)
        self.spec = spec
        self.register_buffer("shift", torch.zeros(robot.dof, LOCAL_FEATURES, dtype=torch.float64))
        self.register_buffer("scale", torch.ones(robot.dof, LOCAL_FEATURES, dtype=torch.float64))

    @property
    def groups(self) -> int:
        """Networks (one per joint)."""
        return self.dof

    def raw(self, robot: Robot, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Unstandardised inputs ``(*B, dof, 8)`` at ``q (*B, dof)`` and the geometry:
        ``R (*B, dof, 3, 3)`` each joint's axes and ``lever (*B, dof, 3)`` joint origin
        -> flange [m], both in joint 1's axes (independent of q1)."""
        dof = self.dof
        q0 = torch.cat([torch.zeros_like(q[..., :1]), q[..., 1:]], -1)
        frames0 = robot.link_frames(q0)
        R01 = frames0[..., 0, :3, :3]
        g = self.gravity.to(q.dtype).expand(*q.shape[:-1], 3)
        if not self.gravity_along_joint_1:  # gravity as the q1 = 0 arm sees it
            R1 = robot.link_frames(q)[..., 0, :3, :3]
            g = (R01 @ R1.transpose(-1, -2) @ g[..., None])[..., 0]
        force, moment = static_wrenches(robot, frames0, g)
        angle = torch.where(
            torch.tensor(self.revolute, device=q.device),
            torch.sin(q),
            q,
        )
        other = torch.where(torch.tensor(self.revolute, device=q.device), torch.cos(q), 0.0)
        if not self.spec.joint_1_angle:
            angle = torch.cat([torch.zeros_like(angle[..., :1]), angle[..., 1:]], -1)
            other = torch.cat([torch.ones_like(other[..., :1]), other[..., 1:]], -1)
        u = torch.cat([angle[..., None], other[..., None], force, moment], -1)
        R01t = R01.transpose(-1, -2)[..., None, :, :]
        R = R01t @ frames0[..., :dof, :3, :3]
        arm = frames0[..., dof : dof + 1, :3, 3] - frames0[..., :dof, :3, 3]
        return u, {"R": R, "lever": (R01t @ arm[..., None])[..., 0]}

    def state(self) -> dict:
        """Plain data for a model file."""
        return {
            "kind": "local",
            "joint_1_angle": self.spec.joint_1_angle,
            **self.standardisation_state(),
        }

    @classmethod
    def from_state(cls, state: dict, robot: Robot) -> LocalFeatures:
        """Inverse of :meth:`state`."""
        out = cls(LocalSpec(bool(state["joint_1_angle"])), robot, state["gravity"])
        return out.load_standardisation(state)

    def extra_repr(self) -> str:
        return f"{self.spec.label}, dof={self.dof}"


class LocalHead(nn.Module):
    """One network per joint: its inputs -> a small twist, carried to the flange.

    Args:
        arch: architecture of every joint's network (e.g. ``mlp:32x2``).
        dof: joints (networks).
        scale: ``(n_out,)`` output units: ``(ω [rad] x3, v [m] x3)`` for a position
            head (``n_out = 6``), ``ω [rad] x3`` for an orientation head (3).
        zero_init: start at zero corrections.
    """

    def __init__(self, arch: str, dof: int, scale: Tensor, zero_init: bool = False) -> None:
        super().__init__()
        scale = scale.detach().to(torch.float64).reshape(-1)
        if scale.numel() not in (3, 6):
            raise ValueError(
                f"scale must have 3 (orientation) or 6 (position) entries, got {scale.numel()}"
            )
        spec = parse_arch(arch)
        if spec.family != "dense":
            raise HybridPKError(
                f"local networks need a dense architecture (mlp, mlp:WxD, D1, B1, ...), "
                f"not {arch!r}"
            )
        self.arch = arch
        hidden, act = spec.args["hidden"], spec.args.get("activation", "relu")
        self.nets = GroupedDenseNet(dof, LOCAL_FEATURES, hidden, scale.numel(), act)
        self.register_buffer("scale", scale.clone())
        if zero_init:
            self.nets.zero_output()

    @property
    def net_dtype(self) -> torch.dtype:
        return next(self.nets.parameters()).dtype

    @property
    def position(self) -> bool:
        return self.scale.numel() == 6

    def twists(self, u: Tensor) -> Tensor:
        """``(*B, dof, 8)`` inputs -> ``(*B, dof, n_out)`` twists in each joint's frame."""
        batch = u.shape[:-2]
        out = self.nets(u.reshape(-1, *u.shape[-2:]).to(self.net_dtype))
        return out.to(u.dtype).reshape(*batch, *out.shape[1:]) * self.scale.to(u.dtype)

    def correct(self, u: Tensor, geo: dict[str, Tensor], w: Tensor | None) -> Tensor:
        """``(*B, 3)`` flange correction in joint 1's axes: ``dp`` [m] (position head) or
        ``dw`` [rad] (orientation head), each joint's twist weighted by ``w (*B, dof)``."""
        tw = self.twists(u)
        if w is not None:
            tw = tw * w[..., None]
        R = geo["R"].to(u.dtype)
        omega = (R @ tw[..., :3, None])[..., 0]
        if not self.position:
            return omega.sum(-2)
        v = (R @ tw[..., 3:, None])[..., 0]
        return (torch.linalg.cross(omega, geo["lever"].to(u.dtype), dim=-1) + v).sum(-2)

    def extra_repr(self) -> str:
        return f"arch={self.arch!r}, outputs={self.scale.numel()}"

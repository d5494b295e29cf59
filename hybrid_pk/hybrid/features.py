"""Inputs of the residual networks chosen by the physics (issue 13).

An error that arises downstream of joint ``k`` turns rigidly with joints ``1..k``. In
the frame of link ``k`` it depends only on the joints after ``k`` and on the direction
of gravity there (which drives the deflections). :class:`PhysicsFeatures` therefore

- expresses the networks' corrections in the axes of link ``k`` (the frame joint ``k``
  moves, nominal robot at the commanded ``q``), so the prediction is *equivariant* to
  the joints before: turn them and the correction turns with the arm;
- feeds the networks only what the physics says the error can depend on:

  - the joints after ``k`` as ``(sin q, cos q)`` (revolute; a pose and its 2π twin
    are the same pose) or ``q`` (prismatic);
  - optionally the gravity direction in frame ``k`` (``gravity=True``; 3 values);
  - optionally the static load of the arm: ``wrench="torque"`` adds the gravity
    torque about each joint after ``k`` [Nm] (what twists its gearbox),
    ``wrench="full"`` the full static wrench at each of these joints in its own frame
    (force [N] and moment [Nm] of the arm beyond it: what bends the links and
    bearings too).

For ``k = 1`` and gravity along joint 1's axis (a floor- or ceiling-mounted robot)
every input is computed at ``q1 = 0``, so it is bit-for-bit independent of ``q1``: the
correction in the root frame turns with ``q1`` to floating-point rounding. For a
tilted mounting the gravity direction in frame 1 changes with ``q1`` and enters the
inputs (``gravity=True``) as the physics demands.

All inputs are standardised with the mean and spread of the training rows
(buffers ``shift`` and ``scale``). The payload is taken as 0: the tool's mass is part
of the campaign (the paper's limitation 6), a payload column does not enter here.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hybrid_pk.errors import HybridPKError
from hybrid_pk.robot import Robot

__all__ = [
    "STANDARD_GRAVITY_VECTOR",
    "WRENCHES",
    "FeatureSpec",
    "PhysicsFeatures",
    "StandardisedInputs",
    "cpu_copies",
    "gravity_along",
    "static_wrenches",
]

WRENCHES = ("none", "torque", "full")
STANDARD_GRAVITY_VECTOR = (0.0, 0.0, -9.80665)  # [m/s^2] in the robot root frame
_ANGLES = re.compile(r"q(\d+)-(\d+)")
_PARALLEL = 1e-9  # |sin| of the angle below which gravity counts as along joint 1


@dataclass(frozen=True)
class FeatureSpec:
    """What :class:`PhysicsFeatures` computes.

    Attributes:
        frame: ``k`` in ``1 .. dof-1``: corrections in link ``k``'s axes, from the
            joints after ``k``.
        gravity: add the gravity direction in frame ``k`` (3 inputs).
        wrench: ``none``, ``torque`` (gravity torque of each joint after ``k``) or
            ``full`` (static force and moment at each joint after ``k``, 6 each).
        angles: ``(first, last)`` (1-based, inclusive): read only these joints' angles,
            e.g. ``(2, 4)`` for the arm's posture without the wrist, whose angles mostly
            move the tool (the base model's geometry) and little load; None: every
            joint after ``k``. The load terms always cover every joint after ``k``.
        arm: ``qarm``: the angle joints are chosen on the training rows by
            :func:`~hybrid_pk.hybrid.posture.resolve_arm` (the joints that move the
            flange point), which sets ``angles``; unresolved specs build no inputs.
    """

    frame: int = 1
    gravity: bool = True
    wrench: str = "none"
    angles: tuple[int, int] | None = None
    arm: bool = False

    def angle_joints(self, dof: int) -> range:
        """0-based joints whose angles are inputs."""
        if self.arm:
            raise HybridPKError(
                f"network inputs {self.label}: qarm is chosen on the training rows "
                "(hybrid_pk.hybrid.posture.resolve_arm) before the inputs are built"
            )
        if self.angles is None:
            return range(self.frame, dof)
        return range(self.angles[0] - 1, self.angles[1])

    def check(self, robot: Robot) -> FeatureSpec:
        """``self``, or a :class:`HybridPKError` saying what to pass for ``robot``."""
        if not 1 <= self.frame < robot.dof:
            raise HybridPKError(
                f"network frame {self.frame}: pick a link 1..{robot.dof - 1} of "
                f"{robot.name!r} (the networks need at least one joint after it)"
            )
        if robot.has_mimic:
            raise HybridPKError(
                f"network inputs {self.label}: {robot.name!r} has mimic joints, which the "
                "physics inputs do not handle yet; use the joints inputs (--inputs joints)"
            )
        if self.wrench not in WRENCHES:
            raise HybridPKError(f"wrench {self.wrench!r}: one of {', '.join(WRENCHES)}")
        if (
            self.angles is not None
            and not self.frame < self.angles[0] <= self.angles[1] <= robot.dof
        ):
            raise HybridPKError(
                f"network inputs {self.label}: the angle joints must lie after the frame, "
                f"within {self.frame + 1}..{robot.dof}"
            )
        return self

    @property
    def label(self) -> str:
        """Short name, e.g. ``frame1+gravity+torque``."""
        parts = [f"frame{self.frame}"]
        parts += ["qarm"] if self.arm else []
        parts += [] if self.angles is None else [f"q{self.angles[0]}-{self.angles[1]}"]
        parts += ["gravity"] if self.gravity else []
        parts += [] if self.wrench == "none" else [self.wrench]
        return "+".join(parts)

    @classmethod
    def parse(cls, text: str) -> FeatureSpec:
        """Inverse of :attr:`label` (``frame2+torque``, ``frame1+q2-4+gravity+full``, ...).

        Raises:
            HybridPKError: an unknown part.
        """
        parts = [p.strip() for p in text.split("+") if p.strip()]
        if not parts or not parts[0].startswith("frame") or not parts[0][5:].isdigit():
            raise HybridPKError(
                f"network inputs {text!r}: expected frameK[+qI-J|+qarm][+gravity]"
                "[+torque|+full], e.g. frame1+qarm+torque"
            )
        angles = [p for p in parts[1:] if _ANGLES.fullmatch(p) or p == "qarm"]
        rest = set(parts[1:]) - set(angles[:1])
        unknown = rest - {"gravity", "torque", "full"}
        if unknown or {"torque", "full"} <= rest:
            raise HybridPKError(
                f"network inputs {text!r}: unknown or clashing part(s) "
                f"{sorted(unknown) or ['torque', 'full']}; parts: qI-J or qarm, gravity, torque "
                "or full"
            )
        wrench = "full" if "full" in rest else "torque" if "torque" in rest else "none"
        span = None
        if angles and angles[0] != "qarm":
            first, last = _ANGLES.fullmatch(angles[0]).groups()
            span = (int(first), int(last))
        return cls(int(parts[0][5:]), "gravity" in rest, wrench, span, angles[:1] == ["qarm"])


def cpu_copies(obj, *names: str) -> dict[str, Tensor]:
    """``{name: copy on the CPU}`` of the tensors ``obj.<name>`` (model-file state)."""
    return {name: getattr(obj, name).cpu().clone() for name in names}


def gravity_along(robot: Robot, gravity: Tensor) -> bool:
    """Whether ``gravity (3,)`` [root frame] lies along joint 1's axis (floor or ceiling
    mounting): then the arm's load does not change when joint 1 turns."""
    frame_1 = robot.link_frames(torch.zeros(robot.dof, dtype=torch.float64))[0, :3, :3]
    axis_1 = frame_1 @ robot.axis[0].detach().to(torch.float64)
    axis_1 = axis_1 / axis_1.norm()
    g = gravity.to(torch.float64)
    return bool(torch.linalg.cross(axis_1, g / g.norm().clamp_min(1e-12)).norm() < _PARALLEL)


def static_wrenches(
    robot: Robot, frames: Tensor, gravity: Tensor, first: int = 0
) -> tuple[Tensor, Tensor]:
    """Static load of the arm at each joint ``i >= first`` in that joint's frame.

    The force is the weight of everything beyond joint ``i``, the moment that of its
    centre of mass about joint ``i``'s origin (payload 0). Its component along the joint
    axis is :meth:`~hybrid_pk.robot.Robot.gravity_torques` with the opposite sign.

    Args:
        robot: the robot (segment masses and centres of mass).
        frames: ``(*B, dof + 1, 4, 4)`` from :meth:`~hybrid_pk.robot.Robot.link_frames`.
        gravity: ``(*B, 3)`` or ``(3,)`` gravity [m/s^2] in the frames' root.
        first: the first joint (0-based) to report.

    Returns:
        ``force (*B, dof - first, 3)`` [N] and ``moment (*B, dof - first, 3)`` [Nm].
    """
    dof, dtype = robot.dof, frames.dtype
    R, p = frames[..., :dof, :3, :3], frames[..., :dof, :3, 3]
    m = robot.segment_mass[1:].to(dtype)
    c = (R @ robot.segment_com[1:].to(dtype)[..., None])[..., 0]  # COM in the root
    moment = m[:, None] * (c + p)
    mass_out = m.flip(-1).cumsum(-1).flip(-1)
    arm = moment.flip(-2).cumsum(-2).flip(-2) - mass_out[:, None] * p  # (*B, dof, 3)
    g = gravity.to(dtype)[..., None, :].expand_as(arm)
    force = mass_out[:, None] * g
    torque = torch.linalg.cross(arm, g)
    Rt = R.transpose(-1, -2)[..., first:, :, :]
    return (Rt @ force[..., first:, :, None])[..., 0], (Rt @ torque[..., first:, :, None])[..., 0]


class StandardisedInputs(nn.Module):
    """Network inputs of a robot standardised by fitted buffers: the common part of
    :class:`PhysicsFeatures` and :class:`~hybrid_pk.hybrid.local.LocalFeatures`.

    A subclass registers the ``shift`` / ``scale`` buffers (the shape of its inputs)
    and defines :meth:`raw`.

    Buffers:
        gravity: ``(3,)`` gravity in the root frame [m/s^2].
    """

    def __init__(self, robot: Robot, gravity: Tensor | tuple[float, float, float]) -> None:
        super().__init__()
        self.dof = robot.dof
        self.revolute = [bool(r) for r in robot.revolute.tolist()]
        g = torch.as_tensor(gravity, dtype=torch.float64).reshape(3)
        self.register_buffer("gravity", g.clone())
        self.gravity_along_joint_1 = gravity_along(robot, g)

    def raw(self, robot: Robot, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Unstandardised inputs at ``q (*B, dof)`` and the geometry of the outputs."""
        raise NotImplementedError

    def fit_standardisation(self, robot: Robot, q: Tensor) -> StandardisedInputs:
        """Set ``shift`` / ``scale`` to the mean / spread of the inputs of rows ``q``."""
        with torch.no_grad():
            f, _ = self.raw(robot, q.to(torch.float64))
        self.shift.copy_(f.mean(0))
        self.scale.copy_(f.std(0).nan_to_num(0.0).clamp_min(1e-6 * f.abs().max().clamp_min(1)))
        return self

    def encode(self, robot: Robot, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Standardised inputs (the shape of ``shift``) and the geometry of :meth:`raw`."""
        f, geo = self.raw(robot, q)
        return (f - self.shift.to(f.dtype)) / self.scale.to(f.dtype), geo

    def standardisation_state(self) -> dict[str, Tensor]:
        """The buffers as plain data for a model file (the tail of ``state()``)."""
        return cpu_copies(self, "gravity", "shift", "scale")

    def load_standardisation(self, state: dict) -> StandardisedInputs:
        """Copy ``shift`` / ``scale`` of a ``state()`` into the buffers; returns self."""
        self.shift.copy_(state["shift"])
        self.scale.copy_(state["scale"])
        return self


class PhysicsFeatures(StandardisedInputs):
    """Network inputs and correction axes of :class:`FeatureSpec` for a robot.

    Buffers:
        gravity: ``(3,)`` gravity in the root frame [m/s^2].
        shift, scale: ``(n_features,)`` standardisation of the inputs.

    Args:
        spec: what to compute.
        robot: checked against ``spec`` (not stored: the caller passes it each time).
        gravity: gravity in the root frame [m/s^2] (default: floor mounting, -z).
    """

    def __init__(
        self,
        spec: FeatureSpec,
        robot: Robot,
        gravity: Tensor | tuple[float, float, float] = STANDARD_GRAVITY_VECTOR,
    ) -> None:
        super().__init__(robot, gravity)
        self.spec = spec.check(robot)
        n = self.n_features
        self.register_buffer("shift", torch.zeros(n, dtype=torch.float64))
        self.register_buffer("scale", torch.ones(n, dtype=torch.float64))

    @property
    def n_features(self) -> int:
        k, spec = self.spec.frame, self.spec
        after = range(k, self.dof)
        n = sum(2 if self.revolute[j] else 1 for j in spec.angle_joints(self.dof))
        n += 3 if spec.gravity else 0
        n += {"none": 0, "torque": 1, "full": 6}[spec.wrench] * len(after)
        return n

    def raw(self, robot: Robot, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Unstandardised inputs ``(*B, n_features)`` at ``q (*B, dof)``, and the
        geometry of the outputs: ``{"A": (*B, 3, 3)}``, link ``k``'s axes in joint 1's
        frame (``{}`` for ``k = 1``)."""
        k, spec = self.spec.frame, self.spec
        g = self.gravity.to(q.dtype)
        # Everything is computed at q1 = 0: bit-for-bit independent of q1. R1ᵀ Rk does
        # not depend on q1, and gravity along joint 1's axis is the same at any q1.
        q0 = torch.cat([torch.zeros_like(q[..., :1]), q[..., 1:]], -1)
        frames0 = robot.link_frames(q0)
        R0k = frames0[..., k - 1, :3, :3]
        if not self.gravity_along_joint_1:  # gravity as the q1 = 0 arm sees it
            R1, R01 = robot.link_frames(q)[..., 0, :3, :3], frames0[..., 0, :3, :3]
            g = (R01 @ R1.transpose(-1, -2) @ g[..., None])[..., 0]
        geo = {} if k == 1 else {"A": frames0[..., 0, :3, :3].transpose(-1, -2) @ R0k}
        parts = []
        for j in spec.angle_joints(self.dof):
            x = q[..., j : j + 1]
            parts += [torch.sin(x), torch.cos(x)] if self.revolute[j] else [x]
        if spec.gravity:
            g_k = (R0k.transpose(-1, -2) @ g.expand(*q.shape[:-1], 3)[..., None])[..., 0]
            parts.append(g_k / self.gravity.norm().to(q.dtype))
        if spec.wrench != "none":
            force, moment = static_wrenches(robot, frames0, g.expand(*q.shape[:-1], 3), k)
            if spec.wrench == "torque":
                axis = robot.axis[k:].detach().to(q.dtype)
                axis = axis / axis.norm(dim=-1, keepdim=True)
                parts.append((moment * axis).sum(-1))
            else:
                parts += [force.flatten(-2), moment.flatten(-2)]
        return torch.cat(parts, -1), geo

    def state(self) -> dict:
        """Plain data for a model file."""
        return {
            "kind": "physics",
            "frame": self.spec.frame,
            "gravity_input": self.spec.gravity,
            "wrench": self.spec.wrench,
            "angles": None if self.spec.angles is None else list(self.spec.angles),
            **self.standardisation_state(),
        }

    @classmethod
    def from_state(cls, state: dict, robot: Robot) -> PhysicsFeatures:
        """Inverse of :meth:`state`."""
        angles = state.get("angles")
        spec = FeatureSpec(
            int(state["frame"]),
            bool(state["gravity_input"]),
            state["wrench"],
            None if angles is None else (int(angles[0]), int(angles[1])),
        )
        return cls(spec, robot, state["gravity"]).load_standardisation(state)

    def extra_repr(self) -> str:
        return f"{self.spec.label}, n_features={self.n_features}"

"""Error-effect base class, operating conditions, and the effect registry.

An effect is a small ``nn.Module`` with one learnable ``value`` (the number of the
contract's vocabulary, in its unit). It acts in one of two places:

- ``stage = "joint"``: maps commanded joint values to true ones, ``apply_q``;
- ``stage = "geometry"``: perturbs the kinematic parameters, ``apply_params``.

Compliance is a joint effect solved as a fixed point by the model (it needs gravity
torques at the deflected configuration), so it only exposes its coefficient.

The same modules serve simulation (set ``value``) and identification (fit it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor, nn

from hybrid_pk.errors import HybridPKError
from hybrid_pk.robot import KinematicParams, Robot

__all__ = ["EFFECTS", "Conditions", "Effect", "approach_direction", "make_effect"]


@dataclass(frozen=True)
class Conditions:
    """Operating conditions of each sample besides ``q`` (all optional).

    Attributes:
        payload: ``(*B,)`` [kg] mass at the flange.
        temperature: ``(*B,)`` [°C].
        direction: ``(*B, dof)`` approach direction of each joint: +1, -1, or 0 (unknown).
        group: ``(*B,)`` long, which base/tool frame set a row uses (its file, when each
            file has its own frames); None = set 0.
    """

    payload: Tensor | None = None
    temperature: Tensor | None = None
    direction: Tensor | None = None
    group: Tensor | None = None

    def subset(self, index: Tensor) -> Conditions:
        return Conditions(*(None if x is None else x[index] for x in self._fields()))

    def _fields(self) -> tuple[Tensor | None, ...]:
        return (self.payload, self.temperature, self.direction, self.group)


def approach_direction(q: Tensor, file_index: Tensor | None = None) -> Tensor:
    """Direction each joint moved to reach each row, in acquisition order.

    ``sign(q[i] - q[i-1])``; a joint that did not move keeps its previous direction
    (it stays on the same side of its play); the first row of a file is 0 (unknown).

    Args:
        q: ``(N, dof)`` joint values in acquisition order.
        file_index: ``(N,)`` file of each row; rows of different files are not chained.
    """
    n = q.shape[0]
    first = torch.zeros(n, dtype=torch.bool, device=q.device)
    first[0] = True
    if file_index is not None:
        first[1:] = file_index[1:] != file_index[:-1]
    step = torch.zeros_like(q)
    step[1:] = torch.sign(q[1:] - q[:-1])
    step[first] = 0
    # Forward fill: each row takes the step of the last row (same file) where it moved.
    keep = (step != 0) | first[:, None]
    rows = torch.arange(n, device=q.device)[:, None].expand_as(q)
    last = torch.where(keep, rows, 0).cummax(dim=0).values
    return step.gather(0, last)


class Effect(nn.Module):
    """One physical error source with a single learnable ``value``.

    Class attributes:
        kind: vocabulary name (contract section 4).
        unit: unit of ``value``.
        stage: ``"joint"`` or ``"geometry"``.
        scale: typical magnitude of ``value``; identification works in ``value / scale``
            so that mm-, mrad- and µrad/Nm-sized parameters are equally conditioned.
        needs: which :class:`Conditions` field it reads, if any.
    """

    kind: ClassVar[str]
    unit: ClassVar[str]
    stage: ClassVar[str]
    scale: ClassVar[float]
    shape: ClassVar[tuple[int, ...]] = ()
    needs: ClassVar[str | None] = None
    per_joint: ClassVar[bool] = True

    def __init__(self, robot: Robot, joint: str | None = None, value=None) -> None:
        super().__init__()
        if self.per_joint:
            if joint not in robot.joint_names:
                raise HybridPKError(
                    f"effect {self.kind} needs a joint of {robot.name}: "
                    f"one of {', '.join(robot.joint_names)}; got {joint!r}"
                )
            self.joint_index = robot.joint_names.index(joint)
        self.joint = joint
        init = torch.zeros(self.shape, dtype=robot.dtype)
        if value is not None:
            init = torch.as_tensor(value, dtype=robot.dtype).reshape(self.shape).clone()
        self.value = nn.Parameter(init)

    @property
    def label(self) -> str:
        """``kind:joint`` (or ``kind``), the name used in reports and ``--effects``."""
        return f"{self.kind}:{self.joint}" if self.joint else self.kind

    def magnitude(self) -> float:
        """The contract's scalar ``value`` (vector effects: their norm)."""
        v = self.value.detach()
        return float(v) if v.dim() == 0 else float(v.norm())

    def report_value(self) -> float | list[float]:
        v = self.value.detach().to(torch.float64)
        return float(v) if v.dim() == 0 else [float(x) for x in v]

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:  # joint stage
        raise NotImplementedError

    def apply_params(self, params: KinematicParams, cond: Conditions) -> KinematicParams:
        raise NotImplementedError  # geometry stage

    def extra_repr(self) -> str:
        return f"{self.label}, value={self.report_value()} {self.unit}"


EFFECTS: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    EFFECTS[cls.kind] = cls
    return cls


def make_effect(robot: Robot, spec: str, value=None) -> Effect:
    """Effect from ``"kind:joint"`` or ``"kind"`` (e.g. ``"joint_offset:joint_2"``)."""
    kind, _, joint = spec.partition(":")
    if kind not in EFFECTS:
        raise HybridPKError(f"unknown effect {kind!r}; known effects: {', '.join(sorted(EFFECTS))}")
    cls = EFFECTS[kind]
    if cls.per_joint and not joint:
        raise HybridPKError(f"effect {kind} is per joint: write {kind}:JOINT")
    if not cls.per_joint and joint:
        raise HybridPKError(f"effect {kind} is not per joint: write just {kind}")
    return cls(robot, joint or None, value)

"""Error-effect base class, operating conditions, and the effect registry.

An effect is a small ``nn.Module`` with one learnable ``value`` (the number of the
contract's vocabulary, in its unit). It acts in one of two places:

- ``stage = "joint"``: maps commanded joint values to true ones, ``apply_q``;
- ``stage = "geometry"``: perturbs the kinematic parameters, ``apply_params``.

Compliance is a joint effect solved as a fixed point by the model (it needs gravity
torques at the deflected configuration), so it only exposes its coefficient.

The same modules serve simulation (set ``value``) and identification (fit it).

Which joint names a per-joint effect (:func:`effect_joint_names`): joint-space effects
(offsets, gear ratios, backlash, compliance, ...) name one of the robot's joints, the
independent ones that the data holds (a mimic leader, never a mimic joint); geometric
effects name a movable joint of the chain (mimic joints included) and act on the
origin in front of it, ``joint_index`` being its index along the chain.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor, nn

from hybrid_pk.effects.conditions import Conditions
from hybrid_pk.errors import HybridPKError
from hybrid_pk.robot import KinematicParams, Robot

__all__ = [
    "EFFECTS",
    "Effect",
    "effect_joint_names",
    "known_kinds",
    "make_effect",
    "register_family",
]


class Effect(nn.Module):
    """One physical error source with a single learnable ``value``.

    Class attributes:
        kind: vocabulary name (contract section 4).
        unit: unit of ``value``.
        stage: ``"joint"`` or ``"geometry"``.
        scale: typical magnitude of ``value``; identification works in ``value / scale``
            so that mm-, mrad- and µrad/Nm-sized parameters are equally conditioned.
        needs: which :class:`Conditions` field it reads, if any.
        joint_set: ``"robot"`` (named by one of ``robot.joint_names``) or ``"chain"``
            (one of ``robot.chain_joint_names``: geometric effects on an origin).
    """

    kind: ClassVar[str]
    unit: ClassVar[str]
    stage: ClassVar[str]
    scale: ClassVar[float]
    shape: ClassVar[tuple[int, ...]] = ()
    needs: ClassVar[str | None] = None
    per_joint: ClassVar[bool] = True
    joint_set: ClassVar[str] = "robot"

    def __init__(self, robot: Robot, joint: str | None = None, value=None) -> None:
        super().__init__()
        if self.per_joint:
            names = effect_joint_names(robot, type(self))
            if joint not in names:
                raise HybridPKError(
                    f"effect {self.kind} needs a joint of {robot.name}: "
                    f"one of {', '.join(names)}; got {joint!r}"
                )
            self.joint_index = names.index(joint)
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


class _Registry(dict):
    """Effect kinds by name: the registered ones, and the members of each family
    (``cyclic_error_<n>``, one kind per order ``n``) built on demand. Iterating lists
    the registered kinds only."""

    # prefix -> (build(kind): the member's class or None, the family's name in lists)
    families: ClassVar[dict[str, tuple[Callable[[str], type[Effect] | None], str]]] = {}

    def _member(self, kind: object) -> type[Effect] | None:
        if not isinstance(kind, str):
            return None
        for prefix, (build, _) in self.families.items():
            if kind.startswith(prefix):
                return build(kind)
        return None

    def __missing__(self, kind: str) -> type[Effect]:
        cls = self._member(kind)
        if cls is None:
            raise KeyError(kind)
        return cls

    def __contains__(self, kind: object) -> bool:
        return dict.__contains__(self, kind) or self._member(kind) is not None


EFFECTS: dict[str, type[Effect]] = _Registry()


def register_family(prefix: str, build: Callable[[str], type[Effect] | None], shown: str) -> None:
    """Kinds ``prefix...`` are made by ``build(kind)`` (None: not a member); ``shown``
    names the family in lists of known effects."""
    _Registry.families[prefix] = (build, shown)


def known_kinds() -> str:
    """The effect kinds for an error message: registered ones and families."""
    return ", ".join(sorted(EFFECTS) + sorted(shown for _, shown in _Registry.families.values()))


def effect_joint_names(robot: Robot, cls: type[Effect]) -> list[str]:
    """The joints an effect of class ``cls`` may name on ``robot`` (in index order)."""
    return robot.chain_joint_names if cls.joint_set == "chain" else robot.joint_names


def register(cls: type[Effect]) -> type[Effect]:
    EFFECTS[cls.kind] = cls
    return cls


def make_effect(robot: Robot, spec: str, value=None) -> Effect:
    """Effect from ``"kind:joint"`` or ``"kind"`` (e.g. ``"joint_offset:joint_2"``)."""
    kind, _, joint = spec.partition(":")
    if kind not in EFFECTS:
        raise HybridPKError(f"unknown effect {kind!r}; known effects: {known_kinds()}")
    cls = EFFECTS[kind]
    if cls.per_joint and not joint:
        raise HybridPKError(f"effect {kind} is per joint: write {kind}:JOINT")
    if not cls.per_joint and joint:
        raise HybridPKError(f"effect {kind} is not per joint: write just {kind}")
    return cls(robot, joint or None, value)

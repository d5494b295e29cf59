"""Error-effect base class, operating conditions, and the effect registry.

An effect is a small ``nn.Module`` with one learnable ``value`` (the number of the
contract's vocabulary, in its unit). It acts in one of two places:

- ``stage = "joint"``: maps commanded joint values to true ones, ``apply_q`` (a map of
  its own joint alone may also give ``joint_derivatives(q, cond, step) -> (d q_j /
  d q_j (*B,), d q_j / d value (size, *B) per step)`` in closed form: the
  identification Jacobian then skips its forward-mode pass);
- ``stage = "geometry"``: perturbs the kinematic parameters, ``apply_params``;
- ``stage = "compliance"``: a joint spring, solved as a fixed point by the model (it
  needs gravity torques at the deflected configuration), so it only exposes its
  coefficient;
- ``stage = "deflection"``: bends an origin under the static wrench the model computes
  once per forward pass (``apply_deflection``).

Each class also describes itself to the rest of the library (limits, candidate
selection, plausibility, planning, evidence plots, simulation, IK conditions, help
texts read these class attributes, never the kind's name): see :class:`Effect`.

The same modules serve simulation (set ``value``) and identification (fit it).

Which joint names a per-joint effect (:func:`effect_joint_names`): joint-space effects
(offsets, gear ratios, backlash, compliance, ...) name one of the robot's joints, the
independent ones that the data holds (a mimic leader, never a mimic joint); geometric
effects name a movable joint of the chain (mimic joints included) and act on the
origin in front of it, ``joint_index`` being its index along the chain.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar, Literal

import torch
from torch import Tensor, nn

from hybrid_pk.effects.conditions import Conditions
from hybrid_pk.errors import HybridPKError
from hybrid_pk.robot import KinematicParams, Robot
from hybrid_pk.robot.chain import plain_inputs

__all__ = [
    "EFFECTS",
    "SIGN_SIGMAS",
    "Effect",
    "EvidenceVariable",
    "JointRule",
    "Stage",
    "effect_joint_names",
    "effect_joint_types",
    "entry_label",
    "family_members",
    "known_kinds",
    "make_effect",
    "register_family",
    "sds_below",
]


Stage = Literal["joint", "compliance", "geometry", "deflection"]
# The joints an effect may sit on: revolute ones only, prismatic ones only, any, or
# none (one value for the whole robot).
JointRule = Literal["revolute", "prismatic", "any", "none"]
# What an evidence plot puts on its x axis: the joint's angle, the gravity torque on the
# joint, the static moment at the joint, the row's temperature, or the approach
# direction the acquisition order gives.
EvidenceVariable = Literal["joint_angle", "torque", "moment", "temperature", "row_order", "pose"]
# A fitted component counts as below zero (a ``positive`` effect's sign rule) when it
# lies more than this many of its standard deviations below: within that it is zero as
# far as the rows can tell (a true zero falls that far below in 0.13 % of fits).
SIGN_SIGMAS = 3.0


class Effect(nn.Module):
    """One physical error source with a single learnable ``value``.

    Class attributes (what the rest of the library asks an effect):
        kind: vocabulary name (contract section 4).
        unit: unit of ``value``.
        stage: where it acts, one of ``"joint"`` (commanded -> true joint value,
            :meth:`apply_q`), ``"compliance"`` (a joint spring the model solves as a
            fixed point), ``"geometry"`` (the kinematic parameters, :meth:`apply_params`)
            or ``"deflection"`` (an origin bent by the static wrench).
        scale: typical magnitude of ``value``; identification works in ``value / scale``
            so that mm-, mrad- and µrad/Nm-sized parameters are equally conditioned.
        needs: which :class:`Conditions` field it reads, if any (``"direction"``,
            ``"temperature"``, ``"payload"``).
        joint_set: ``"robot"`` (named by one of ``robot.joint_names``) or ``"chain"``
            (one of ``robot.chain_joint_names``: geometric effects on an origin).
        joints: the joints it may sit on (:data:`JointRule`); ``"none"`` for an effect
            that is not per joint.
        positive: its physical sign rule: True where a negative value is not physical
            (play, compliance), so simulation draws it >= 0 and the diagnosis refuses
            a value below zero (:meth:`refused`, which an effect may widen).
        floor: the least value a component may take under that rule or an effect's own
            :meth:`refused` (0; a thermal expansion's most negative structure).
        limit: largest credible norm of ``value`` [its unit] (None: depends on the loads
            or the data); :func:`~hybrid_pk.effects.limits.effect_limit` adapts it to a
            prismatic joint.
        drawn: largest norm simulation draws it at, where real robots stay well below
            ``limit`` (None: ``limit``; :func:`~hybrid_pk.effects.limits.drawn_limit`).
        unplannable: None when the choice of poses controls its information; otherwise
            why not (pose planning leaves it out and says so).
        evidence: the variable its evidence plot shows it against (:data:`EvidenceVariable`).
        order: cycles per turn of its joint when its law is periodic in that joint's
            angle (0: not periodic). From 2 up the law repeats within a turn, and what
            is fitted on part of the joint's range must hold beyond it (the diagnosis
            checks it on the ends of that range).
        simulate_random: drawn by ``simulate --effects random[:K]``.
        first_joint_is_frame: on the first joint it is a base-frame error (simulation
            does not draw it there; the diagnosis does not test geometric ones there).
        needs_torque: only observable on a joint that gravity loads (simulation draws it
            on such joints only).
        law: its law in words, as evidence plots show it.
        equation: its model in one line (the contract's vocabulary table).
        description: its model with what the user needs to know (the README's table).
    """

    kind: ClassVar[str]
    unit: ClassVar[str]
    stage: ClassVar[Stage]
    scale: ClassVar[float]
    shape: ClassVar[tuple[int, ...]] = ()
    needs: ClassVar[str | None] = None
    per_joint: ClassVar[bool] = True
    joint_set: ClassVar[str] = "robot"
    joints: ClassVar[JointRule] = "any"
    positive: ClassVar[bool] = False
    floor: ClassVar[float] = 0.0
    limit: ClassVar[float | None] = None
    drawn: ClassVar[float | None] = None
    unplannable: ClassVar[str | None] = None
    evidence: ClassVar[EvidenceVariable] = "joint_angle"
    order: ClassVar[int] = 0
    simulate_random: ClassVar[bool] = False
    first_joint_is_frame: ClassVar[bool] = False
    needs_torque: ClassVar[bool] = False
    law: ClassVar[str] = ""
    equation: ClassVar[str] = ""
    description: ClassVar[str] = ""

    @classmethod
    def refused(cls, value: float | list[float], std=None) -> list[str]:
        """Why a fitted ``value`` (as reported) cannot be this effect at all, whatever
        its size; empty where it can. The diagnosis refuses such a candidate at its
        refit, takes out a cause a later refit carries there, and lists either as a
        structural finding. The base rule: a ``positive`` effect below zero
        (:meth:`below_zero`; ``std``: the value's standard deviation, as reported,
        where the fit gave one)."""
        if cls.positive and cls.below_zero(value, std, cls.floor):
            return [
                f"negative {cls.kind} ({value:.3g} {cls.unit}{sds_below(value, std)}) is not "
                "physical: it likely absorbs another, unmodelled error"
            ]
        return []

    @classmethod
    def implausible(cls, value: float | list[float], std=None) -> list[str]:
        """Why a fitted ``value`` (as reported) is not physically credible, the warnings
        of a named cause; empty where it is. The base rule: what :meth:`refused` says."""
        return cls.refused(value, std)

    @staticmethod
    def below_zero(value: float | list[float], std=None, floor: float = 0.0) -> bool:
        """Whether a component of ``value`` is below ``floor`` (default zero): by more
        than :data:`SIGN_SIGMAS` of its standard deviation where ``std`` gives it
        (finite), else at all."""
        sds = _sds(value, std)
        return any(v < floor - SIGN_SIGMAS * s for v, s in zip(_listed(value), sds, strict=True))

    @classmethod
    def allowed_on(cls, joint_type: str) -> bool:
        """Whether it may sit on a joint of type ``joint_type`` (``"revolute"``, ...)."""
        if cls.joints == "any":
            return True
        if cls.joints == "prismatic":
            return joint_type == "prismatic"
        return cls.joints == "revolute" and joint_type != "prismatic"

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
            init = self._checked_value(value, init)
        self.value = nn.Parameter(init)

    def _checked_value(self, value, like: Tensor) -> Tensor:
        """``value`` as a finite tensor of the effect's shape, else a one-line error."""
        what = f"{self.kind} value must be {tuple(self.shape) or 'a number'} [{self.unit}]"
        try:
            v = torch.as_tensor(value, dtype=like.dtype)
        except (TypeError, ValueError, RuntimeError):
            raise HybridPKError(f"{what}, got {value!r}") from None
        if v.numel() != like.numel():
            raise HybridPKError(f"{what}, got shape {tuple(v.shape)}")
        if not torch.isfinite(v).all():
            raise HybridPKError(f"{what}, finite, got {value!r}")
        return v.reshape(self.shape).clone()

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

    def inert(self) -> bool:
        """Whether applying it changes nothing: a built-in effect that reads no condition,
        at exactly zero (a candidate being scored), its value plain (no derivative taken
        through it). Its law then adds 0 x something finite (a rotation by exp(0) = I),
        so skipping it gives the same values, up to the sign of a zero. A plug-in may do
        anything at zero, and one that reads a condition still runs, for its error where
        the rows lack it."""
        return (
            type(self).__module__.startswith("hybrid_pk.effects.")
            and self.needs is None
            and plain_inputs(self.value)
            and not bool(self.value.detach().any())
        )

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

    # prefix -> (build(kind): the member's class or None, the family's name in lists,
    # the class its members derive from)
    families: ClassVar[
        dict[str, tuple[Callable[[str], type[Effect] | None], str, type[Effect] | None]]
    ] = {}

    def _member(self, kind: object) -> type[Effect] | None:
        if not isinstance(kind, str):
            return None
        for prefix, (build, _, _) in self.families.items():
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


def _listed(value) -> list[float]:
    return [float(v) for v in (value if isinstance(value, list | tuple) else [value])]


def _sds(value, std) -> list[float]:
    """Per component of ``value``, its standard deviation (0 where ``std`` gives none
    or a NaN one: then any value below zero counts)."""
    n = len(_listed(value))
    sds = [0.0] * n if std is None else _listed(std)
    if len(sds) != n:
        sds = [0.0] * n
    return [s if s == s and s > 0 else 0.0 for s in sds]


def sds_below(value, std) -> str:
    """``", k std below zero"`` for the most negative component where ``std`` gives
    it; empty otherwise."""
    sds = _sds(value, std)
    ratios = [-v / s for v, s in zip(_listed(value), sds, strict=True) if s > 0 and v < 0]
    return f", {max(ratios):.3g} std below zero" if ratios else ""


def register_family(
    prefix: str,
    build: Callable[[str], type[Effect] | None],
    shown: str,
    common: type[Effect] | None = None,
) -> None:
    """Kinds ``prefix...`` are made by ``build(kind)`` (None: not a member); ``shown``
    names the family in lists of known effects; ``common`` is the class every member
    derives from (it describes the family: unit, law, ...)."""
    _Registry.families[prefix] = (build, shown, common)


def family_members() -> list[tuple[str, type[Effect]]]:
    """``(prefix<n>, common class)`` of every family of kinds that states its class."""
    return [(f"{p}<n>", c) for p, (_, _, c) in _Registry.families.items() if c is not None]


def known_kinds() -> str:
    """The effect kinds for an error message: registered ones and families."""
    return ", ".join(sorted(EFFECTS) + sorted(f[1] for f in _Registry.families.values()))


def effect_joint_names(robot: Robot, cls: type[Effect]) -> list[str]:
    """The joints an effect of class ``cls`` may name on ``robot`` (in index order)."""
    return robot.chain_joint_names if cls.joint_set == "chain" else robot.joint_names


def effect_joint_types(robot: Robot, cls: type[Effect]) -> list[str]:
    """The types of :func:`effect_joint_names` (``"revolute"``, ``"prismatic"``, ...)."""
    return robot.chain_joint_types if cls.joint_set == "chain" else robot.joint_types


def register(cls: type[Effect]) -> type[Effect]:
    EFFECTS[cls.kind] = cls
    return cls


def entry_label(entry) -> str:
    """``kind:joint`` (or ``kind``) of a JSON effect entry ``{"effect", "joint", ...}``
    (a truth file's, a model file's, a diagnosis'), as :attr:`Effect.label` names it."""
    joint = entry.get("joint")
    return entry["effect"] if joint is None else f"{entry['effect']}:{joint}"


def make_effect(robot: Robot, spec: str, value=None) -> Effect:
    """Effect from ``"kind:joint"`` or ``"kind"`` (e.g. ``"joint_offset:joint_2"`` on rx160).

    Args:
        robot: the robot the effect acts on.
        spec: effect kind and, for per-joint kinds, a joint name as in the URDF
            (``robot.joint_names``; geometric kinds: ``robot.chain_joint_names``).
        value: the effect's value in its unit (``EFFECTS[kind].unit``: ``rad`` for
            ``joint_offset`` / ``backlash``, ``m`` for ``link_length``, ...), a number or
            a sequence of the kind's ``shape`` (``link_length``: ``(3,)`` [m]); None: 0.

    Raises:
        HybridPKError: unknown kind, joint not of the robot, or a value of the wrong
            shape or not finite.
    """
    kind, _, joint = spec.partition(":")
    if kind not in EFFECTS:
        raise HybridPKError(f"unknown effect {kind!r}; known effects: {known_kinds()}")
    cls = EFFECTS[kind]
    if cls.per_joint and not joint:
        raise HybridPKError(f"effect {kind} is per joint: write {kind}:JOINT")
    if not cls.per_joint and joint:
        raise HybridPKError(f"effect {kind} is not per joint: write just {kind}")
    return cls(robot, joint or None, value)

"""A :class:`~hybrid_pk.hybrid.HybridFK` from an inputs string and training rows.

The inputs string names the stages (:mod:`~hybrid_pk.hybrid.stage`)::

    joints                                   the paper's networks on every joint
    frame1+qarm+torque                       one stage of physics inputs (qarm: the
                                             joints that move the flange point,
                                             :mod:`~hybrid_pk.hybrid.posture`)
    frame1+qarm+torque/joints,local+q1       cascade: posture networks refined by
                                             networks on every joint, then local
                                             deformation networks, then the physics

``,`` starts a new cascade stage (a level of fall-back), ``/`` a refinement of the
stage before it. Each stage's inputs are standardised over the training rows and get a
coverage fitted on the validation rows (:func:`fit_coverages`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import so3_log
from hybrid_pk.hybrid.blocked_trust import JointGate
from hybrid_pk.hybrid.coverage import Coverage
from hybrid_pk.hybrid.features import PhysicsFeatures
from hybrid_pk.hybrid.hybrid_fk import HybridFK
from hybrid_pk.hybrid.inputs import InputBox, parse_inputs
from hybrid_pk.hybrid.local import LocalFeatures, LocalSpec
from hybrid_pk.hybrid.losses import ResidualTargets
from hybrid_pk.hybrid.posture import resolve_arm
from hybrid_pk.hybrid.spread import TargetSpread
from hybrid_pk.hybrid.stage import NetworkInputs, ResidualStage, check_stages
from hybrid_pk.robot import Robot

__all__ = [
    "DEFAULT_INPUTS",
    "TRUSTS",
    "HybridSettings",
    "build_hybrid",
    "check_trust",
    "fit_coverages",
    "fit_gates",
    "fit_spreads",
    "parse_stages",
]

TRUSTS = ("auto", "box", "coverage", "none")
DEFAULT_INPUTS = "frame1+qarm+torque/joints,local+q1"


@dataclass(frozen=True)
class HybridSettings:
    """How :func:`build_hybrid` builds the stages.

    Attributes:
        position_net, orientation_net: architectures of the networks of the cascade
            stages on all joints or physics features (None: no such network).
        refine_net: architecture of the refine stages' networks.
        local_net: architecture of each joint's network in local stages.
        trust: ``auto`` (the joint box for ``joints`` alone, else a coverage for every
            stage; ``joints`` stages keep their box too), ``box`` (``joints`` alone only),
            ``coverage`` or ``none`` (the networks apply everywhere).
        input_range: ``data`` or ``limits``: normalisation range of ``joints`` inputs.
        fade: fade-out width outside the joint box, fraction of its size.
        coverage_quantile, coverage_ratio: coverage of the stages on all joints or on
            physics features (a network of the posture extrapolates poorly: tight).
        local_coverage_quantile, local_coverage_ratio: coverage of local stages (their
            structure carries the loads to the flange: wider).
        zero_init: start every network at zero output.
        spread: shrink a refined stage's correction where its refine stage is off, by
            the spread of its training targets (:mod:`~hybrid_pk.hybrid.spread`), if
            the blocked hold-out keeps it (``blocked``).
        blocked: test each stage on physics inputs on blocked hold-out of its training
            rows before it is used away from them (:mod:`~hybrid_pk.hybrid.blocked_trust`);
            off: every such stage stays gated to its training joints.
    """

    position_net: str | None = "mlp"
    orientation_net: str | None = "mlp"
    refine_net: str = "mlp"
    local_net: str = "mlp:32x2"
    trust: str = "auto"
    input_range: str = "data"
    fade: float = 0.0
    # a posture network is trusted in full only as close to its training rows as 9 in
    # 10 held-out rows of the training region lie: the farthest tenth already lies in
    # the gaps between training rows, where a posture network starts to extrapolate
    coverage_quantile: float = 0.9
    # its weight reaches zero half that distance again further out: a fade as wide as
    # half the trusted radius keeps the blend's slope (and the IK's Jacobian) moderate
    coverage_ratio: float = 1.5
    # local stages carry the loads to the flange by their structure, so they are
    # trusted where 99 in 100 held-out rows lie (the rare farthest rows excepted) ...
    local_coverage_quantile: float = 0.99
    # ... and fade out by twice that distance (a direct Coverage's own defaults)
    local_coverage_ratio: float = 2.0
    zero_init: bool = True
    spread: bool = True
    # issue 27: what extrapolates is measured, not assumed (off: gated, never worse
    # than the physics away from the training rows, and no probe fits to pay for)
    blocked: bool = True


def parse_stages(text: str) -> list[tuple[str, str]]:
    """``(inputs, role)`` of each stage of an inputs string (see the module docstring).

    Raises:
        HybridPKError: an unknown part, or stages that do not combine.
    """
    out = []
    for group in text.split(","):
        for i, part in enumerate(group.split("/")):
            part = part.strip()
            if not part:
                raise HybridPKError(f"network inputs {text!r}: an empty stage")
            if part != "joints":
                parse_inputs(part)
            out.append((part, "cascade" if i == 0 else "refine"))
    for i, (part, role) in enumerate(out):
        local = part.startswith("local")
        if local and (i != len(out) - 1 or role != "cascade"):
            raise HybridPKError(
                f"network inputs {text!r}: local networks must be the last stage (they have "
                "one weight per joint), e.g. frame1+qarm+torque/joints,local+q1"
            )
    return out


def check_trust(trust: str, inputs: str) -> list[tuple[str, str]]:
    """The stages of ``inputs`` (:func:`parse_stages`), checked against ``trust``: the
    joint box (``box``) is the trust region of the ``joints`` inputs alone.

    Raises:
        HybridPKError: ``box`` with other inputs, or inputs that do not parse.
    """
    plan = parse_stages(inputs)
    if trust == "box" and [spec for spec, _ in plan] != ["joints"]:
        raise HybridPKError(
            f"trust 'box' needs the joints inputs alone, not {inputs!r}; use trust coverage"
        )
    return plan


def _inputs(spec: str, settings: HybridSettings, robot: Robot, q: Tensor) -> NetworkInputs:
    limits = robot.joint_limits if settings.input_range == "limits" else None
    if spec == "joints":
        if settings.trust == "none":  # an unbounded box: the networks apply everywhere
            box = InputBox.from_data(q, limits, 1.0)
            inf = torch.full_like(box.trust_lower, math.inf)
            return InputBox(box.lower, box.upper, -inf, inf, 1.0)
        return InputBox.from_data(q, limits, settings.fade)
    parsed = parse_inputs(spec)  # build_hybrid's check_trust left no box to non-joints
    if isinstance(parsed, LocalSpec):
        return LocalFeatures(parsed, robot).fit_standardisation(robot, q)
    return PhysicsFeatures(resolve_arm(parsed, robot, q), robot).fit_standardisation(robot, q)


def build_hybrid(
    base: ExtendedModel,
    inputs: str,
    settings: HybridSettings,
    q: Tensor,
    position_scale: Tensor | None = None,
    orientation_scale: Tensor | None = None,
) -> HybridFK:
    """Fresh networks for the stages of ``inputs`` (no coverage yet), standardised over
    the training joints ``q (N, dof)``.

    Args:
        position_scale, orientation_scale: ``(3,)`` output units [m], [rad]; None
            orientation scale and ``settings.orientation_net``: no orientation networks.
    """
    plan = check_trust(settings.trust, inputs)
    stages = []
    for spec, role in plan:
        feats = _inputs(spec, settings, base.robot, q)
        own = settings.local_net if isinstance(feats, LocalFeatures) else settings.refine_net
        if role == "cascade" and not isinstance(feats, LocalFeatures):
            pos, ori = settings.position_net, settings.orientation_net
        else:
            pos = own if settings.position_net else None
            ori = own if settings.orientation_net else None
        stages.append(
            ResidualStage.build(
                feats, pos, ori, position_scale, orientation_scale, settings.zero_init, role
            )
        )
    check_stages(stages)
    first, *more = stages
    return HybridFK(base, first.inputs, first.position, first.orientation, None, more)


def fit_coverages(
    hybrid: HybridFK,
    train: list[tuple[Tensor, dict]],
    val: list[tuple[Tensor, dict]],
    settings: HybridSettings,
) -> None:
    """Give every stage its coverage from its encoded training and validation inputs
    (``hybrid.encode_all``), unless the settings trust a lone ``joints`` stage's box
    (``auto``, ``box``) or nothing (``none``)."""
    alone_box = len(hybrid.stages) == 1 and hybrid.box is not None
    if settings.trust == "none" or (alone_box and settings.trust in ("auto", "box")):
        return
    for i, stage in enumerate(hybrid.stages):
        local = stage.grouped
        hybrid.set_coverage(
            Coverage.from_inputs(
                train[i][0],
                val[i][0],
                quantile=settings.local_coverage_quantile if local else settings.coverage_quantile,
                ratio=settings.local_coverage_ratio if local else settings.coverage_ratio,
            ),
            i,
        )


def fit_gates(hybrid: HybridFK, q_train: Tensor, q_val: Tensor, settings: HybridSettings) -> None:
    """Gate every stage on physics inputs to its training joints ``q_train`` (radius set
    by the validation joints ``q_val``, with the stage's coverage quantile and ratio),
    unless the settings trust the networks everywhere (``none``). A stage on every joint
    needs none: its own trust is a joint-space coverage already."""
    if settings.trust == "none":
        return
    for stage in hybrid.stages:
        if stage.box is None:
            local = stage.grouped
            stage.gate = JointGate.fit(
                q_train,
                q_val,
                settings.local_coverage_quantile if local else settings.coverage_quantile,
                settings.local_coverage_ratio if local else settings.coverage_ratio,
            )


def fit_spreads(
    hybrid: HybridFK,
    train: list[tuple[Tensor, dict]],
    targets: ResidualTargets,
    settings: HybridSettings,
) -> None:
    """Give every cascade stage that a refine stage follows the spread of its training
    ``targets`` among rows of nearly equal inputs (``train``: ``hybrid.encode_all`` of
    the training rows), unless ``settings.spread`` is off."""
    if not settings.spread:
        return
    rotation = None if targets.rotation is None else so3_log(targets.rotation)
    stages = hybrid.stages
    for i, stage in enumerate(stages[:-1]):
        if stage.role == "cascade" and stages[i + 1].role == "refine":
            stage.spread = TargetSpread.from_targets(train[i][0], targets.position, rotation)

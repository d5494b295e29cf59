"""`HybridFK`: a base model (nominal or calibrated) corrected by two residual networks.

Composition (all differentiable w.r.t. ``q``)::

    E  = base.end_pose(q, cond)                       flange in the robot root frame
    R1 = axes of the frame joint 1 moves (nominal robot at the commanded q)
    u, A = inputs(q)                                  network inputs, axes of the output
    E* = [exp(R1 A w dw(u)) R_E | p_E + R1 A w dp(u)] corrected flange pose
    T  = T_meas_root · E* · T_end_point               measured point, measurement frame

``dp`` [m] and ``dw`` [rad, axis-angle] are the position and orientation networks'
outputs times their output scales; ``w`` in [0, 1] is their trust. Two kinds of inputs:

- :class:`~hybrid_pk.hybrid.inputs.InputBox` (the paper's): every joint, min-max
  normalised, corrections in joint 1's axes (``A = I``), trust 1 inside the training
  rows' joint box and 0 (or fading out) outside it;
- :class:`~hybrid_pk.hybrid.features.PhysicsFeatures` (issue 13): corrections in the
  axes of link ``k`` (``A = R1ᵀ Rk``), from the joints after ``k``, the gravity
  direction and the static load there: equivariant to the joints before ``k``.

An optional :class:`~hybrid_pk.hybrid.coverage.Coverage` replaces the trust by the
distance to the training rows in the networks' own input space (physics as fall-back,
a smooth blend between).

Why the *flange* is corrected in robot coordinates: the networks then do not depend on
the base and tool frames, so a re-fitted tracker or tool frame (``calibrate --refit``)
leaves them valid, and the frame sets of several files share them. Why joint 1's axes
even for the paper's inputs: every error that arises downstream of joint 1 turns with
it (on the RX160 acceptance data: 1.4 x lower error after 30 epochs than in root axes).
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.hybrid.coverage import Coverage
from hybrid_pk.hybrid.inputs import DEFAULT_FADE, InputBox, joint_1_axes
from hybrid_pk.hybrid.networks_state import networks_state, stages_from_state
from hybrid_pk.hybrid.stage import (
    Head,
    NetworkInputs,
    ResidualStage,
    check_stages,
    combine_stages,
    refine_trust,
)

__all__ = [
    "DEFAULT_FADE",
    "Head",
    "HybridFK",
    "NetworkInputs",
    "correction_axes",
    "frame_matrices",
]


def correction_axes(base: ExtendedModel, q: Tensor) -> Tensor:
    """``(*B, 3, 3)`` axes in which the training targets are kept: joint 1's frame in the
    root frame (nominal robot at the commanded ``q (*B, dof)``)."""
    return joint_1_axes(base.robot, q)


def frame_matrices(model: ExtendedModel, cond: Conditions | None) -> tuple[Tensor, Tensor]:
    """Base ``T_meas_root`` and tool ``T_end_point`` of each row: ``(4, 4)`` when shared,
    ``(*B, 4, 4)`` when rows pick their frame set with ``cond.group``."""
    group = None if cond is None else cond.group
    if group is None or model.base.sets == 1:
        return model.base.matrix()[0], model.tool.matrix()[0]
    return model.base.matrix(group), model.tool.matrix(group)


class HybridFK(nn.Module):
    """Base model + residual networks in one or more stages.

    The first stage is given by ``inputs``, ``position``, ``orientation`` and
    ``coverage``; ``more`` stages follow it (:mod:`~hybrid_pk.hybrid.stage`: cascade
    levels of fall-back and refinements). :attr:`inputs`, :attr:`position`,
    :attr:`orientation`, :attr:`coverage` and :attr:`box` are the first stage's.

    Args:
        base: the nominal or calibrated model (frames + effects); not trained here.
        inputs: the first networks' inputs (:class:`InputBox`, :class:`PhysicsFeatures`
            or :class:`~hybrid_pk.hybrid.local.LocalFeatures`).
        position: head predicting the flange position correction ``dp`` [m], or None.
        orientation: head predicting the flange rotation correction ``dw`` [rad], or
            None (position-only data).
        coverage: trust from the distance to the training inputs; None: the joint box
            of an :class:`InputBox`, or full trust for the physics inputs.
        more: further stages, in order.
    """

    def __init__(
        self,
        base: ExtendedModel,
        inputs: NetworkInputs,
        position: Head | None,
        orientation: Head | None,
        coverage: Coverage | None = None,
        more: Sequence[ResidualStage] = (),
    ) -> None:
        super().__init__()
        self.base = base
        first = ResidualStage(inputs, position, orientation, coverage)
        self.stages = nn.ModuleList([first, *more])
        dof = base.robot.dof
        for stage in self.stages:
            if isinstance(stage.inputs, InputBox) and stage.inputs.lower.numel() != dof:
                raise ValueError(f"input box has {stage.inputs.lower.numel()} joints, robot {dof}")
            if not isinstance(stage.inputs, InputBox) and stage.inputs.dof != dof:
                raise ValueError(f"network inputs made for {stage.inputs.dof} joints, robot {dof}")
        check_stages(list(self.stages))

    @classmethod
    def build(
        cls,
        base: ExtendedModel,
        inputs: NetworkInputs,
        *heads,
        coverage: Coverage | None = None,
        **options,
    ) -> HybridFK:
        """One stage of fresh networks on ``base``: ``heads`` and ``options`` are
        :meth:`ResidualStage.build`'s (``position_net``, ``orientation_net``: the named
        architectures, None: no such network; ``position_scale``, ``orientation_scale``,
        ``zero_init``)."""
        stage = ResidualStage.build(inputs, *heads, **options)
        return cls(base, inputs, stage.position, stage.orientation, coverage)

    # ------------------------------------------------------------------ the first stage
    @property
    def inputs(self) -> NetworkInputs:
        return self.stages[0].inputs

    @property
    def position(self) -> Head | None:
        return self.stages[0].position

    @property
    def orientation(self) -> Head | None:
        return self.stages[0].orientation

    @property
    def coverage(self) -> Coverage | None:
        return self.stages[0].coverage

    def set_coverage(self, coverage: Coverage | None, stage: int = 0) -> None:
        """Give stage ``stage`` a coverage (None: its default trust)."""
        self.stages[stage].coverage = coverage

    @property
    def box(self) -> InputBox | None:
        """The first stage's input box (the paper's inputs), or None."""
        return self.stages[0].box

    @property
    def input_label(self) -> str:
        """The stages' inputs: ``joints``, ``frame1+q2-4+torque/joints,local+q1``, ..."""
        out = ""
        for i, stage in enumerate(self.stages):
            out += ("" if i == 0 else "/" if stage.role == "refine" else ",") + stage.label
        return out

    # ------------------------------------------------------------------ prediction
    def networks(self) -> nn.ModuleDict:
        """The trainable heads by name: ``position``, ``orientation`` for the first
        stage, ``s1.position``, ... for the next."""
        out = {}
        for i, stage in enumerate(self.stages):
            for name, head in stage.heads().items():
                out[name if i == 0 else f"s{i}.{name}"] = head
        return nn.ModuleDict({k.replace(".", "_"): v for k, v in out.items()})

    def encode(self, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """The first stage's network inputs at ``q (*B, dof)`` and their output
        geometry (``{}``, ``{"A"}`` or ``{"R", "lever"}``; see the inputs' ``raw``)."""
        return self.stages[0].encode(self.base.robot, q)

    def encode_all(self, q: Tensor) -> list[tuple[Tensor, dict[str, Tensor]]]:
        """Every stage's inputs and geometry at ``q``."""
        return [stage.encode(self.base.robot, q) for stage in self.stages]

    def weights(self, q: Tensor, encoded: list[tuple[Tensor, dict]] | None = None) -> list:
        """Effective weight of every stage's networks at ``q`` (own trust combined by the
        stage rules): ``(*B,)``, or ``(*B, dof)`` for local networks."""
        encoded = self.encode_all(q) if encoded is None else encoded
        own = [stage.weight(q, u) for stage, (u, _) in zip(self.stages, encoded, strict=True)]
        return combine_stages(list(self.stages), own)

    def weight(self, q: Tensor, u: Tensor) -> Tensor:
        """The first stage's own trust at ``q`` with its inputs ``u``."""
        return self.stages[0].weight(q, u)

    def trust(self, q: Tensor) -> Tensor:
        """Weight in [0, 1] of the first stage's corrections at ``q`` (1: networks fully
        on, 0: the base model alone, or the next stage): ``(*B,)``, or ``(*B, dof)`` per
        joint for local networks."""
        return self.weight(q, self.encode(q)[0])

    def coverage_distance(self, q: Tensor) -> Tensor | None:
        """Distance of ``q``'s first-stage inputs to the training inputs (None without a
        :class:`Coverage`)."""
        return None if self.coverage is None else self.coverage.distance(self.encode(q)[0])

    def correction_axes(self, q: Tensor) -> Tensor:
        """``(*B, 3, 3)`` rotation of joint 1's frame in the root frame: the axes of
        :meth:`corrections` (nominal robot, commanded ``q``)."""
        return correction_axes(self.base, q)

    def corrections(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Flange corrections at ``q (*B, dof)``: every stage at its weight.

        Returns:
            ``dp (*B, 3)`` [m] and ``dw (*B, 3)`` [rad] in the axes of
            :meth:`correction_axes`, dtype of ``q``.
        """
        encoded = self.encode_all(q)
        return self.predict_all(encoded, self.weights(q, encoded))

    def predict_all(
        self, encoded: list[tuple[Tensor, dict]], weights: list[Tensor | None]
    ) -> tuple[Tensor, Tensor]:
        """Sum of the stages' corrections from encoded inputs and effective weights; a
        stage with a spread is shrunk where its refine stage is off."""
        dp = dw = None
        for i, (stage, (u, geo), w) in enumerate(zip(self.stages, encoded, weights, strict=True)):
            p, r = stage.predict(u, geo, w)
            if stage.spread is not None:
                p, r = stage.spread.apply(p, r, refine_trust(weights, i))
            dp, dw = (p, r) if dp is None else (dp + p, dw + r)
        return dp, dw

    def predict(
        self, u: Tensor, geo: dict[str, Tensor], w: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """The first stage's corrections from its encoded inputs (see
        :meth:`ResidualStage.predict`)."""
        return self.stages[0].predict(u, geo, w)

    def end_pose(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` corrected flange pose in the robot root frame."""
        q = self.base.robot.check_q(q)  # a list / array like Robot.fk
        E = self.base.end_pose(q, cond)
        q = q.to(E.dtype)
        dp, dw = self.corrections(q)
        R1 = self.correction_axes(q)
        dp, dw = (R1 @ dp[..., None])[..., 0], (R1 @ dw[..., None])[..., 0]
        return transform(so3_exp(dw) @ E[..., :3, :3], E[..., :3, 3] + dp)

    def forward(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` pose of the measured point/frame in the measurement frame."""
        E = self.end_pose(q, cond)
        base, tool = frame_matrices(self.base, cond)
        return base.to(E.dtype) @ E @ tool.to(E.dtype)

    # ------------------------------------------------------------------ model file
    def state(self, metadata: dict | None = None) -> dict:
        """The ``networks`` entry of a model file (tensors and plain data only; format:
        :func:`~hybrid_pk.hybrid.networks_state.networks_state`)."""
        return networks_state(self.base.robot.joint_names, list(self.stages), metadata)

    @classmethod
    def from_state(cls, base: ExtendedModel, state: dict, source: str = "model file") -> HybridFK:
        """Rebuild from :meth:`state` on ``base`` (the model file's extended model), in
        eval mode; reads networks format versions 1 to 4.

        Raises:
            ModelFileError: not a networks entry, a newer version, or networks made for
                other joints than ``base``'s robot.
        """
        first, *more = stages_from_state(base.robot, state, source)
        model = cls(base, first.inputs, first.position, first.orientation, first.coverage, more)
        model.stages[0].spread = first.spread
        model.stages[0].gate, model.stages[0].blocked = first.gate, first.blocked
        check_stages(list(model.stages))
        return model.eval()

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

import torch
from torch import Tensor, nn

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.hybrid.coverage import Coverage
from hybrid_pk.hybrid.features import PhysicsFeatures
from hybrid_pk.hybrid.inputs import DEFAULT_FADE, InputBox, joint_1_axes
from hybrid_pk.hybrid.local import LOCAL_FEATURES, LocalFeatures, LocalHead
from hybrid_pk.hybrid.nets import ResidualHead
from hybrid_pk.hybrid.networks_state import networks_state, parts_from_state

__all__ = [
    "DEFAULT_FADE",
    "Head",
    "HybridFK",
    "NetworkInputs",
    "correction_axes",
    "frame_matrices",
]

NetworkInputs = InputBox | PhysicsFeatures | LocalFeatures
Head = ResidualHead | LocalHead


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
    """Base model + position and orientation residual networks.

    Args:
        base: the nominal or calibrated model (frames + effects); not trained here.
        inputs: the networks' inputs and output axes (:class:`InputBox` or
            :class:`PhysicsFeatures`).
        position: head predicting the flange position correction ``dp`` [m], or None.
        orientation: head predicting the flange rotation correction ``dw`` [rad], or
            None (position-only data).
        coverage: trust from the distance to the training inputs; None: the joint box
            of an :class:`InputBox`, or full trust for :class:`PhysicsFeatures`.
    """

    def __init__(
        self,
        base: ExtendedModel,
        inputs: NetworkInputs,
        position: Head | None,
        orientation: Head | None,
        coverage: Coverage | None = None,
    ) -> None:
        super().__init__()
        dof = base.robot.dof
        if isinstance(inputs, InputBox) and inputs.lower.numel() != dof:
            raise ValueError(f"input box has {inputs.lower.numel()} joints, robot {dof}")
        if isinstance(inputs, PhysicsFeatures | LocalFeatures) and inputs.dof != dof:
            raise ValueError(f"network inputs made for {inputs.dof} joints, robot {dof}")
        self.base = base
        self.inputs = inputs
        self.position = position
        self.orientation = orientation
        self.coverage = coverage

    @classmethod
    def build(
        cls,
        base: ExtendedModel,
        inputs: NetworkInputs,
        position_net: str | None,
        orientation_net: str | None,
        position_scale: Tensor | None = None,
        orientation_scale: Tensor | None = None,
        zero_init: bool = False,
        coverage: Coverage | None = None,
    ) -> HybridFK:
        """Fresh networks of the named architectures (None: no such network).

        Args:
            position_scale, orientation_scale: ``(3,)`` output units [m], [rad]
                (default 1 mm and 1 mrad).
        """
        default = torch.full((3,), 1e-3, dtype=torch.float64)
        n_inputs = cls.n_inputs_of(inputs)

        def head(arch: str | None, scale: Tensor | None, twist: bool) -> Head | None:
            if arch is None:
                return None
            scale = default if scale is None else scale
            if isinstance(inputs, LocalFeatures):  # per-joint axes: one unit for all three
                size = scale.detach().to(torch.float64).mean()
                # a twist's rotation [rad] moves the flange ~1 m away by as many metres
                return LocalHead(arch, inputs.dof, size.repeat(6 if twist else 3), zero_init)
            return ResidualHead(arch, n_inputs, scale, zero_init)

        return cls(
            base,
            inputs,
            head(position_net, position_scale, True),
            head(orientation_net, orientation_scale, False),
            coverage,
        )

    @staticmethod
    def n_inputs_of(inputs: NetworkInputs) -> int:
        """Number of inputs of each network (per joint for local networks)."""
        if isinstance(inputs, InputBox):
            return inputs.lower.numel()
        if isinstance(inputs, LocalFeatures):
            return LOCAL_FEATURES
        return inputs.n_features

    @property
    def box(self) -> InputBox | None:
        """The paper's input box (normalisation and joint-box trust), or None."""
        return self.inputs if isinstance(self.inputs, InputBox) else None

    @property
    def input_label(self) -> str:
        """``joints`` (the paper's inputs) or the physics features' label."""
        return "joints" if self.box is not None else self.inputs.spec.label

    # ------------------------------------------------------------------ prediction
    def networks(self) -> nn.ModuleDict:
        """The trainable heads by name (``position``, ``orientation``)."""
        heads = {"position": self.position, "orientation": self.orientation}
        return nn.ModuleDict({k: v for k, v in heads.items() if v is not None})

    def encode(self, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Network inputs ``u`` at ``q (*B, dof)`` (``(*B, n_inputs)``, or ``(*B, dof, 8)``
        for local networks) and the geometry that turns their outputs into joint 1's
        axes (``{}``, ``{"A"}`` or ``{"R", "lever"}``; see the inputs' ``raw``)."""
        return self.inputs.encode(self.base.robot, q)

    def weight(self, q: Tensor, u: Tensor) -> Tensor:
        """Trust of the networks at ``q`` with inputs ``u`` (see :meth:`trust`)."""
        if self.coverage is not None:
            return self.coverage.trust(u)
        if self.box is not None:
            return self.box.trust(q)
        return torch.ones(u.shape[:-1], dtype=u.dtype, device=u.device)  # (*B[, dof])

    def trust(self, q: Tensor) -> Tensor:
        """Weight in [0, 1] of the corrections at ``q`` (1: networks fully on, 0: the
        base model alone): ``(*B,)``, or ``(*B, dof)`` per joint for local networks."""
        return self.weight(q, self.encode(q)[0])

    def coverage_distance(self, q: Tensor) -> Tensor | None:
        """``(*B,)`` distance of ``q``'s inputs to the training inputs (None without a
        :class:`Coverage`)."""
        return None if self.coverage is None else self.coverage.distance(self.encode(q)[0])

    def correction_axes(self, q: Tensor) -> Tensor:
        """``(*B, 3, 3)`` rotation of joint 1's frame in the root frame: the axes of
        :meth:`corrections` (nominal robot, commanded ``q``)."""
        return correction_axes(self.base, q)

    def corrections(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Flange corrections at ``q (*B, dof)``, already weighted by :meth:`trust`.

        Returns:
            ``dp (*B, 3)`` [m] and ``dw (*B, 3)`` [rad] in the axes of
            :meth:`correction_axes`, dtype of ``q``.
        """
        u, geo = self.encode(q)
        return self.predict(u, geo, self.weight(q, u))

    def predict(
        self, u: Tensor, geo: dict[str, Tensor], w: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Corrections from inputs already encoded (:meth:`encode`; training batches).

        Args:
            u: network inputs.
            geo: their geometry (:meth:`encode`).
            w: trust, ``(*B,)`` or ``(*B, dof)`` (local networks); None: unweighted.

        Returns:
            ``dp (*B, 3)`` [m] and ``dw (*B, 3)`` [rad] in joint 1's axes.
        """
        batch = u.shape[: -2 if isinstance(self.inputs, LocalFeatures) else -1]
        zero = torch.zeros(*batch, 3, dtype=u.dtype, device=u.device)
        dp = zero if self.position is None else self.position.correct(u, geo, w)
        dw = zero if self.orientation is None else self.orientation.correct(u, geo, w)
        return dp, dw

    def end_pose(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` corrected flange pose in the robot root frame."""
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
        return networks_state(
            self.base.robot.joint_names,
            self.inputs,
            {"position": self.position, "orientation": self.orientation},
            self.coverage,
            metadata,
        )

    @classmethod
    def from_state(cls, base: ExtendedModel, state: dict, source: str = "model file") -> HybridFK:
        """Rebuild from :meth:`state` on ``base`` (the model file's extended model), in
        eval mode; reads networks format versions 1 and 2.

        Raises:
            ModelFileError: not a networks entry, a newer version, or networks made for
                other joints than ``base``'s robot.
        """
        inputs, heads, coverage = parts_from_state(base.robot, state, source)
        return cls(base, inputs, heads["position"], heads["orientation"], coverage).eval()

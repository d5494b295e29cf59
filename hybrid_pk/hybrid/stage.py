"""`ResidualStage`: one set of residual networks (inputs, heads, coverage) of a hybrid
model, and how several stages combine.

A :class:`~hybrid_pk.hybrid.HybridFK` holds one or more stages, in order:

- a ``cascade`` stage is a level of fall-back: where it is trusted (weight ``w``) it
  corrects, and the stages after it get the rest ``1 - w``; after the last one the base
  model (the physics) alone remains. So the most detailed networks come first and the
  ones whose structure extrapolates (local deformation networks, one weight per joint:
  always the last cascade stage) after them;
- a ``refine`` stage adds detail to the cascade stage before it, trained on what that
  one leaves, and applies only where both are trusted.

Per row, with ``r`` the weight left for a cascade stage and ``g`` the gate of the
cascade stage being refined::

    cascade:  dp += predict(u, r w)      g = r w      r = r (1 - w)
    refine:   dp += predict(u, g w)
    local:    dp += predict(u, r w_j)    r = 0        (per joint j)

A cascade stage refined by the next one may carry a
:class:`~hybrid_pk.hybrid.spread.TargetSpread`: where the refine stage is not trusted,
its correction is shrunk by how much of it the training rows confirm
(:mod:`~hybrid_pk.hybrid.spread`).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hybrid_pk.hybrid.blocked_trust import JointGate
from hybrid_pk.hybrid.coverage import Coverage
from hybrid_pk.hybrid.features import PhysicsFeatures
from hybrid_pk.hybrid.inputs import InputBox
from hybrid_pk.hybrid.local import LOCAL_FEATURES, LocalFeatures, LocalHead
from hybrid_pk.hybrid.nets import ResidualHead
from hybrid_pk.hybrid.spread import TargetSpread
from hybrid_pk.robot import Robot

__all__ = [
    "ROLES",
    "Head",
    "NetworkInputs",
    "ResidualStage",
    "check_stages",
    "combine_stages",
    "refine_trust",
]

ROLES = ("cascade", "refine")
NetworkInputs = InputBox | PhysicsFeatures | LocalFeatures
Head = ResidualHead | LocalHead


class ResidualStage(nn.Module):
    """Inputs, position / orientation heads and coverage of one set of networks.

    Args:
        inputs: the networks' inputs and output geometry.
        position: head predicting the flange position correction ``dp`` [m], or None.
        orientation: head predicting the flange rotation correction ``dw`` [rad], or None.
        coverage: trust from the distance to the training inputs; None: the joint box
            of an :class:`InputBox`, or full trust otherwise.
        role: ``cascade`` or ``refine`` (see the module docstring).
        spread: shrinks this cascade stage's correction where the refine stage after it
            is not trusted; None: never shrunk.
        gate: trust in joint space (the stage off away from its training joints:
            :mod:`~hybrid_pk.hybrid.blocked_trust`); None: its own trust alone.
        blocked: record of the blocked hold-out test that set or lifted the gate
            (plain data), or None.
    """

    def __init__(
        self,
        inputs: NetworkInputs,
        position: Head | None,
        orientation: Head | None,
        coverage: Coverage | None = None,
        role: str = "cascade",
        spread: TargetSpread | None = None,
        gate: JointGate | None = None,
        blocked: dict | None = None,
    ) -> None:
        super().__init__()
        if role not in ROLES:
            raise ValueError(f"stage role must be one of {', '.join(ROLES)}, got {role!r}")
        self.inputs = inputs
        self.position = position
        self.orientation = orientation
        self.coverage = coverage
        self.role = role
        self.spread = spread
        self.gate = gate
        self.blocked = blocked

    @classmethod
    def build(
        cls,
        inputs: NetworkInputs,
        position_net: str | None,
        orientation_net: str | None,
        position_scale: Tensor | None = None,
        orientation_scale: Tensor | None = None,
        zero_init: bool = False,
        role: str = "cascade",
    ) -> ResidualStage:
        """Fresh networks of the named architectures (None: no such network).

        Args:
            position_scale, orientation_scale: ``(3,)`` output units [m], [rad]
                (default 1 mm and 1 mrad).
        """
        # 1 mm, 1 mrad: the order of a calibrated arm's residual, so outputs start O(1)
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
            inputs,
            head(position_net, position_scale, True),
            head(orientation_net, orientation_scale, False),
            None,
            role,
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
    def grouped(self) -> bool:
        """One network and one weight per joint (local networks)."""
        return isinstance(self.inputs, LocalFeatures)

    @property
    def label(self) -> str:
        """``joints`` (the paper's inputs) or the physics inputs' label."""
        return "joints" if self.box is not None else self.inputs.spec.label

    def heads(self) -> dict[str, Head]:
        """The trainable heads by quantity (``position``, ``orientation``)."""
        heads = {"position": self.position, "orientation": self.orientation}
        return {k: v for k, v in heads.items() if v is not None}

    def encode(self, robot: Robot, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Network inputs at ``q (*B, dof)`` and their output geometry."""
        return self.inputs.encode(robot, q)

    def weight(self, q: Tensor, u: Tensor, gated: bool = True) -> Tensor:
        """Trust at ``q`` with inputs ``u``: ``(*B,)``, or ``(*B, dof)`` when grouped;
        ``gated=False`` leaves out the :attr:`gate` (the blocked hold-out's probes)."""
        if self.box is not None:  # the paper's inputs: never beyond the joint box
            box = self.box.trust(q)
            return box if self.coverage is None else box * self.coverage.trust(u)
        batch = u.shape[:-1]
        w = torch.ones(batch, dtype=u.dtype, device=u.device)
        if self.coverage is not None:
            w = self.coverage.trust(u)
        if self.gate is not None and gated:
            g = self.gate.trust(q).to(w.dtype)
            w = w * (g[..., None] if self.grouped else g)
        return w

    def predict(
        self, u: Tensor, geo: dict[str, Tensor], w: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``dp (*B, 3)`` [m] and ``dw (*B, 3)`` [rad] in joint 1's axes from encoded
        inputs, weighted by ``w`` (``(*B,)`` or ``(*B, dof)``; None: unweighted)."""
        batch = u.shape[: -2 if self.grouped else -1]
        zero = torch.zeros(*batch, 3, dtype=u.dtype, device=u.device)
        dp = zero if self.position is None else self.position.correct(u, geo, w)
        dw = zero if self.orientation is None else self.orientation.correct(u, geo, w)
        return dp, dw

    def extra_repr(self) -> str:
        return f"{self.label}, role={self.role}"


def check_stages(stages: list[ResidualStage]) -> None:
    """Raise ValueError unless the roles combine: a refine stage follows a cascade stage
    with one weight per row, and local networks (a weight per joint) come last."""
    for i, stage in enumerate(stages):
        if stage.role == "refine" and (i == 0 or stages[i - 1].grouped):
            raise ValueError("a refine stage must follow a stage with one weight per row")
        if stage.grouped and stage.role == "cascade" and i != len(stages) - 1:
            raise ValueError("local networks (one weight per joint) must be the last stage")
        refined = i + 1 < len(stages) and stages[i + 1].role == "refine"
        if stage.spread is not None and not refined:
            raise ValueError("a spread shrinks a stage where its refine stage is off: none follows")


def combine_stages(stages: list[ResidualStage], weights: list[Tensor]) -> list[Tensor]:
    """Effective weight of every stage's networks from their own trusts ``weights``
    (``(*B,)``, or ``(*B, dof)`` for grouped stages), by the rules of the module
    docstring."""
    rest: Tensor | None = None
    gate: Tensor | None = None
    out = []
    for stage, w in zip(stages, weights, strict=True):
        if stage.role == "refine":
            out.append(gate * w)
            continue
        r = torch.ones_like(w if not stage.grouped else w[..., 0]) if rest is None else rest
        if stage.grouped:
            out.append(r[..., None] * w)
            rest, gate = torch.zeros_like(r), None
        else:
            out.append(r * w)
            rest, gate = r * (1 - w), r * w
    return out


def refine_trust(weights: list[Tensor], i: int) -> Tensor:
    """Own trust of the refine stage ``i + 1`` from the effective ``weights``: its weight
    is the gate of stage ``i`` (that stage's weight) times its own trust."""
    gate, refined = weights[i], weights[i + 1]
    on = gate > 0
    return torch.where(on, refined / torch.where(on, gate, torch.ones_like(gate)), 0 * gate)

"""`InputBox`: the paper's network inputs (all joints, min-max normalised) and their
joint-box trust region.

The networks read every joint normalised to [-1, 1] over the input range (the full
joint limits, paper 4.1, or the range of the training data, paper 4.2) and predict in
the axes of joint 1's frame. Their weight ``w(q)`` in [0, 1] is 1 inside the joint box
of the training data, 0 outside it by default (the base model, as the paper restricts
its networks to the training range), or falling smoothly (C¹) to 0 within ``fade`` x
the box size outside it. On the real UR10 a 10 % fade made the orientation worse on
held-out rows just outside the box while helping on average further out, so the safe
fall-back is the default and the fade is opt-in.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hybrid_pk.hybrid.features import FeatureSpec, cpu_copies
from hybrid_pk.hybrid.local import LocalSpec
from hybrid_pk.robot import Robot

__all__ = ["DEFAULT_FADE", "InputBox", "finite_limits", "joint_1_axes", "parse_inputs"]

DEFAULT_FADE = 0.0  # fade-out width outside the training box, fraction of its size


def joint_1_axes(robot: Robot, q: Tensor) -> Tensor:
    """``(*B, 3, 3)`` rotation of joint 1's frame in the root frame at ``q (*B, dof)``:
    the axes of the network corrections."""
    return robot.link_frames(q)[..., 0, :3, :3]


def finite_limits(lower: Tensor, upper: Tensor) -> tuple[Tensor, Tensor]:
    """Limits with ``±inf`` (continuous joints) replaced by ``±pi``."""
    pi = torch.full_like(lower, torch.pi)
    return torch.where(torch.isfinite(lower), lower, -pi), torch.where(
        torch.isfinite(upper), upper, pi
    )


class InputBox(nn.Module):
    """Input normalisation and trust region of the networks.

    Buffers (each ``(dof,)``, joint units [rad or m]):
        lower, upper: range mapped to [-1, 1] (joint limits or the data's range).
        trust_lower, trust_upper: joint box of the training data.

    Args:
        lower, upper: normalisation range.
        trust_lower, trust_upper: training-data box (default: the normalisation range).
        fade: width of the fade-out outside the box, as a fraction of its size per joint.
    """

    def __init__(
        self,
        lower: Tensor,
        upper: Tensor,
        trust_lower: Tensor | None = None,
        trust_upper: Tensor | None = None,
        fade: float = DEFAULT_FADE,
    ) -> None:
        super().__init__()
        lower, upper = finite_limits(lower.to(torch.float64), upper.to(torch.float64))
        if not bool((upper > lower).all()):
            raise ValueError(f"input range needs upper > lower per joint, got {lower}, {upper}")
        tl = lower if trust_lower is None else trust_lower.to(torch.float64)
        tu = upper if trust_upper is None else trust_upper.to(torch.float64)
        self.register_buffer("lower", lower.clone())
        self.register_buffer("upper", upper.clone())
        self.register_buffer("trust_lower", tl.clone())
        self.register_buffer("trust_upper", tu.clone())
        self.fade = float(fade)

    @classmethod
    def from_data(cls, q: Tensor, limits: tuple[Tensor, Tensor] | None, fade: float) -> InputBox:
        """Box of the training joints ``q (N, dof)``; normalised over ``limits`` if given
        (paper 4.1), else over the data's own range (paper 4.2)."""
        lo, hi = q.min(0).values, q.max(0).values
        hi = torch.where(hi > lo, hi, lo + 1e-6)  # a joint that never moved
        if limits is None:
            return cls(lo, hi, fade=fade)
        return cls(*limits, trust_lower=lo, trust_upper=hi, fade=fade)

    def normalise(self, q: Tensor) -> Tensor:
        """``(*B, dof)`` joints -> ``(*B, dof)`` in [-1, 1] over the range (beyond it outside)."""
        lo, hi = self.lower.to(q.dtype), self.upper.to(q.dtype)
        return 2 * (q - lo) / (hi - lo) - 1

    def trust(self, q: Tensor) -> Tensor:
        """``(*B,)`` weight of the network corrections: 1 inside the training box, 0 beyond
        ``fade`` x its size, ``(1 - r²)²`` in between (``r``: distance outside the box in
        units of the fade width), which is C¹ at both ends."""
        lo, hi = self.trust_lower.to(q.dtype), self.trust_upper.to(q.dtype)
        width = (self.fade * (hi - lo)).clamp_min(1e-9)
        outside = (torch.relu(lo - q) + torch.relu(q - hi)) / width
        r2 = (outside * outside).sum(-1)
        return (1 - r2).clamp_min(0) ** 2

    def encode(self, robot: Robot, q: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Network inputs ``(*B, dof)`` at ``q``; the corrections are in joint 1's axes
        (no geometry: ``{}``)."""
        return self.normalise(q), {}

    def state(self) -> dict:
        """Plain data for a model file (the ``input`` entry of format 1)."""
        return {
            **cpu_copies(self, "lower", "upper", "trust_lower", "trust_upper"),
            "fade": self.fade,
        }

    @classmethod
    def from_state(cls, state: dict) -> InputBox:
        """Inverse of :meth:`state`."""
        return cls(
            state["lower"],
            state["upper"],
            state["trust_lower"],
            state["trust_upper"],
            state["fade"],
        )

    def extra_repr(self) -> str:
        return f"dof={self.lower.numel()}, fade={self.fade}"


def parse_inputs(text: str) -> FeatureSpec | LocalSpec:
    """The spec of ``--inputs`` other than ``joints``: ``local[+q1]`` or
    ``frameK[+qI-J][+gravity][+torque|+full]``.

    Raises:
        HybridPKError: the message lists the forms.
    """
    if text.strip().startswith("local"):
        return LocalSpec.parse(text)
    return FeatureSpec.parse(text)

"""How far a stage's correction can be trusted where the networks refining it are not.

A posture stage (:class:`~hybrid_pk.hybrid.features.PhysicsFeatures` in the frame of
link 1) predicts the same correction, turned with joint 1, at every angle of joint 1.
What the error does with joint 1 itself (the base bearing's cyclic error, a tilt that
depends on where the arm points) it learns as the average over the angles its training
rows were measured at. The refine stage after it reads every joint and adds that part
back, but only inside the training rows' joint box. Outside it, the posture correction
``c`` is an estimate with an error of the size of what it cannot see, and adding all of
it can make a well-calibrated row worse.

:class:`TargetSpread` measures that error on the training rows: the spread
``s² = E[(t_i - t_j)²]`` of the stage's training targets ``t`` (the base model's
residual, per axis of the corrections) between each row and its ``k`` nearest rows in
the stage's own input space, rows the networks cannot tell apart. Where the refine stage
is not trusted (its trust ``ρ``), each axis of the correction is shrunk like a Wiener
filter::

    c' = c (ρ + (1 - ρ) c² / (c² + s²))

A correction well above the spread stays; one of the size of the spread is halved; a
small one, of a size the training rows cannot confirm, fades to the physics. Inside the
box (``ρ = 1``) nothing changes. The spread includes the measurement noise, so this errs
on the side of the physics. ``c'`` is smooth in ``c`` (IK gradients).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hybrid_pk.hybrid.coverage import nearest
from hybrid_pk.hybrid.features import cpu_copies
from hybrid_pk.hybrid.tuning import hybrid_tuning

__all__ = ["TargetSpread", "shrink"]

_TINY = 1e-30  # keeps c² / (c² + s²) finite at c = s = 0


def shrink(c: Tensor, spread: Tensor, rho: Tensor) -> Tensor:
    """``c (*B, 3)`` shrunk per axis by ``spread (3,)`` where ``rho (*B,)`` is below 1."""
    c2 = c * c
    keep = c2 / (c2 + spread.to(c.dtype) + _TINY)
    rho = rho[..., None].to(c.dtype)
    return c * (rho + (1 - rho) * keep)


class TargetSpread(nn.Module):
    """Spread of a stage's training targets among rows of nearly equal inputs.

    Buffers:
        position: ``(3,)`` [m²] per axis of the position correction.
        orientation: ``(3,)`` [rad²] per axis of the rotation correction.
    """

    def __init__(self, position: Tensor, orientation: Tensor) -> None:
        super().__init__()
        pos = torch.as_tensor(position, dtype=torch.float64).detach().clone()
        ori = torch.as_tensor(orientation, dtype=torch.float64).detach().clone()
        if pos.shape != (3,) or ori.shape != (3,) or bool((pos < 0).any() | (ori < 0).any()):
            raise ValueError(
                f"spreads must be (3,) and >= 0, got {tuple(pos.shape)}, {tuple(ori.shape)}"
            )
        self.register_buffer("position", pos)
        self.register_buffer("orientation", ori)

    @classmethod
    def from_targets(
        cls,
        u: Tensor,
        position: Tensor,
        rotation: Tensor | None,
        *,
        neighbours: int | None = None,
        max_reference: int | None = None,
        seed: int = 0,
    ) -> TargetSpread:
        """Spread of the targets over each row's ``neighbours`` nearest rows in inputs.

        Args:
            u: ``(N, F)`` standardised inputs of the training rows.
            position: ``(N, 3)`` position targets [m] (the base model's residual).
            rotation: ``(N, 3)`` rotation targets [rad] (rotation vectors), or None.
            neighbours: ``k`` (None: the tuning's ``coverage_neighbours``).
            max_reference: rows used (a seeded random sample of the training rows; None:
                the tuning's ``coverage_reference``).
            seed: seed of the sample.
        """
        tuning = hybrid_tuning()
        neighbours = tuning.coverage_neighbours if neighbours is None else neighbours
        max_reference = tuning.coverage_reference if max_reference is None else max_reference
        gen = torch.Generator().manual_seed(seed)
        rows = torch.randperm(u.shape[0], generator=gen)[:max_reference]
        x = u.detach().to(torch.float64)[rows]
        if x.shape[0] < 2:
            zero = torch.zeros(3, dtype=torch.float64)
            return cls(zero, zero)
        k = min(neighbours, x.shape[0] - 1)
        _, idx = nearest(x, x, k + 1)
        # each row's own index last (a repeated row may come before it), then drop it
        rank = torch.arange(k + 1).expand_as(idx) + (k + 1) * (idx == torch.arange(len(x))[:, None])
        idx = idx.gather(1, rank.argsort(dim=1)[:, :k])
        mine, theirs = rows[:, None].expand_as(idx), rows[idx]

        def spread(t: Tensor | None) -> Tensor:
            if t is None:
                return torch.zeros(3, dtype=torch.float64)
            t = t.detach().to(torch.float64)
            return (t[mine] - t[theirs]).pow(2).reshape(-1, 3).mean(0)

        return cls(spread(position), spread(rotation))

    def apply(self, dp: Tensor, dw: Tensor, rho: Tensor) -> tuple[Tensor, Tensor]:
        """The corrections ``dp``, ``dw (*B, 3)`` shrunk where ``rho (*B,)`` < 1."""
        return shrink(dp, self.position, rho), shrink(dw, self.orientation, rho)

    def state(self) -> dict:
        """Plain data for a model file."""
        return cpu_copies(self, "position", "orientation")

    @classmethod
    def from_state(cls, state: dict) -> TargetSpread:
        """Inverse of :meth:`state`."""
        return cls(state["position"], state["orientation"])

    def extra_repr(self) -> str:
        mm = [round(float(v) ** 0.5 * 1e3, 4) for v in self.position]
        mrad = [round(float(v) ** 0.5 * 1e3, 4) for v in self.orientation]
        return f"rms position {mm} mm, rotation {mrad} mrad"

"""Where the residual networks apply: coverage of the training data in their input space.

A joint box is a poor notion of "inside": a row can lie inside the per-joint range of
the training rows and far from all of them (a Cartesian block of the workspace), or
outside it in a joint the networks do not read. :class:`Coverage` measures instead the
distance of a row's network inputs to the training rows' inputs (the mean distance to
its ``k`` nearest neighbours among a stored reference sample, in the standardised input
space) and turns it into the networks' weight:

- ``w = 1`` up to ``radius_in``: the distance within which held-out rows of the
  training region lie (the ``quantile`` of their distances, validation rows by default);
- ``w = 0`` from ``radius_out = ratio x radius_in`` on: the base model (physics) alone;
- a C¹ smoothstep ``1 - 3t² + 2t³`` in between (``t`` from 0 to 1), so the blend of
  networks and physics has continuous Jacobians for the IK.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hybrid_pk.hybrid.features import cpu_copies
from hybrid_pk.hybrid.tuning import hybrid_tuning

__all__ = [
    "DEFAULT_QUANTILE",
    "DEFAULT_RATIO",
    "Coverage",
    "nearest",
    "smoothstep",
]

# Defaults of a direct call (the hybrid passes its HybridSettings' coverage): 99 % of
# held-out rows of the training region trusted fully, the base model beyond twice that.
DEFAULT_QUANTILE = 0.99
DEFAULT_RATIO = 2.0
# query rows per distance matrix: 2048 x 50,000 float64 reference distances is 0.8 GB
_CHUNK = 2048
_EPS = 1e-12  # inside the square root: finite gradients at zero distance


def smoothstep(t: Tensor) -> Tensor:
    """``1`` for ``t <= 0``, ``0`` for ``t >= 1``, ``1 - 3t² + 2t³`` between (C¹)."""
    t = t.clamp(0.0, 1.0)
    return 1 - t * t * (3 - 2 * t)


def nearest(u: Tensor, reference: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Squared distances ``(n, k)`` (ascending) and indices ``(n, k)`` of the ``k``
    nearest rows of ``reference (M, F)`` to each row of ``u (n, F)``, in chunks."""
    ref = reference.to(u.dtype)
    k = min(k, ref.shape[0])
    values, indices = [], []
    for start in range(0, u.shape[0], _CHUNK):
        x = u[start : start + _CHUNK]
        d2 = (x * x).sum(-1, keepdim=True) - 2 * x @ ref.T + (ref * ref).sum(-1)
        near = d2.clamp_min(0).topk(k, dim=-1, largest=False)
        values.append(near.values)
        indices.append(near.indices)
    if not values:
        return u.new_zeros(0, k), torch.zeros(0, k, dtype=torch.long, device=u.device)
    return torch.cat(values), torch.cat(indices)


def _knn_distance(u: Tensor, reference: Tensor, neighbours: int, leave_one_out: bool) -> Tensor:
    """``(*B,)`` mean distance of ``u (*B, F)`` to its nearest rows of ``reference (M, F)``."""
    batch = u.shape[:-1]
    d2, _ = nearest(u.reshape(-1, u.shape[-1]), reference, neighbours + int(leave_one_out))
    if leave_one_out:
        d2 = d2[:, 1:]
    return (d2 + _EPS).sqrt().mean(-1).reshape(batch)


class Coverage(nn.Module):
    """Trust of the networks from the distance to the training data in input space.

    With grouped inputs (one network per joint: inputs ``(*B, G, F)``) every group has
    its own reference and radii, and the trust is ``(*B, G)``.

    Buffers:
        reference: ``(M, F)`` standardised inputs of (a sample of) the training rows, or
            ``(G, M, F)`` per group.
        radius_in, radius_out: ``()`` or ``(G,)`` distances where the trust starts /
            ends falling.

    Args:
        reference: ``(M, F)`` or ``(G, M, F)`` reference inputs.
        radius_in, radius_out: as above, ``radius_out > radius_in > 0``.
        neighbours: ``k`` of the mean k-nearest-neighbour distance.
    """

    def __init__(
        self,
        reference: Tensor,
        radius_in: float | Tensor,
        radius_out: float | Tensor,
        neighbours: int | None = None,
    ) -> None:
        super().__init__()
        if reference.ndim not in (2, 3) or reference.shape[-2] < 1:
            raise ValueError(
                f"reference must be (M, F) or (G, M, F) with M >= 1, got {tuple(reference.shape)}"
            )
        r_in = torch.as_tensor(radius_in, dtype=torch.float64).clone()
        r_out = torch.as_tensor(radius_out, dtype=torch.float64).clone()
        if not bool((0 < r_in).all() and (r_in < r_out).all()):
            raise ValueError(f"need 0 < radius_in < radius_out, got {radius_in}, {radius_out}")
        self.register_buffer("reference", reference.detach().to(torch.float64).clone())
        self.register_buffer("radius_in", r_in)
        self.register_buffer("radius_out", r_out)
        k = hybrid_tuning().coverage_neighbours if neighbours is None else neighbours
        self.neighbours = min(int(k), reference.shape[-2])

    @classmethod
    def from_inputs(
        cls,
        train: Tensor,
        calibration: Tensor | None = None,
        *,
        neighbours: int | None = None,
        quantile: float = DEFAULT_QUANTILE,
        ratio: float = DEFAULT_RATIO,
        max_reference: int | None = None,
        seed: int = 0,
    ) -> Coverage:
        """Coverage of the training inputs ``train (N, F)``.

        Args:
            train: standardised inputs of the training rows, ``(N, F)`` or grouped
                ``(N, G, F)``.
            calibration: inputs of held-out rows of the same region (validation rows)
                whose distances set ``radius_in``; None: the training rows left out of
                the reference sample, or (all in it) each row's distance to the others.
            neighbours: ``k`` (None: the tuning's ``coverage_neighbours``).
            quantile: share of the calibration rows within ``radius_in``.
            ratio: ``radius_out / radius_in``.
            max_reference: at most this many reference rows (None: the tuning's
                ``coverage_reference``).
            seed: seed of the reference sample.
        """
        if not 0 < quantile <= 1 or ratio <= 1:
            raise ValueError(f"need 0 < quantile <= 1 and ratio > 1, got {quantile}, {ratio}")
        train = train.detach().to(torch.float64)
        if max_reference is None:
            max_reference = hybrid_tuning().coverage_reference
        gen = torch.Generator().manual_seed(seed)
        perm = torch.randperm(train.shape[0], generator=gen)
        ref, rest = train[perm[:max_reference]], train[perm[max_reference:]]
        grouped = train.ndim == 3
        if grouped:  # (N, G, F) -> (G, M, F)
            ref = ref.transpose(0, 1)
        probe = cls(ref, 1.0, 2.0, neighbours)
        if calibration is not None and calibration.shape[0] > 0:
            d = probe.distance(calibration.detach().to(torch.float64))
        elif rest.shape[0] > 0:
            d = probe.distance(rest)
        else:
            d = probe.distance(train[perm[:max_reference]], leave_one_out=True)
        radius = torch.quantile(d, quantile, dim=0).clamp_min(1e-9)
        return cls(ref, radius, ratio * radius, neighbours)

    def distance(self, u: Tensor, leave_one_out: bool = False) -> Tensor:
        """Mean distance of inputs ``u`` to their ``k`` nearest reference rows
        (differentiable in ``u``): ``(*B, F) -> (*B,)``, grouped ``(*B, G, F) -> (*B, G)``.

        Args:
            leave_one_out: ``u`` is the reference itself: skip each row's own distance.
        """
        if self.reference.ndim == 3:
            return torch.stack(
                [
                    _knn_distance(u[..., g, :], ref, self.neighbours, leave_one_out)
                    for g, ref in enumerate(self.reference)
                ],
                -1,
            )
        return _knn_distance(u, self.reference, self.neighbours, leave_one_out)

    def trust(self, u: Tensor) -> Tensor:
        """Weight in [0, 1] of the networks at inputs ``u``: ``(*B,)`` or ``(*B, G)``."""
        lo, hi = self.radius_in.to(u.dtype), self.radius_out.to(u.dtype)
        return smoothstep((self.distance(u) - lo) / (hi - lo))

    def state(self) -> dict:
        """Plain data for a model file."""
        return {
            **cpu_copies(self, "reference", "radius_in", "radius_out"),
            "neighbours": self.neighbours,
        }

    @classmethod
    def from_state(cls, state: dict) -> Coverage:
        """Inverse of :meth:`state`."""
        return cls(state["reference"], state["radius_in"], state["radius_out"], state["neighbours"])

    def extra_repr(self) -> str:
        r_in = [round(float(r), 3) for r in self.radius_in.reshape(-1)]
        return f"reference={tuple(self.reference.shape)}, k={self.neighbours}, radius_in={r_in}"

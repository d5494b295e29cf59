"""The fit's least-squares problem with row weights and prior rows.

``residual(theta) = [sqrt(w) * r_data(theta); A theta - b]``: the data residuals of a
:class:`~hybrid_pk.calibration.fit.Problem`, each measured row scaled by the square root
of its robust weight (:mod:`hybrid_pk.calibration.robust`), followed by the prior rows of
the frames (:mod:`hybrid_pk.calibration.frames`). Without weights and priors it is the
problem itself.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from hybrid_pk.calibration.frames import PriorRows
from hybrid_pk.calibration.robust import row_weights_vector

if TYPE_CHECKING:
    from hybrid_pk.calibration.fit import Problem

__all__ = ["Penalised"]


class Penalised:
    """``problem`` with row weights ``(N,)`` (or None) and prior rows (or None)."""

    def __init__(self, problem: Problem, prior: PriorRows | None, weights: Tensor | None) -> None:
        self.problem, self.prior = problem, prior
        n_rows = problem.data.n
        n_parts = 1 if problem.R_meas is None else 2
        self.m = 3 * n_rows * n_parts
        self.sw = None
        if weights is not None:
            self.sw = row_weights_vector(weights.to(problem.x0.dtype), n_parts).sqrt()

    def residual(self, theta: Tensor) -> Tensor:
        r = self.problem.residual(theta)
        if self.sw is not None:
            r = self.sw * r
        if self.prior is None:
            return r
        return torch.cat([r, self.prior.residual(theta)])

    def jacobian(self, theta: Tensor) -> tuple[Tensor, Tensor]:
        return self.augment(*self.problem.jacobian(theta), theta)

    def augment(self, r: Tensor, J: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
        """Weighted residual and Jacobian with the prior rows, from the data's ``r, J``."""
        if self.sw is not None:
            r, J = self.sw * r, self.sw[:, None] * J
        if self.prior is None:
            return r, J
        return torch.cat([r, self.prior.residual(theta)]), torch.cat([J, self.prior.A])

    def data_residual(self, r: Tensor) -> Tensor:
        """The unweighted data part ``(m,)`` of a residual of :meth:`residual`."""
        r = r[: self.m]
        return r if self.sw is None else r / self.sw.clamp_min(1e-150)

"""The diagnosis's split of a campaign into fit rows and hold-out rows."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions

__all__ = ["Split", "split_campaign"]


@dataclass(frozen=True)
class Split:
    """Fit and hold-out rows of a campaign with their operating conditions.

    Attributes:
        fit_rows, holdout_rows: ``(n_fit,)``, ``(n_hold,)`` sorted row indices.
        train, test: the rows themselves.
        cond_fit, cond_hold: their conditions (payload, temperature, frame group, ...).
    """

    fit_rows: Tensor
    holdout_rows: Tensor
    train: MeasuredData
    test: MeasuredData
    cond_fit: Conditions
    cond_hold: Conditions

    @property
    def position_only(self) -> bool:
        return self.train.quat is None


def split_campaign(data: MeasuredData, cond: Conditions, holdout: float, seed: int) -> Split:
    """Random split keeping ``holdout`` (a fraction in (0, 1)) of the rows out of fits."""
    if not 0 < holdout < 1:
        raise ValueError(f"holdout (--holdout) must lie in (0, 1), got {holdout}")
    perm = torch.randperm(data.n, generator=torch.Generator().manual_seed(seed))
    n_hold = max(1, round(holdout * data.n))
    fit_rows, hold_rows = perm[n_hold:].sort().values, perm[:n_hold].sort().values
    return Split(
        fit_rows=fit_rows,
        holdout_rows=hold_rows,
        train=data.subset(fit_rows),
        test=data.subset(hold_rows),
        cond_fit=cond.subset(fit_rows),
        cond_hold=cond.subset(hold_rows),
    )

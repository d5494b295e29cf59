"""`IKResult`: every distinct solution of every target, padded into tensors."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pandas as pd
import torch
from torch import Tensor

__all__ = ["IKResult"]


@dataclass(frozen=True, eq=False)
class IKResult:
    """Solutions of a batch of IK targets.

    ``*B`` is the batch shape of the targets, ``K`` the largest number of solutions of
    any target. A target's solutions come first in its ``K`` slots (``valid`` true),
    ordered by joint values (lexicographically); the remaining slots are padding and
    hold NaN.

    Attributes:
        q: ``(*B, K, dof)`` joint values [rad, m for prismatic joints], each within
            the joint limits.
        position_error_mm: ``(*B, K)`` distance of the reached and the target point [mm].
        orientation_error_deg: ``(*B, K)`` rotation angle between reached and target
            orientation [deg]; NaN for position-only targets.
        valid: ``(*B, K)`` bool, which slots hold a solution.
        joint_names: names of ``q``'s columns.
        tol_mm: position tolerance [mm] every solution of :func:`solve_ik` meets.
        tol_deg: orientation tolerance [deg].
        position_only: True when the targets had no orientation.
        info: diagnostics (seeds, iterations, evaluations, stages, ...).
        closest_mm: ``(*B,)`` [mm] position error of the start that came closest to
            each target (least Levenberg-Marquardt cost, limits respected): for a
            failed target, by how much the solver missed it (e.g. a target a few
            micrometres beyond the reach of a stretched arm); NaN where not measured.
        closest_deg: ``(*B,)`` [deg] orientation error of that start (NaN for
            position-only targets).
        near_singular: ``(*B,)`` bool, targets with a solution at or near a singular
            configuration (stretched or folded elbow, aligned wrist axes): where
            ``smallest_singular_value`` times the distinctness tolerance (1e-3 rad) is
            below ``tol_mm``. A pose change within the tolerance moves the joints there
            by more than 1e-3 rad: solutions are polished onto their exact branch, but
            some may be samples of a singular family instead (several within
            tolerance, none at a branch), and the branches move by more than the
            tolerance with the target (a measured pose's noise). False for failures.
        smallest_singular_value: ``(*B,)`` [m/rad] the least, over the target's
            solutions, of the smallest singular value of the model's Jacobian (angular
            rows weighted by ``IKOptions.rotation_weight``; velocity rows only for
            position-only targets); NaN for failures.
    """

    q: Tensor
    position_error_mm: Tensor
    orientation_error_deg: Tensor
    valid: Tensor
    joint_names: tuple[str, ...]
    tol_mm: float
    tol_deg: float
    position_only: bool = False
    info: dict = field(default_factory=dict)
    closest_mm: Tensor | None = None
    closest_deg: Tensor | None = None
    near_singular: Tensor | None = None
    smallest_singular_value: Tensor | None = None

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.valid.shape[:-1])

    @property
    def counts(self) -> Tensor:
        """``(*B,)`` number of distinct solutions of each target."""
        return self.valid.sum(-1)

    @property
    def failed(self) -> Tensor:
        """``(*B,)`` bool, targets without any solution within tolerance."""
        return self.counts == 0

    @property
    def n_failed(self) -> int:
        return int(self.failed.sum())

    @property
    def within_tolerance(self) -> Tensor:
        """``(*B, K)`` bool: valid slots whose errors meet ``tol_mm`` and ``tol_deg``."""
        ok = self.valid & (self.position_error_mm <= self.tol_mm)
        if not self.position_only:
            ok &= self.orientation_error_deg <= self.tol_deg
        return ok

    def solutions(self, index: int | tuple[int, ...]) -> Tensor:
        """``(count, dof)`` the solutions of one target (its index in ``*B``)."""
        return self.q[index][self.valid[index]]

    def to_frame(self) -> pd.DataFrame:
        """Contract section 6 table: ``target`` (flat 0-based target index),
        ``solution``, one column per joint, ``position_error_mm``,
        ``orientation_error_deg`` (empty for position-only targets)."""
        dof = len(self.joint_names)
        k = self.valid.shape[-1]
        valid = self.valid.reshape(math.prod(self.batch_shape), k)
        target, slot = torch.nonzero(valid, as_tuple=True)
        q = self.q.reshape(valid.shape[0], k, dof)[target, slot].detach().cpu().numpy()
        pos = self.position_error_mm.reshape(valid.shape)[target, slot]
        ori = self.orientation_error_deg.reshape(valid.shape)[target, slot]
        cols: dict[str, object] = {
            "target": target.cpu().numpy(),
            "solution": slot.cpu().numpy(),
        }
        for j in range(dof):
            cols[self.joint_names[j]] = q[:, j]
        cols["position_error_mm"] = pos.detach().cpu().numpy()
        cols["orientation_error_deg"] = ori.detach().cpu().numpy()
        return pd.DataFrame(cols)

    def error_summary(self) -> dict[str, dict[str, float]]:
        """Mean, std and max of the errors over all solutions (the paper's Tables IV/V).

        Returns:
            ``{"position_mm": {...}, "orientation_deg": {...}}``; NaN where there is
            nothing to summarise.
        """

        def stats(x: Tensor) -> dict[str, float]:
            x = x[self.valid].to(torch.float64)
            if x.numel() == 0 or not bool(torch.isfinite(x).all()):
                return {"mean": math.nan, "std": math.nan, "max": math.nan}
            std = float(x.std()) if x.numel() > 1 else 0.0
            return {"mean": float(x.mean()), "std": std, "max": float(x.max())}

        return {
            "position_mm": stats(self.position_error_mm),
            "orientation_deg": stats(self.orientation_error_deg),
        }

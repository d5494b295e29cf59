"""What a diagnosis returns: named causes, the diagnosis, and their JSON and report values."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.calibration.covariance import determined
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.effects import Effect, ExtendedModel
from hybrid_pk.effects.geometric import AxisMisalignment
from hybrid_pk.effects.joint import JointEccentricity
from hybrid_pk.evaluation.metrics import error_stats

__all__ = [
    "Cause",
    "Diagnosis",
    "cause_labels",
    "gravity_json",
    "identifiability_json",
    "report_value",
    "stats_json",
]


@dataclass
class Cause:
    """One statistically supported error cause (the diagnosis JSON's ``causes``)."""

    effect: str
    joint: str | None
    value: float | list[float]
    unit: str
    std: float | list[float]
    position_gain_mm: float
    orientation_gain_deg: float | None
    evidence: str
    components: list[float] | None = None
    in_sample_gain_mm: float | None = None
    random_holdout_gain_mm: float | None = None
    blocked_holdout_gain_mm: float | None = None
    blocked_position_gain_mm: float | None = None
    blocked_orientation_gain_deg: float | None = None
    blocked_blocks: dict[str, int] | None = None
    fitted_range_rad: list[float] | None = None
    own_range_gain_mm: float | None = None
    own_range: dict | None = None
    blocked_holdout_gain_se_mm: float | None = None  # its jackknife standard error
    # components whose split with other parameters the data do not determine at all:
    # ``{"component": k, "with": [parameter names]}`` (their value and std are the
    # minimum-norm solution's, not a measurement)
    undetermined: list[dict] | None = None

    def to_json(self) -> dict:
        out = {
            "effect": self.effect,
            "joint": self.joint,
            "value": self.value,
            "unit": self.unit,
            "std": self.std,
            "position_gain_mm": self.position_gain_mm,
            "orientation_gain_deg": self.orientation_gain_deg,
            "evidence": self.evidence,
        }
        if self.joint is None:
            del out["joint"]
        if self.components is not None:
            out["components"] = self.components
        for key in (
            "in_sample_gain_mm",
            "random_holdout_gain_mm",
            "blocked_holdout_gain_mm",
            "blocked_holdout_gain_se_mm",
            "blocked_position_gain_mm",
            "blocked_orientation_gain_deg",
            "blocked_blocks",
            "fitted_range_rad",
            "own_range_gain_mm",
            "own_range",
            "undetermined",
        ):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out


@dataclass
class Diagnosis:
    """Result of :func:`~hybrid_pk.calibration.diagnosis.diagnose`; ``to_json()`` is the
    diagnosis JSON of ``hybrid-pk diagnose --json``."""

    robot: str
    n_samples: int
    n_holdout: int
    nominal: dict
    extended: dict
    causes: list[Cause]
    ambiguous: list[dict]
    unexplained: dict
    identifiability: dict
    model: ExtendedModel
    nominal_model: ExtendedModel
    fit_rows: Tensor
    holdout_rows: Tensor
    steps: list[dict] = field(default_factory=list)
    warnings: list[dict] = field(default_factory=list)
    outliers: list[dict] = field(default_factory=list)
    robust: dict | None = None
    structural: dict | None = None
    frames: dict | None = None
    carry_over: dict | None = None
    budget: dict | None = None
    detectable: dict | None = None
    rival_stories: list[dict] = field(default_factory=list)
    setup_moves: list[dict] = field(default_factory=list)

    def to_json(self) -> dict:
        return {
            "robot": self.robot,
            "n_samples": self.n_samples,
            "n_holdout": self.n_holdout,
            "nominal": self.nominal,
            "causes": [c.to_json() for c in self.causes],
            "ambiguous": self.ambiguous,
            "extended": self.extended,
            "unexplained": self.unexplained,
            "identifiability": self.identifiability,
            "selection": self.steps,
            "warnings": self.warnings,
            "outliers": self.outliers,
            "robust": self.robust,
            "structural": self.structural,
            "frames": self.frames,
            "gravity": gravity_json(self.model),
            "carry_over": self.carry_over,
            "budget": self.budget,
            "detectable": self.detectable,
            "rival_stories": self.rival_stories,
            "setup_moves": self.setup_moves,
        }


def cause_labels(diag: Diagnosis) -> list[str]:
    """The diagnosed causes as effect labels (``kind:joint`` or ``kind``)."""
    return [c.effect if c.joint is None else f"{c.effect}:{c.joint}" for c in diag.causes]


def gravity_json(model: ExtendedModel) -> dict:
    """The mounting the statics used, with gravity in the root frame of each base set."""
    out = model.gravity.to_dict()
    with torch.no_grad():
        if model.gravity.levelled:
            R = model.base.matrix()[:, :3, :3]
            g = torch.tensor(model.gravity.vector, dtype=R.dtype)
            out["root_frame"] = [(R[k].T @ g).tolist() for k in range(R.shape[0])]
        else:
            out["root_frame"] = [list(model.gravity.vector)]
    return out


def stats_json(pos: Tensor, ori: Tensor | None) -> dict:
    """Mean/RMS/p95/max of per-row position [mm] and orientation [deg] errors."""
    return {
        "position_mm": error_stats(pos).to_dict(),
        "orientation_deg": None if ori is None else error_stats(ori).to_dict(),
    }


def report_value(e: Effect, std: Tensor) -> tuple:
    """``(value, std, components)`` of an effect as reported, from its parameter std.

    An axis misalignment's internal ``(u, v)`` on its basis becomes a rotation vector;
    an eccentricity is reported by its amplitude (``components`` = its two terms).
    """
    v = e.value.detach().to(torch.float64)
    if isinstance(e, AxisMisalignment):  # internal (u, v) on a basis -> rotation vector
        basis = e.basis.to(torch.float64)
        w_std = ((std[:, None] * basis) ** 2).sum(0).sqrt()  # ignores the u-v covariance
        return e.report_value(), [float(x) for x in w_std], None
    if isinstance(e, JointEccentricity):  # and cyclic_error_<n>
        amp = float(v.norm())
        # std of the amplitude by first-order propagation
        grad = (v / max(amp, 1e-300)).numpy()
        s = float(np.sqrt((grad**2 * std.numpy() ** 2).sum()))
        return amp, s, [float(x) for x in v]
    if v.numel() == 1:
        return float(v), float(std[0]), None
    return [float(x) for x in v], [float(x) for x in std], None


def identifiability_json(res: FitResult, unobservable: list[str]) -> dict:
    """Singular values, condition and observability index of the final fit.

    A direction whose singular value is below the rank cut of
    :func:`~hybrid_pk.calibration.covariance.determined` is an exact degeneracy: its
    singular value is round-off (it moves with the order of any sum that built the
    Jacobian), so it is counted in ``unidentifiable_directions`` and reported as 0,
    and the condition number and the observability index (the geometric mean of the
    singular values per square root of the residual count) are taken over the other
    directions only.
    """
    sv = res.singular_values
    keep = determined(sv, res.n_obs, res.n_params)
    s = sv[keep]
    return {
        "n_parameters": res.n_params,
        "unidentifiable_directions": res.n_params - int(keep.sum()),
        "condition_number": float(s[0] / s[-1]) if s.numel() else None,
        "singular_values": [float(v) if k else 0.0 for v, k in zip(sv, keep, strict=True)],
        "observability_index": (
            float(s.log().mean().exp() / math.sqrt(res.n_obs)) if s.numel() else 0.0
        ),
        "unobservable_candidates": unobservable,
        "noise_estimate": {"position_mm": res.sigma_pos_mm, "orientation_rad": res.sigma_rot_rad},
    }

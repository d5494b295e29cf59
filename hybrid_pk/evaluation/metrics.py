"""Pose error metrics of the seed paper (Ojer et al. 2024, eqs. 1 and 2) and their summaries.

Inputs are homogeneous transforms ``(*B, 4, 4)`` with translations in metres, or points
``(*B, 3)`` [m]; leading batch shapes broadcast. Errors come out in millimetres and
degrees (reports) or millimetres and radians (least-squares residuals). Every tensor
function is differentiable with finite gradients at zero error and at 180 degrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.errors import ShapeError
from hybrid_pk.geometry import broadcast_shapes, rotation_angle, so3_log

if TYPE_CHECKING:
    from hybrid_pk.data.measured import MeasuredData

__all__ = [
    "ErrorStats",
    "PoseError",
    "error_stats",
    "evaluate_json",
    "ik_cost",
    "pose_error",
    "pose_residual",
    "position_error_mm",
    "row_errors",
]

M_TO_MM = 1000.0


class PoseError(NamedTuple):
    """Per-sample pose errors: ``position_mm (*B,)`` [mm], ``orientation_deg (*B,)`` [deg]."""

    position_mm: Tensor
    orientation_deg: Tensor


def _check_transforms(name: str, T: Tensor) -> None:
    if T.ndim < 2 or T.shape[-2:] != (4, 4):
        raise ShapeError(
            f"{name}: expected homogeneous transforms (*B, 4, 4), got {tuple(T.shape)}"
        )


def _check_batches(measured: torch.Size, model: torch.Size) -> None:
    try:
        broadcast_shapes(measured, model)
    except RuntimeError:
        raise ShapeError(
            f"T_measured batch {tuple(measured)} and T_model batch {tuple(model)} do not "
            "match (one pose each per sample)"
        ) from None


def _check_points(name: str, p: Tensor) -> None:
    if p.ndim < 1 or p.shape[-1] != 3:
        raise ShapeError(f"{name}: expected points (*B, 3), got {tuple(p.shape)}")


def position_error_mm(p_measured: Tensor, p_model: Tensor) -> Tensor:
    """Euclidean distance ``||p_measured - p_model||`` between points.

    Args:
        p_measured: ``(*B, 3)`` measured points [m].
        p_model: ``(*B, 3)`` model points [m].

    Returns:
        ``(*B,)`` distance [mm]. Its gradient at zero distance is 0 (finite).
    """
    _check_points("p_measured", p_measured)
    _check_points("p_model", p_model)
    return M_TO_MM * torch.linalg.vector_norm(p_measured - p_model, dim=-1)


def _relative_rotation(T_measured: Tensor, T_model: Tensor) -> Tensor:
    """``R_meas @ R_model^T`` ``(*B, 3, 3)``: the rotation part of ``T_meas T_model^-1``."""
    return T_measured[..., :3, :3] @ T_model[..., :3, :3].transpose(-1, -2)


def pose_error(T_measured: Tensor, T_model: Tensor) -> PoseError:
    """Position and orientation error of the paper's eq. 1, ``T_diff = T_meas T_model^-1``.

    Position error is the point distance ``||p_meas - p_model||``, which is also the norm
    of the translation of ``T_model^-1 T_meas``. The literal translation of
    ``T_meas T_model^-1`` is ``p_meas - R_diff p_model``: it adds a lever arm (orientation
    error times the distance of the point from the base origin) and would change with
    where the base frame is put, so we deliberately report the point distance.
    Orientation error is the angle of ``R_meas R_model^T`` (the same for
    ``R_model^T R_meas``), from a robust ``atan2`` formula.

    Args:
        T_measured: ``(*B, 4, 4)`` measured poses [m].
        T_model: ``(*B, 4, 4)`` model poses [m].

    Returns:
        :class:`PoseError` with ``position_mm (*B,)`` [mm] and ``orientation_deg (*B,)``
        [deg] in ``[0, 180]``.
    """
    _check_transforms("T_measured", T_measured)
    _check_transforms("T_model", T_model)
    _check_batches(T_measured.shape[:-2], T_model.shape[:-2])
    position = position_error_mm(T_measured[..., :3, 3], T_model[..., :3, 3])
    angle = rotation_angle(_relative_rotation(T_measured, T_model))
    return PoseError(position_mm=position, orientation_deg=torch.rad2deg(angle))


def row_errors(T_model: Tensor, data: MeasuredData) -> tuple[Tensor, Tensor | None]:
    """Per-row position [mm] and orientation [deg] errors of predicted poses
    ``T_model (N, 4, 4)`` against measured rows (contract section 5); the orientation
    is None for position-only data."""
    if data.quat is None:
        return position_error_mm(data.position, T_model[..., :3, 3]), None
    err = pose_error(data.T_measured(), T_model)
    return err.position_mm, err.orientation_deg


def pose_residual(T_measured: Tensor, T_model: Tensor) -> Tensor:
    """Residual vector for least squares: ``[p_meas - p_model, log(R_meas R_model^T)]``.

    Args:
        T_measured: ``(*B, 4, 4)`` measured poses [m].
        T_model: ``(*B, 4, 4)`` model poses [m].

    Returns:
        ``(*B, 6)``: position difference [mm] (3, base-frame axes) then the rotation
        vector of ``R_meas R_model^T`` [rad] (3, norm in ``[0, pi]``). Mixed units: weight
        the two parts before summing squares.
    """
    _check_transforms("T_measured", T_measured)
    _check_transforms("T_model", T_model)
    dp = M_TO_MM * (T_measured[..., :3, 3] - T_model[..., :3, 3])
    dw = so3_log(_relative_rotation(T_measured, T_model))
    return torch.cat(torch.broadcast_tensors(dp, dw), dim=-1)


def ik_cost(T_a: Tensor, T_b: Tensor, *, translation_scale: float = M_TO_MM) -> Tensor:
    """Cartesian cost of the paper's eq. 2: ``e^T (T_A - T_B)^{o2} e``.

    The sum of the elementwise squared differences of the two matrices, with the
    translation column multiplied by ``translation_scale`` (metres to millimetres by
    default, as in the paper).

    Args:
        T_a: ``(*B, 4, 4)`` poses [m].
        T_b: ``(*B, 4, 4)`` poses [m].
        translation_scale: factor applied to translations (1000: cost in mm^2 + 1).

    Returns:
        ``(*B,)`` cost: rotation entries (unitless) squared plus translations squared
        [mm^2 with the default scale].
    """
    _check_transforms("T_a", T_a)
    _check_transforms("T_b", T_b)
    diff = T_a - T_b
    col_scale = torch.ones(4, dtype=diff.dtype, device=diff.device)
    col_scale[3] = translation_scale
    return (diff * col_scale).square().sum(dim=(-2, -1))


@dataclass(frozen=True)
class ErrorStats:
    """Summary of per-sample errors, all in the unit of the errors (mm or deg).

    Attributes:
        mean: arithmetic mean.
        rms: root mean square.
        p95: 95th percentile (linear interpolation, as ``numpy.percentile``).
        max: largest value.
    """

    mean: float
    rms: float
    p95: float
    max: float

    def to_dict(self) -> dict[str, float]:
        """Plain floats under the keys ``mean``, ``rms``, ``p95``, ``max`` (contract 5)."""
        return {"mean": self.mean, "rms": self.rms, "p95": self.p95, "max": self.max}


ArrayLike = Tensor | np.ndarray | Sequence[float]


def _as_flat_float64(values: ArrayLike, name: str) -> np.ndarray:
    if isinstance(values, Tensor):
        values = values.detach().to("cpu", torch.float64).numpy()
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    if x.size == 0:
        raise ShapeError(f"{name}: expected at least one value, got none")
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise ShapeError(
            f"{name}: expected finite values, found {bad.size} of {x.size} not finite "
            f"(first at flat index {bad[0]}: {x[bad[0]]})"
        )
    return x


def error_stats(values: ArrayLike, *, name: str = "values") -> ErrorStats:
    """Mean, RMS, 95th percentile and max of per-sample errors.

    Args:
        values: errors of any shape (flattened), e.g. ``(n,)`` [mm] or [deg].
        name: what the values are, for error messages.

    Returns:
        :class:`ErrorStats` in the unit of ``values``, computed in float64.

    Raises:
        ValueError: if ``values`` is empty or holds NaN/inf.
    """
    x = _as_flat_float64(values, name)
    return ErrorStats(
        mean=float(np.mean(x)),
        rms=float(math.sqrt(np.mean(np.square(x)))),
        p95=float(np.percentile(x, 95.0)),
        max=float(np.max(x)),
    )


def _stats_of(values: ErrorStats | ArrayLike, n: int, name: str) -> ErrorStats:
    if isinstance(values, ErrorStats):
        return values
    count = values.numel() if isinstance(values, Tensor) else np.size(values)
    if count != n:
        raise ShapeError(f"{name}: expected n = {n} values, got {count}")
    return error_stats(values, name=name)


def evaluate_json(
    n: int,
    position_mm: ErrorStats | ArrayLike,
    orientation_deg: ErrorStats | ArrayLike | None = None,
) -> dict:
    """Evaluation summary in the JSON structure of contract section 5.

    Args:
        n: number of evaluated samples.
        position_mm: ``(n,)`` position errors [mm], or their :class:`ErrorStats`.
        orientation_deg: ``(n,)`` orientation errors [deg], their :class:`ErrorStats`, or
            ``None`` for position-only data.

    Returns:
        ``{"n": n, "position_mm": {mean, rms, p95, max}, "orientation_deg": {...} | None}``
        with plain ``int``/``float`` values, ready for ``json.dump``.

    Raises:
        ValueError: if ``n`` is not a positive integer or an error array has not ``n``
            values.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ShapeError(f"n: expected a positive integer, got {n!r}")
    n = int(n)
    position = _stats_of(position_mm, n, "position_mm")
    orientation = (
        None if orientation_deg is None else _stats_of(orientation_deg, n, "orientation_deg")
    )
    return {
        "n": n,
        "position_mm": position.to_dict(),
        "orientation_deg": None if orientation is None else orientation.to_dict(),
    }

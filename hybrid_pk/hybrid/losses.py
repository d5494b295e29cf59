"""Training targets and losses of the residual networks (Ojer et al. 2024, section 3).

The base model is evaluated once per measured row; what the networks must still
explain is kept in the axes of the corrections (joint 1's frame, see
:mod:`hybrid_pk.hybrid.hybrid_fk`) as :class:`ResidualTargets`, so a training step costs
two small network passes and a few 3 x 3 products, in float64.

Losses (paper): the position network minimises the distance between measured and
predicted point (the Euclidean norm of the translation of ``T_diff``), the
orientation network the angle of ``R_meas R_pred^T`` (the norm of the axis-angle of
``T_diff``). Each network sees only its own loss: the rotation correction enters the
predicted *point* through the tool lever arm, but is detached there.

Names: :func:`corrected_position_errors_mm` and :func:`corrected_orientation_errors_deg`
take a base model's residual and the networks' corrections (the errors *after*
correcting, from :class:`ResidualTargets`); the evaluation metrics
:func:`hybrid_pk.evaluation.metrics.position_error_mm` and
:func:`~hybrid_pk.evaluation.metrics.pose_error` take two points or poses. On the same
rows both give the same numbers (``tests/test_hybrid_nets.py`` checks it).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import quat_to_matrix, rotation_angle, so3_exp, so3_log, transform_inverse
from hybrid_pk.hybrid.hybrid_fk import correction_axes, frame_matrices

__all__ = [
    "LOSSES",
    "ResidualTargets",
    "corrected_orientation_errors_deg",
    "corrected_position_errors_mm",
    "reduce_errors",
    "residual_targets",
]

LOSSES = ("norm", "mse")
# rows per base-model evaluation: 4096 poses' link transforms (4x4 float64 per link)
# stay in a few MB, and each chunk still fills the cores
_CHUNK = 4096


@dataclass(frozen=True, eq=False)
class ResidualTargets:
    """What the base model leaves unexplained, per row, in the axes of the corrections
    (joint 1's frame; float64). Distances and angles are those of the measurement frame.

    Attributes:
        q: ``(N, dof)`` joint values [rad or m].
        position: ``(N, 3)`` measured point minus the base model's point [m].
        lever: ``(N, 3)`` flange origin -> measured point, ``R_E x_tool`` [m].
        rotation: ``(N, 3, 3)`` ``R_meas R_base^T``, or None for position-only data.
    """

    q: Tensor
    position: Tensor
    lever: Tensor
    rotation: Tensor | None

    @property
    def n(self) -> int:
        return self.q.shape[0]

    def subset(self, index: Tensor) -> ResidualTargets:
        """Rows ``index`` as a new value."""
        rot = None if self.rotation is None else self.rotation[index]
        return ResidualTargets(self.q[index], self.position[index], self.lever[index], rot)

    def tensors(self) -> dict[str, Tensor]:
        """The columns as a dict (a training batch); ``rotation`` only if present."""
        out = {"q": self.q, "position": self.position, "lever": self.lever}
        if self.rotation is not None:
            out["rotation"] = self.rotation
        return out

    def scales(self) -> tuple[Tensor, Tensor]:
        """``(3,)`` RMS per axis of the position residual [m] and of the rotation vector
        of the rotation residual [rad] (1 mrad when there is none): the networks'
        output units."""
        pos = self.position.pow(2).mean(0).sqrt().clamp_min(1e-9)
        if self.rotation is None:
            # 1 mrad: the order of a calibrated arm's orientation error
            return pos, torch.full((3,), 1e-3, dtype=pos.dtype)
        rot = so3_log(self.rotation).pow(2).mean(0).sqrt().clamp_min(1e-12)
        return pos, rot


@torch.no_grad()
def residual_targets(
    base: ExtendedModel, data: MeasuredData, cond: Conditions | None = None
) -> ResidualTargets:
    """Evaluate ``base`` once on every row of ``data`` and keep what it leaves unexplained.

    Args:
        base: the base model (its frames map the measurement frame to the root frame).
        data: measured rows.
        cond: their conditions (payload, temperature, direction, frame set per row).
    """
    q = data.q.to(torch.float64)
    ends = []
    for start in range(0, data.n, _CHUNK):
        rows = slice(start, min(start + _CHUNK, data.n))
        sub = None if cond is None else cond.subset(torch.arange(rows.start, rows.stop))
        ends.append(base.end_pose(q[rows], sub).to(torch.float64))
    E = torch.cat(ends) if ends else torch.zeros(0, 4, 4, dtype=torch.float64)
    B, X = frame_matrices(base, cond)
    B, X = B.to(torch.float64), X.to(torch.float64)
    # Root frame first, then the axes of the corrections: R1^T (.) and R1^T (.) R1.
    B_inv = transform_inverse(B)
    p_meas = (B_inv[..., :3, :3] @ data.position[..., None])[..., 0] + B_inv[..., :3, 3]
    lever = (E[:, :3, :3] @ X[..., :3, 3:])[..., 0]
    position = p_meas - E[:, :3, 3] - lever
    R1t = correction_axes(base, q).transpose(-1, -2)
    rotation = None
    if data.quat is not None:
        R_meas = B_inv[..., :3, :3] @ quat_to_matrix(data.quat)
        rotation = R1t @ R_meas @ (E[:, :3, :3] @ X[..., :3, :3]).transpose(-1, -2) @ R1t.mT
    return ResidualTargets(
        q, (R1t @ position[..., None])[..., 0], (R1t @ lever[..., None])[..., 0], rotation
    )


def corrected_position_errors_mm(
    position: Tensor, lever: Tensor, dp: Tensor, dw: Tensor, detach_rotation: bool = True
) -> Tensor:
    """Distance [mm] between measured and hybrid point, ``(N,)``, from the base model's
    residual and the corrections (for two points: ``evaluation.metrics.position_error_mm``).

    Args:
        position: ``(N, 3)`` residual of the base model [m] (:class:`ResidualTargets`).
        lever: ``(N, 3)`` flange -> point [m].
        dp: ``(N, 3)`` flange position correction [m].
        dw: ``(N, 3)`` flange rotation correction [rad]; it moves the point by
            ``(exp(dw) - I) lever``.
        detach_rotation: the position loss does not train the orientation network.
    """
    if detach_rotation:
        dw = dw.detach()
    eye = torch.eye(3, dtype=lever.dtype, device=lever.device)
    swing = ((so3_exp(dw) - eye) @ lever[..., None])[..., 0]
    return 1e3 * torch.linalg.vector_norm(position - dp - swing, dim=-1)


def corrected_orientation_errors_deg(rotation: Tensor, dw: Tensor) -> Tensor:
    """Angle [deg] of ``R_meas R_hybrid^T`` = ``rotation exp(dw)^T``, ``(N,)``, from the
    base model's rotation residual and the correction ``dw``."""
    return torch.rad2deg(rotation_angle(rotation @ so3_exp(dw).transpose(-1, -2)))


def reduce_errors(errors: Tensor, loss: str) -> Tensor:
    """Batch loss from per-row errors: ``norm`` = mean error (paper), ``mse`` = mean square."""
    if loss == "norm":
        return errors.mean()
    if loss == "mse":
        return errors.square().mean()
    raise ValueError(f"unknown loss {loss!r}; one of {', '.join(LOSSES)}")

"""How much of what an effect does a change of the base and tool frames does too.

A cause whose displacement of the measured points is mostly a frame change measures a
trade-off with the frames, not a physical error (the structural check's frame share,
:mod:`.structural`); the structural search's link-length moves leave out the directions
a frame change makes exactly. Both judge displacements on an even subset of the rows.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.effects.base import SIGN_SIGMAS

__all__ = [
    "FRAME_SHARE_ROWS",
    "determined_part",
    "displacement",
    "even_subset",
    "frame_share",
    "off_frames",
]

# Rows the frame share is computed on (an even subset of larger data): a share is a
# ratio of the rows' spread, and 2000 rows (6000 equations) measure the 2 % a share
# keeps beside DiagnosisTuning.max_frame_share to about 1/sqrt(2000) = 2 % of itself.
FRAME_SHARE_ROWS = 2000


@torch.no_grad()
def displacement(
    model: ExtendedModel, label: str, data: MeasuredData, cond: Conditions, value=None
):
    """``(N, 3)`` [mm] what effect ``label`` moves the measured points by, frames fixed
    (the measurement frame); ``value`` (its parameters) in place of its own if given."""

    def copy(replace: bool) -> ExtendedModel:
        kept = [
            make_effect(model.robot, e.label, (value if e.label == label else e.value).detach())
            for e in model.effects
            if replace or e.label != label
        ]
        out = ExtendedModel(model.robot, kept, frame_sets=model.base.sets, gravity=model.gravity)
        out.base.reset_to(model.base.matrix().detach())
        out.tool.reset_to(model.tool.matrix().detach())
        return out

    full = model if value is None else copy(True)
    return 1e3 * (full(data.q, cond)[:, :3, 3] - copy(False)(data.q, cond)[:, :3, 3])


def off_frames(
    model: ExtendedModel, data: MeasuredData, cond: Conditions, *fields: Tensor
) -> list[Tensor]:
    """``fields`` (each ``(N, 3)``, displacements of the measured points in the
    measurement frame) without the part a change of the base and tool frames makes
    (least-squares projection off the frames' position columns at ``model``)."""
    blocks = param_blocks(
        model, ["base_frame.translation", "base_frame.rotation", "tool_frame.translation"], True
    )
    problem = Problem(model, data, cond, blocks, 1.0, 1.0)
    _, J = problem.jacobian(torch.zeros_like(problem.x0))
    Q, _ = torch.linalg.qr(J[: 3 * data.n])  # position rows, row-major like the fields
    out = []
    for f in fields:
        flat = f.reshape(-1).to(Q.dtype)
        out.append((flat - Q @ (Q.T @ flat)).reshape(-1, 3))
    return out


def even_subset(data: MeasuredData, cond: Conditions) -> tuple[MeasuredData, Conditions]:
    """At most ``FRAME_SHARE_ROWS`` rows, evenly spaced: a share or a rank of the rows'
    spread needs no more."""
    if data.n <= FRAME_SHARE_ROWS:
        return data, cond
    rows = torch.arange(0, data.n, math.ceil(data.n / FRAME_SHARE_ROWS))
    return data.subset(rows), cond.subset(rows)


def frame_share(
    model: ExtendedModel, label: str, data: MeasuredData, cond: Conditions, std=None
) -> tuple[float, Tensor, Tensor]:
    """Fraction of the displacement effect ``label`` makes that a frame change makes too.

    ``std``: the fit's standard deviations of the effect's parameters. A parameter
    within :data:`~hybrid_pk.effects.base.SIGN_SIGMAS` of them of zero is zero as far
    as the rows can tell (its value is wherever the frames' trade-off left it, within
    the rows' noise), so it is left out of the displacement judged: a value the rows do
    not determine measures neither a physical error nor a trade-off. With no parameter
    determined the share is 0 (nothing to judge).

    Returns:
        ``(share, d, d_phys)``: ``share`` in [0, 1], the displacement ``d (n, 3)`` [mm]
        and its part ``d_phys`` that no change of the base and tool frames makes, on
        the rows used (an even subset of at most ``FRAME_SHARE_ROWS``).
    """
    data, cond = even_subset(data, cond)
    d = displacement(model, label, data, cond, determined_part(model.effect(label), std))
    (d_phys,) = off_frames(model, data, cond, d)
    total = float((d**2).sum())
    if total == 0.0:
        return 0.0, d, d_phys
    share = 1.0 - float((d_phys**2).sum()) / total
    return min(max(share, 0.0), 1.0), d, d_phys


def determined_part(effect, std) -> Tensor | None:
    """The effect's value with its parameters within ``SIGN_SIGMAS`` of their ``std``
    of zero set to zero, or None when there is no such parameter (or no finite std)."""
    if std is None:
        return None
    v = effect.value.detach()
    s = torch.as_tensor(std, dtype=v.dtype).reshape(v.shape)
    noise = v.abs() <= SIGN_SIGMAS * s  # False where the std is NaN: kept
    return torch.where(noise, torch.zeros_like(v), v) if bool(noise.any()) else None

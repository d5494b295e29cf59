"""Frame directions the data do not determine are held with the tool at its prior.

Along a trade-off valley of the frames (the tool translation against the base's when
the flange orientation barely varies) the Gaussian prior of
:mod:`hybrid_pk.calibration.frames` only shrinks: with a prior of 0.1 m and data
that carry a comparable information, the fit still walks half-way to wherever the
unmodelled errors push it. Here such a direction is *held*: a residual row whose
information dwarfs the data's keeps the tool's part of it at the centre of the tool's
prior (the end link's origin, a given ``--tool``, or the tool registered to a given
``--base``); the base follows the data to
where that tool puts it. The directions are found at the optimum of the fit without
the hold (:func:`hybrid_pk.calibration.fit.fit`), so neither they nor the held value
depend on the start guess.

Rule (the same as the registration's): after the other frame parameters have
compensated what they can, a direction ``v`` moves the measured points by ``s``
(rms per row, mm per mm or mrad per mrad). An unmodelled error as large as the rms
error ``e`` left at that optimum that no free column removes (to first order: an
error the fitted effects explain is a modelled one), which no row count averages away
when it is systematic, moves the frame along ``v`` by ``e / s``. Where that exceeds
the prior's std along ``v`` the data do not determine ``v``; it is held.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from hybrid_pk.calibration.frames import Centre, PriorRows
from hybrid_pk.calibration.problem import subset_jacobian
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel

if TYPE_CHECKING:
    from hybrid_pk.calibration.problem import ParamBlock

__all__ = ["HOLD_INFORMATION", "HeldPrior", "held_prior", "join_rows"]

_FRAME_BLOCKS = ("base.dp", "base.rotvec", "tool.dp", "tool.rotvec")
# Rows of the frame Jacobian used to find the valleys (an even subset of larger data):
# the valleys are a property of the poses' spread, not of their count.
MAX_ROWS = 2000
# A held direction's row carries this many times the information of the data (at the
# start's error level) and the prior along it: the fit moves it by < 1e-6 of where
# they alone would take it, while the problem stays smooth for LM.
HOLD_INFORMATION = 1e6


class HeldPrior:
    """The frame prior's rows followed by the hold rows (``Problem(extra=...)``).

    Attributes:
        A: ``(k, n)`` constant rows of both.
        held: ``(n_frame, h)`` the held directions (scaled frame parameters).
    """

    def __init__(self, prior: PriorRows | None, start: PriorRows, W: Tensor, held: Tensor):
        self.prior, self.start, self.W, self.held = prior, start, W, held
        A_hold = W @ start.A
        self.A = A_hold if prior is None else torch.cat([prior.A, A_hold])

    def __call__(self, theta: Tensor) -> tuple[Tensor, Tensor]:
        r0, A0 = self.start(theta)
        r, A = self.W @ r0, self.W @ A0
        if self.prior is None:
            return r, A
        rp, Ap = self.prior(theta)
        return torch.cat([rp, r]), torch.cat([Ap, A])


def _tool_rows(
    model: ExtendedModel, blocks: tuple[ParamBlock, ...], prior: PriorRows, tool_given: bool
) -> PriorRows:
    """Rows ``theta_frame - (centre - now) / scale``: the frame offsets from the
    tool prior's centre (the end link's origin, or with ``tool_given`` the prior's:
    the given ``--tool`` or the tool registered to a given ``--base``) in scaled
    units (identity on the frame columns). The base's rows are centred where it is
    now; the hold weights give them no weight (:func:`held_prior`)."""
    centres = {}
    for b in blocks:
        if b.name not in _FRAME_BLOCKS:
            continue
        which, kind = b.name.split(".")
        if which == "tool" and b.name in prior.centres:
            value = prior.centres[b.name].value.clone()
            if kind == "dp" and not tool_given:  # the end link's origin, not a guess
                value = torch.zeros_like(value)
            centres[b.name] = Centre(value, b.scale)
            continue
        T = getattr(model, which).matrix().detach()
        value = T[:, :3, 3] if kind == "dp" else T[:, :3, :3]
        centres[b.name] = Centre(value.clone(), b.scale)
    return PriorRows(model, blocks, centres)


def _valleys(
    model: ExtendedModel, data: MeasuredData, cond: Conditions, blocks: tuple[ParamBlock, ...]
) -> tuple[Tensor, Tensor, Tensor, float]:
    """``(sens, V, H, e)``: rms point motion per row and unit of each eigenvector
    (columns of ``V``) of the frame columns' information, the information ``H`` of all
    rows per unit error [1/mm² per scaled unit²] and the rms position error ``e`` [mm]
    the fit cannot remove (a linear step of every free column from the start)."""
    r, J_all, sub, _ = subset_jacobian(model, data, cond, blocks, MAX_ROWS)
    is_frame = torch.cat(
        [torch.full((b.size,), b.name in _FRAME_BLOCKS, dtype=torch.bool) for b in blocks]
    )
    J = J_all[:, is_frame]
    n_sub = sub.n
    H = J.T @ J
    lam, V = torch.linalg.eigh(H / n_sub)
    # what neither the frames nor the fit's effects explain (to first order) is the
    # unmodelled error: an error the fitted effects remove does not move the frames
    step_ = torch.linalg.lstsq(J_all, r[:, None]).solution[:, 0]
    left = (r - J_all @ step_)[: 3 * n_sub]
    e = float(left.pow(2).sum().div(n_sub).sqrt())  # rms 3-D position error [mm]
    return lam.clamp_min(0).sqrt(), V, H * (data.n / n_sub), e


def held_prior(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    blocks: tuple[ParamBlock, ...],
    prior: PriorRows | None,
    tool_given: bool = False,
) -> PriorRows | HeldPrior | None:
    """``prior`` with hold rows for the frame directions the data do not determine
    (module docstring), or ``prior`` itself when there is none.

    Without a prior (every std infinite) nothing is held: a plain least-squares fit.
    """
    names = [b.name for b in blocks if b.name in _FRAME_BLOCKS]
    if prior is None or not names or data.n < 2:
        return prior
    idx = []
    start = 0
    for b in blocks:
        if b.name in _FRAME_BLOCKS:
            idx.extend(range(start, start + b.size))
        start += b.size
    sens, V, H, e = _valleys(model, data, cond, blocks)
    P = prior.A[:, idx].T @ prior.A[:, idx]
    # the tool's columns among the frame columns: a held valley is pinned by its tool
    # part, so the base follows the data to wherever that tool puts it
    tool_cols = torch.cat(
        [
            torch.full((b.size,), b.name.startswith("tool."), dtype=torch.bool)
            for b in blocks
            if b.name in _FRAME_BLOCKS
        ]
    )
    held, weights = [], []
    for k in range(V.shape[1]):
        v = V[:, k]
        prior_info = float(v @ P @ v)
        if prior_info <= 0:
            continue
        prior_std = 1.0 / math.sqrt(prior_info)  # scaled units: mm or mrad
        if e <= sens[k] * prior_std:
            continue
        v_tool = torch.where(tool_cols, v, torch.zeros_like(v))
        along = float(v_tool @ v)  # a step along v moves the tool row by this much
        # a valley with (almost) no tool part cannot be pinned by the tool: the row
        # would need more than HOLD_INFORMATION times the weight; the prior keeps it
        if along * along * HOLD_INFORMATION < 1.0:
            continue
        # H = J^T J is positive semi-definite: a negative v H v is rounding (a direction
        # the rows do not see at all), and with noise-free rows e is ~0, which made it -1e10
        data_info = max(float(v @ H @ v), 0.0) / max(e, 1e-12) ** 2
        held.append(v_tool / along)
        weights.append(math.sqrt(HOLD_INFORMATION * (data_info + prior_info)))
    if not held:
        return prior
    Vh = torch.stack(held, 1)
    W = torch.diag(torch.tensor(weights, dtype=Vh.dtype)) @ Vh.T
    return HeldPrior(prior, _tool_rows(model, blocks, prior, tool_given), W, Vh)


def join_rows(a, b):
    """Extra residual rows ``a`` then ``b`` (either may be None)."""
    if a is None or b is None:
        return a or b

    def both(theta: Tensor) -> tuple[Tensor, Tensor]:
        (ra, Ja), (rb, Jb) = a(theta), b(theta)
        return torch.cat([ra, rb]), torch.cat([Ja, Jb])

    return both

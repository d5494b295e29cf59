"""Blocked hold-out: what a model predicts for rows unlike the ones it was fitted on.

Random hold-out rows lie between fit rows: they measure interpolation. The diagnosis
also scores every model on *blocked* hold-out data: the fit rows are cut into
contiguous regions of joint space (k-means of the joints that move the measured point
most, in metres of that motion: :mod:`.regions`) and, with several files, into whole
files (set-ups). Each block is predicted by the model fitted on the other blocks. With
frames per file, a held-out file's own frames are re-fitted on its rows (a new set-up
is re-stationed), everything else comes from the other files.

The fits per block are linearised at the current fit: one Jacobian of every parameter
(and candidate) on the fit rows, reduced to one Gram matrix of ``[J r]`` per cell
(region x file), gives every block's refit and prediction by a small solve, for any
subset of the parameters and for any effect set to zero (a cause removed).

A gain is the drop of the RMS error in mm: the position error, with the rotation error
(pose data) counted at the campaign's noise ratio ``sigma_pos / sigma_rot`` (the
weighting every fit uses), so that one unit of rotation noise counts as one of position:
every measured component is evidence of a physical cause. With the tuning's
``carry_over_channel = "position"`` only the position error is judged (the quantity an
absolute accuracy is stated in); the fits per block still use every component.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.fold_fits import fold_fits, fold_fits_each
from hybrid_pk.calibration.diagnosis.grams import add_gram, filled
from hybrid_pk.calibration.problem import ParamBlock, Problem
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.errors import HybridPKError

__all__ = [
    "Blocked",
    "BlockedScore",
    "Folds",
    "cell_factors",
    "margin_sigma",
    "position_channel",
    "practical_margin",
    "whole_campaign",
]


def practical_margin(
    sigma_pos_mm: float, override: float | None = None, noise_mm: float | None = None
) -> float:
    """The smallest blocked hold-out gain [mm] a cause must bring: ``override`` (the
    ``--min-gain-mm`` option) or ``sigma / sqrt(2 n)`` with n the tuning's ``check_rows``,
    ``sigma`` the measurement noise ``noise_mm`` (:mod:`.noise`, model-free) capped by
    the fit's ``sigma_pos_mm`` (which also holds every error the model leaves out)."""
    if override is not None:
        return float(override)
    return margin_sigma(sigma_pos_mm, noise_mm) / math.sqrt(2 * diagnosis_tuning().check_rows)


def position_channel() -> bool:
    """Whether gains are judged on the position error alone (the tuning's
    ``carry_over_channel``; the fits per block use every measured component)."""
    channel = diagnosis_tuning().carry_over_channel
    if channel not in ("position", "pose"):
        raise HybridPKError(f"carry_over_channel {channel!r}: position or pose")
    return channel == "position"


def margin_sigma(sigma_pos_mm: float, noise_mm: float | None) -> float:
    """The noise [mm] the default margin is set from: the model-free ``noise_mm``
    capped by the fit's ``sigma_pos_mm`` (the fit's alone without a noise estimate)."""
    return float(sigma_pos_mm) if noise_mm is None else min(float(noise_mm), sigma_pos_mm)


@dataclass(frozen=True)
class Folds:
    """Cells of the fit rows and the folds (sets of cells) held out in turn.

    Attributes:
        cell: ``(n_fit,)`` cell of each fit row (``file * regions + region``).
        n_cells: number of cells.
        folds: the cells of each held-out block.
        description: what the blocks are (JSON).
    """

    cell: Tensor
    n_cells: int
    folds: tuple[tuple[int, ...], ...]
    description: dict


def whole_campaign(n: int) -> Folds:
    """One cell of all ``n`` fit rows and no block held out: :func:`cell_factors` then
    gives the Grams of the whole fit, e.g. its position part alone."""
    return Folds(torch.zeros(n, dtype=torch.long), 1, (), {})


def cell_factors(
    problem: Problem,
    folds: Folds | None,
    factor: bool = True,
    lead: int | None = None,
    chunks: Iterable[Tensor] | None = None,
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """A factor ``R`` of ``[J r]`` on all rows (``R^T R = [J r]^T [J r]``, as
    :meth:`Problem.r_factor`; None unless ``factor``) and, with ``folds``, the Gram
    matrices of ``[J r]`` per cell: ``(pos, rot)``, each ``(n_cells, n + 1, n + 1)``
    (``rot`` None for position-only data).

    ``lead``: only the first ``lead`` columns are factored by QR; the rest of ``R``
    is completed from the Gram (:func:`_completed_factor`), or by a full QR where the
    leading columns are too ill-conditioned for that. ``chunks``: the problem's ``[J r]``
    chunks at its values when already built (default: built here).
    """
    R, start = None, 0
    per_row = 3 if problem.R_meas is None else 6
    grams: tuple = ()
    size = problem.x0.numel() + 1
    if folds is not None:
        zeros = torch.zeros(folds.n_cells, size, size, dtype=problem.x0.dtype)
        grams = (zeros, None if per_row == 3 else zeros.clone())
    G = torch.zeros(size, size, dtype=problem.x0.dtype) if lead is not None and not grams else None
    if chunks is None:
        chunks = problem.augmented_chunks(torch.zeros_like(problem.x0))
    for M in chunks:
        n_c = M.shape[0] // per_row
        if folds is not None:
            # rows gathered cell by cell (stable: each cell's rows keep their order)
            cells, order = folds.cell[start : start + n_c].repeat_interleave(3).sort(stable=True)
            counts = torch.bincount(cells, minlength=folds.n_cells).tolist()
            for channel, part in enumerate((M[: 3 * n_c], M[3 * n_c :])):
                if grams[channel] is None:
                    continue
                for c, sub in enumerate(part[order].split(counts)):
                    if counts[c]:
                        add_gram(grams[channel][c], sub)
        elif G is not None:
            add_gram(G, M)
        start += n_c
        if factor:
            M = M if lead is None else M[:, :lead]
            R = torch.linalg.qr(M if R is None else torch.cat([R, M], 0), mode="r").R
    grams = tuple(None if g is None else filled(g) for g in grams)  # lower triangles so far
    G = None if G is None else filled(G)
    if factor and lead is not None:
        if G is None:
            G = grams[0].sum(0) if grams[1] is None else grams[0].sum(0) + grams[1].sum(0)
        R = _completed_factor(R, G, per_row * problem.data.n)
        if R is None:
            R = problem.r_factor(torch.zeros_like(problem.x0))
    return R, grams[0] if grams else None, grams[1] if grams else None


def _completion_limit(m: int) -> float:
    """Condition number (columns at unit norm) of the leading columns up to which the
    rest of a factor is completed from the Gram of ``m`` residual rows: that loses
    ~ 2 sqrt(m) eps cond of a column's squared norm, which must stay 100 times below
    the 1e-8 share that makes a candidate equivalent to the model
    (``selection.EQUIVALENCE_FRACTION``)."""
    return 1e-10 / (2 * math.sqrt(max(m, 1)) * torch.finfo(torch.float64).eps)


# Directions of the leading columns (at unit norm) weaker than this share of the
# strongest are exact degeneracies (two parameters the data cannot tell apart): a QR
# leaves them at round-off, ~ sqrt(m) eps ~ 1e-13; 1e-10 lies far above that and far
# below any direction data determine (their singular values pass the completion limit).
NULL_SHARE = 1e-10


def _completed_factor(R11: Tensor, G: Tensor, m: int) -> Tensor | None:
    """``R`` with ``R^T R = G`` (the Gram of ``[J r]``, ``m`` rows) whose leading rows
    stand for the first ``k`` columns, from their QR factor ``R11 = U diag(s) W^T``:
    ``[[diag(s) W^T, B], [0, F]]`` with ``B = diag(1/s) W^T G_12`` (zero in the
    directions the leading columns do not span, :data:`NULL_SHARE`) and ``F^T F = S =
    G_22 - B^T B``, the Gram of the other columns projected off the leading ones
    (semi-normal equations: a QR of only ``k`` columns). ``F`` from the
    eigen-decomposition of ``S`` at the columns' unit norm (``S`` may be singular:
    candidates the model already explains). None where ``R11`` has fewer rows than
    columns, or spans a direction too weakly for the Gram (:func:`_completion_limit`)."""
    k = R11.shape[1]
    norms = R11.norm(dim=0)
    if R11.shape[0] < k:
        return None
    unit = torch.where(norms > 0, norms, torch.ones_like(norms))
    _, sv, Wt = torch.linalg.svd(R11 / unit, full_matrices=False)  # R11 = U diag(sv) Wt D
    spans = sv > NULL_SHARE * sv[0]
    if float(sv[0]) > _completion_limit(m) * float(sv[spans][-1]):
        return None
    coef = torch.where(spans, 1.0 / sv.clamp_min(1e-300), torch.zeros_like(sv))
    B = coef[:, None] * ((Wt / unit[None, :]) @ G[:k, k:])  # U^T Q^T [J_rest r]
    S = G[k:, k:] - B.T @ B
    scale = G[k:, k:].diagonal().clamp_min(0).sqrt()  # the other columns' norms
    inv = torch.where(scale > 0, 1.0 / scale.clamp_min(1e-300), torch.zeros_like(scale))
    lam, V = torch.linalg.eigh(S * inv[:, None] * inv[None, :])
    F = lam.clamp_min(0).sqrt()[:, None] * V.T * scale[None, :]
    top = torch.cat([sv[:, None] * Wt * unit[None, :], B], 1)  # U^T R11
    return torch.cat([top, torch.cat([F.new_zeros(F.shape[0], k), F], 1)], 0)


@dataclass(frozen=True)
class BlockedScore:
    """Blocked hold-out sums of squares (noise-normalised) and the rows they cover."""

    total: float
    position: float
    rotation: float | None
    rows: int
    per_fold: tuple[tuple[float, float, int], ...] = ()  # (total, position, rows) per block


@dataclass
class Blocked:
    """Cell Gram matrices of one linearisation and the folds they are scored on.

    Attributes:
        pos, rot: ``(n_cells, n + 1, n + 1)`` Grams of ``[J r]`` (position, rotation).
        folds: the cells held out in turn.
        frame_cols: ``(n,)`` which columns are frame parameters (re-fitted on a
            held-out file that no training row sees).
        blocks: the parameter blocks of the columns (frames first, then effects).
        values: ``(n,)`` each column's current value in its scaled unit (setting an
            effect to zero shifts its columns by ``-values``).
        sigmas: ``(sigma_pos_mm, sigma_rot_rad)`` the residuals are normalised by.
    """

    pos: Tensor
    rot: Tensor | None
    folds: Folds
    blocks: tuple[ParamBlock, ...]
    values: Tensor
    sigmas: tuple[float, float | None]

    def __post_init__(self) -> None:
        self.rows = torch.bincount(self.folds.cell, minlength=self.folds.n_cells)
        self.frame_cols = self.columns(
            [b.label for b in self.blocks if b.label.startswith(("base_frame", "tool_frame"))]
        )

    def columns(self, labels) -> Tensor:
        """Bool ``(n,)``: the columns of the blocks ``labels``."""
        out, start, wanted = torch.zeros(self.values.numel(), dtype=torch.bool), 0, set(labels)
        for b in self.blocks:
            if b.label in wanted:
                out[start : start + b.size] = True
            start += b.size
        return out

    def of(self, effects, removed=()) -> BlockedScore:
        """Blocked score of the frames and ``effects`` (labels) re-fitted per block,
        the effects ``removed`` set to zero, every other column held where it is."""
        free = self.frame_cols | self.columns(effects)
        gone = self.columns(removed)
        return self.score(free, torch.where(gone, -self.values, torch.zeros_like(self.values)))

    def each(self, effects, extras, removed=()) -> list[BlockedScore]:
        """``[self.of([*effects, x], removed) for x in extras]``, the same values, with
        the extras of one column count gathered and solved as one batch."""
        out: list[BlockedScore | None] = [None] * len(extras)
        gone = self.columns(removed)
        shift = torch.where(gone, -self.values, torch.zeros_like(self.values))
        base, groups = self.frame_cols | self.columns(effects), {}
        for i, x in enumerate(extras):
            free = base | self.columns([x])
            if bool((free & gone).any()) or not self.folds.folds:
                out[i] = self.score(free, shift)  # a held column freed: its own last column
            else:
                groups.setdefault(int(free.sum()), []).append((i, torch.nonzero(free).flatten()))
        last = torch.zeros(self.values.numel() + 1, dtype=self.pos.dtype)
        last[-1], last[:-1] = 1.0, shift
        for items in groups.values():
            idx = torch.stack([ix for _, ix in items])
            for (i, _), sc in zip(items, self._scores(idx, last), strict=True):
                out[i] = sc
        return out

    def _scores(self, idx: Tensor, last: Tensor) -> list[BlockedScore]:
        """:meth:`score` of each row of ``idx`` (``(C, k)`` free columns), the held
        columns at ``last``: the gathers and the solves batched, each candidate's
        sums and products as :meth:`score` makes them."""
        pos = _selected_each(self.pos, idx, last)
        both = pos if self.rot is None else pos + _selected_each(self.rot, idx, last)
        out = []
        folds = [list(cells) for cells in self.folds.folds]
        rows = [int(self.rows[cells].sum()) for cells in folds]
        all_cells = both.sum(1)  # sums over cells: each candidate's in the same order
        test = torch.stack([both[:, cells].sum(1) for cells in folds], 1)
        test_pos = torch.stack([pos[:, cells].sum(1) for cells in folds], 1)
        theta = fold_fits_each(all_cells[:, None] - test, test, self.frame_cols[idx], all_cells)
        for c in range(idx.shape[0]):
            v = torch.cat([theta[c], theta.new_ones(theta.shape[1], 1)], 1)[:, None, :]
            per_fold = tuple(
                zip(
                    (v @ test[c] @ v.mT).flatten().tolist(),
                    (v @ test_pos[c] @ v.mT).flatten().tolist(),
                    rows,
                    strict=True,
                )
            )
            total, total_pos, n = (sum(f[i] for f in per_fold) for i in range(3))  # in order
            rot = None if self.rot is None else total - total_pos
            out.append(BlockedScore(total, total_pos, rot, n, per_fold))
        return out

    def score(self, free: Tensor, shift: Tensor | None = None) -> BlockedScore:
        """Blocked score of the linearised model with the columns ``free`` (bool
        ``(n,)``) re-fitted per block and the others held at ``shift`` (scaled offsets;
        None: zero, the linearisation point)."""
        n = free.numel()
        idx = torch.nonzero(free).flatten()
        last = torch.zeros(n + 1, dtype=self.pos.dtype)
        last[n] = 1.0
        if shift is not None:
            last[:n] = torch.where(free, torch.zeros_like(shift), shift)
        pos = _selected(self.pos, idx, last)
        both = pos if self.rot is None else pos + _selected(self.rot, idx, last)
        if not self.folds.folds:  # the whole campaign as one cell: nothing held out
            return BlockedScore(0.0, 0.0, None if self.rot is None else 0.0, 0)
        frames = self.frame_cols[idx]
        all_cells = both.sum(0)
        test = torch.stack([both[list(cells)].sum(0) for cells in self.folds.folds])
        test_pos = torch.stack([pos[list(cells)].sum(0) for cells in self.folds.folds])
        theta = fold_fits(all_cells - test, test, frames, all_cells)
        v = torch.cat([theta, theta.new_ones(theta.shape[0], 1)], 1)[:, None, :]
        per_fold = tuple(
            zip(
                (v @ test @ v.mT).flatten().tolist(),
                (v @ test_pos @ v.mT).flatten().tolist(),
                [int(self.rows[list(cells)].sum()) for cells in self.folds.folds],
                strict=True,
            )
        )
        total, total_pos, rows = (sum(f[i] for f in per_fold) for i in range(3))  # in order
        rot = None if self.rot is None else total - total_pos
        return BlockedScore(total, total_pos, rot, rows, per_fold)

    def gain_mm(self, without: BlockedScore, with_it: BlockedScore) -> float:
        """Drop of the blocked RMS error [mm] in the carry-over channel
        (:func:`position_channel`) from ``without`` to ``with_it``."""
        part = (lambda s: s.position) if position_channel() else (lambda s: s.total)
        return self.sigmas[0] * _rms_drop(part(without), part(with_it), without.rows)

    def gain_se_mm(self, without: BlockedScore, with_it: BlockedScore) -> float:
        """Standard error [mm] of :meth:`gain_mm` over the held-out blocks: the
        delete-one-block jackknife of the pooled gain (each block left out of both
        sums in turn). It holds what the model leaves out as well as the noise: a gain
        one block gives and another takes back has a standard error as large as
        itself. 0 with fewer than two blocks."""
        i = 1 if position_channel() else 0
        a, b = [f[i] for f in without.per_fold], [f[i] for f in with_it.per_fold]
        n = [f[2] for f in without.per_fold]
        k = len(n)
        if k < 2:
            return 0.0
        rest = [
            _rms_drop(sum(a) - a[j], sum(b) - b[j], sum(n) - n[j]) for j in range(k)
        ]  # fmt: skip
        mean = sum(rest) / k
        return self.sigmas[0] * math.sqrt((k - 1) / k * sum((g - mean) ** 2 for g in rest))

    def rms_mm(self, score: BlockedScore) -> float:
        """The blocked RMS error [mm] of ``score`` in the carry-over channel (what
        :meth:`gain_mm` takes differences of)."""
        part = score.position if position_channel() else score.total
        return self.sigmas[0] * _rms_drop(part, 0.0, score.rows)

    def block_drops(self, without: BlockedScore, with_it: BlockedScore) -> list[float]:
        """Per held-out block, the drop of its RMS error [mm] in the carry-over channel
        (:meth:`gain_mm` pools the blocks)."""
        i = 1 if position_channel() else 0
        return [
            self.sigmas[0] * _rms_drop(a[i], b[i], a[2])
            for a, b in zip(without.per_fold, with_it.per_fold, strict=True)
        ]

    def parts(self, without: BlockedScore, with_it: BlockedScore) -> dict:
        """The drop of the blocked RMS position error [mm] and rotation error [deg], and
        in how many of the held-out blocks the error drops (``blocks_gained`` of
        ``blocks``): a gain all blocks share, or one region's."""
        drops = self.block_drops(without, with_it)
        out = {"position_mm": self.sigmas[0] * _rms_drop(without.position, with_it.position,
                                                          without.rows),
               "blocks_gained": sum(d > 0 for d in drops), "blocks": len(drops)}  # fmt: skip
        if without.rotation is not None and self.sigmas[1] is not None:
            drop = _rms_drop(without.rotation, with_it.rotation, without.rows)
            out["orientation_deg"] = math.degrees(self.sigmas[1] * drop)
        return out


def _selected(P: Tensor, idx: Tensor, last: Tensor) -> Tensor:
    """``T^T P T`` of every cell's Gram ``P (cells, n + 1, n + 1)`` of ``[J r]`` with
    ``T = [e_idx, last]``: the columns ``idx`` and, last, the residual column plus the
    held columns times their shifts (``last (n + 1,)``), by indexing and one matrix-
    vector product instead of two matrix products."""
    k = idx.numel()
    u = P @ last  # (cells, n + 1)
    out = P.new_empty(P.shape[0], k + 1, k + 1)
    out[:, :k, :k] = P[:, idx][:, :, idx]
    out[:, :k, k] = u[:, idx]
    out[:, k, :k] = u[:, idx]
    out[:, k, k] = u @ last
    return out


def _selected_each(P: Tensor, idx: Tensor, last: Tensor) -> Tensor:
    """:func:`_selected` of each row of ``idx (C, k)``: ``(C, cells, k + 1, k + 1)``."""
    k = idx.shape[1]
    u = P @ last
    out = P.new_empty(idx.shape[0], P.shape[0], k + 1, k + 1)
    out[:, :, :k, :k] = P[:, idx[:, :, None], idx[:, None, :]].transpose(0, 1)
    out[:, :, :k, k] = out[:, :, k, :k] = u[:, idx].transpose(0, 1)
    out[:, :, k, k] = u @ last
    return out


def _rms_drop(a: float, b: float, rows: int) -> float:
    return math.sqrt(max(a, 0.0) / max(rows, 1)) - math.sqrt(max(b, 0.0) / max(rows, 1))

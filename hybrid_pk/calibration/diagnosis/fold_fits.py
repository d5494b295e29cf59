"""The fits per held-out block of the blocked hold-out (:mod:`.blocked`): least squares
on the Gram of ``[J r]`` of the training cells, the frame columns that only the held-out
file sees then fitted on its rows; one candidate, or many in one batch."""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.grams import solve_gram

__all__ = ["UNSEEN_SHARE", "fold_fit", "fold_fits", "fold_fits_each"]

# A frame column the training rows of a block see less than this share of (relative to
# all rows) belongs to the held-out file alone: re-fitted on the held-out rows. A seen
# column keeps at least one row's share (1/n, > 1e-6 up to a million rows), an unseen
# one only float64 round-off (~1e-16): 1e-9 lies orders of magnitude from both.
UNSEEN_SHARE = 1e-9


def fold_fit(train: Tensor, test: Tensor, frames: Tensor, all_rows: Tensor) -> Tensor:
    """Scaled parameter offsets of one block: least squares on ``train`` (a Gram of
    ``[J r]``); frame columns the training rows do not see are then fitted on ``test``
    with the rest held."""
    k = train.shape[0] - 1
    seen_all = all_rows.diagonal()[:k].clamp_min(1e-300)
    unseen = frames & (train.diagonal()[:k] <= UNSEEN_SHARE * seen_all)
    theta = torch.zeros(k, dtype=train.dtype)
    fit = ~unseen
    if fit.any():
        theta[fit] = solve_gram(train[:k, :k][fit][:, fit], train[:k, k][fit])
    if unseen.any():
        g = test[:k, k][unseen] + test[:k, :k][unseen][:, fit] @ theta[fit]
        theta[unseen] = solve_gram(test[:k, :k][unseen][:, unseen], g)
    return theta


def fold_fits(train: Tensor, test: Tensor, frames: Tensor, all_rows: Tensor) -> Tensor:
    """:func:`fold_fit` of every fold (``train``, ``test``: ``(folds, k + 1, k + 1)``),
    ``(folds, k)``: the folds whose training rows see every frame column in one batched
    solve, the others one by one."""
    k = train.shape[-1] - 1
    seen_all = all_rows.diagonal()[:k].clamp_min(1e-300)
    unseen = frames & (train.diagonal(dim1=-2, dim2=-1)[:, :k] <= UNSEEN_SHARE * seen_all)
    plain = ~unseen.any(1)
    theta = train.new_zeros(train.shape[0], k)
    if bool(plain.any()):
        theta[plain] = solve_gram(train[plain][:, :k, :k], train[plain][:, :k, k])
    for f in torch.nonzero(~plain).flatten().tolist():
        theta[f] = fold_fit(train[f], test[f], frames, all_rows)
    return theta


def fold_fits_each(train: Tensor, test: Tensor, frames: Tensor, all_rows: Tensor) -> Tensor:
    """:func:`fold_fits` of each candidate (``train``, ``test``: ``(C, folds, k + 1,
    k + 1)``; ``frames (C, k)``, ``all_rows (C, k + 1, k + 1)``): ``(C, folds, k)``."""
    k = train.shape[-1] - 1
    seen_all = all_rows.diagonal(dim1=-2, dim2=-1)[:, None, :k].clamp_min(1e-300)
    share = train.diagonal(dim1=-2, dim2=-1)[..., :k] <= UNSEEN_SHARE * seen_all
    unseen = frames[:, None, :] & share
    plain = ~unseen.any(-1)
    theta = train.new_zeros(*train.shape[:2], k)
    if bool(plain.any()):
        theta[plain] = solve_gram(train[plain][:, :k, :k], train[plain][:, :k, k])
    groups: dict[bytes, list[tuple[int, int]]] = {}  # by the columns left unseen
    for c, f in torch.nonzero(~plain).tolist():
        groups.setdefault(unseen[c, f].numpy().tobytes(), []).append((c, f))
    for items in groups.values():
        c, f = torch.tensor(items).T
        theta[c, f] = _held_out_fits(train[c, f], test[c, f], unseen[c[0], f[0]])
    return theta


def _held_out_fits(train: Tensor, test: Tensor, unseen: Tensor) -> Tensor:
    """:func:`fold_fit` of a batch of blocks ``(B, k + 1, k + 1)`` that leave the same
    frame columns ``unseen`` (at least one): the solves batched, each block's product
    as :func:`fold_fit` makes it."""
    k = train.shape[-1] - 1
    fit = ~unseen
    theta = train.new_zeros(train.shape[0], k)
    if fit.any():
        theta[:, fit] = solve_gram(train[:, :k, :k][:, fit][:, :, fit], train[:, :k, k][:, fit])
    g = torch.stack(
        [
            t[:k, k][unseen] + t[:k, :k][unseen][:, fit] @ th[fit]
            for t, th in zip(test, theta, strict=True)
        ]
    )
    theta[:, unseen] = solve_gram(test[:, :k, :k][:, unseen][:, :, unseen], g)
    return theta

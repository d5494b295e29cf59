"""One ``[J r]`` per model point, shared by every question asked there.

After the search the diagnosis asks several questions of the same final model: is the
capped search's next candidate still worth it, which swap's alternative, does every
cause carry over (settle), what could the data have detected, which candidate could
stand in for a cause (rival stories). Each linearises the model with its own
candidates' columns, most of them the same. The chunks of ``[J r]`` (as
:meth:`Problem.augmented_chunks` yields them at the model's values) are kept for the
last point linearised, with every column asked for there; a question at the same point
computes only the columns not yet kept and reads the rest (rescaled to its noise
levels). The point is the model's frames and the values of its non-zero effects (a
candidate at zero changes nothing): exactly equal, so a kept column is the column the
question would have computed (up to the round-off of another chunking).
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Iterator

import torch
from torch import Tensor

from hybrid_pk.calibration.problem import ParamBlock, Problem
from hybrid_pk.calibration.work import count as count_work
from hybrid_pk.effects import ExtendedModel

__all__ = ["SharedColumns", "model_point", "release_shared", "same_point", "shared_chunks"]


def model_point(model: ExtendedModel) -> tuple:
    """What the model's poses depend on besides the rows: robot (its values too),
    mounting, frames (their guesses and offsets) and the values of the effects that are
    not zero, in order."""
    robot = [*model.robot.parameters(), *model.robot.buffers()]
    frames = [t.detach().clone() for f in (model.base, model.tool) for t in (f.T0, f.dp, f.rotvec)]
    frames += [t.detach().clone() for t in robot if t.is_floating_point()]
    effects = [(e.label, e.value.detach().clone()) for e in model.effects if bool(e.value.any())]
    return model.robot, model.gravity, frames, effects


def same_point(a: tuple, b: tuple) -> bool:
    """Whether two :func:`model_point` are the same point."""
    if a[0] is not b[0] or a[1] is not b[1] or len(a[3]) != len(b[3]):
        return False
    if not all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(a[2], b[2], strict=True)):
        return False
    return all(
        la == lb and va.shape == vb.shape and torch.equal(va, vb)
        for (la, va), (lb, vb) in zip(a[3], b[3], strict=True)
    )


class SharedColumns:
    """The kept ``[J r]`` chunks of one point: ``blocks`` (their columns in order, then
    ``r``), built under ``sigmas`` on ``data``'s rows in chunks of ``chunk_rows``."""

    def __init__(self, problem: Problem) -> None:
        self.point = model_point(problem.model)
        self.data = weakref.ref(problem.data)
        self.cond, self.weights = problem.cond, problem.row_weights
        self.sigmas = (problem.sigma_pos_mm, problem.sigma_rot_rad)
        self.per_row = 3 if problem.R_meas is None else 6
        self.chunk_rows = problem.chunk_rows
        self.blocks: list[ParamBlock] = []
        self.chunks: list[Tensor] = []

    def serves(self, problem: Problem) -> bool:
        """Whether ``problem`` is at this point, on the same rows and row weights."""
        if self.data() is not problem.data or self.cond is not problem.cond:
            return False
        if (self.weights is None) != (problem.row_weights is None):
            return False
        if self.weights is not None and not torch.equal(self.weights, problem.row_weights):
            return False
        return problem.extra is None and same_point(self.point, model_point(problem.model))

    def where(self) -> dict[str, tuple[int, int]]:
        """``label -> (first column, size)`` of the kept blocks."""
        out, start = {}, 0
        for b in self.blocks:
            out[b.label] = (start, b.size)
            start += b.size
        return out

    def extend(self, problem: Problem, blocks: list[ParamBlock]) -> None:
        """Add the columns of ``blocks`` (parameters of ``problem.model``), built at this
        point: each chunk becomes ``[J_kept J_new r]`` (one chunk copied at a time)."""
        sub = Problem(
            problem.model, problem.data, problem.cond, tuple(blocks), *self.sigmas,
            row_weights=self.weights, chunk_rows=self.chunk_rows, progress=problem.progress,
        )  # fmt: skip
        for i, M in enumerate(sub.augmented_chunks(torch.zeros_like(sub.x0))):
            if i < len(self.chunks):
                self.chunks[i] = torch.cat([self.chunks[i][:, :-1], M], 1)
            else:
                self.chunks.append(M)
        self.blocks += blocks

    def gathered(self, problem: Problem) -> Iterator[Tensor]:
        """``[J r]`` chunks of ``problem``'s blocks under its noise levels (copies, but
        the kept chunks themselves where they are exactly that: read-only)."""
        where = self.where()
        idx = [torch.arange(where[b.label][0], where[b.label][0] + b.size) for b in problem.blocks]
        idx.append(torch.tensor([sum(b.size for b in self.blocks)]))
        cols = torch.cat(idx)
        every = cols.numel() == self.chunks[0].shape[1] and bool(
            torch.equal(cols, torch.arange(cols.numel()))
        )  # all kept columns in order: no copy
        to_pos = self.sigmas[0] / problem.sigma_pos_mm  # columns and residuals: 1 / sigma
        to_rot = self.sigmas[1] / problem.sigma_rot_rad
        same = to_pos == 1.0 and to_rot == 1.0
        for M in self.chunks:
            if every and same:
                yield M
                continue
            G = M[:, cols]
            if not same:
                n_c = M.shape[0] // self.per_row
                G[: 3 * n_c] *= to_pos
                G[3 * n_c :] *= to_rot
            yield G


# The kept point of each thread (one at a time: the next point's columns replace it;
# two diagnoses in two threads keep theirs apart), dropped with its rows.
_KEPT: dict[int, SharedColumns] = {}


def _forget(thread: int, entry_id: int) -> None:
    if id(_KEPT.get(thread)) == entry_id:
        _KEPT.pop(thread, None)


def release_shared() -> None:
    """Drop this thread's kept point (its questions are all asked: the model moved on)."""
    _KEPT.pop(threading.get_ident(), None)


def shared_chunks(problem: Problem) -> tuple[Iterator[Tensor], SharedColumns]:
    """``[J r]`` chunks of ``problem`` at its model's values (``theta = 0``): read from
    the kept point where it is the same, the missing columns computed and kept with
    them; else the kept point is replaced by this one. Returns the chunks (under the
    problem's noise levels, one at a time) and the kept point (every column there, for
    a refit to step with: :class:`~hybrid_pk.calibration.chord.Linearisation`)."""
    thread = threading.get_ident()
    entry = _KEPT.get(thread)
    if entry is None or not entry.serves(problem):
        _KEPT.pop(thread, None)
        entry = SharedColumns(problem)  # the old one's memory free before this one's is taken
        weakref.finalize(problem.data, _forget, thread, id(entry))
        _KEPT[thread] = entry
    have = entry.where()
    missing = [b for b in problem.blocks if b.label not in have]
    if any(have[b.label][1] != b.size for b in problem.blocks if b.label in have):
        raise ValueError("a block's size differs from the kept column's at the same point")
    # the columns read are counted as if built here (the work budget bounds what a stage
    # asks, not what an earlier one left ready: the same stages run either way)
    read = problem.x0.numel() - sum(b.size for b in missing)
    if missing or not entry.chunks:
        entry.extend(problem, missing)  # counts its rows and the missing columns
        count_work(problem.data.n * read)
    else:
        count_work(problem.data.n, read)
    return entry.gathered(problem), entry

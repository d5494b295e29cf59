"""The weighted least-squares problem of a fit: residuals and their structured Jacobian.

Residuals per measured pose: position difference [mm] and the small-angle rotation
difference ``vee(E - E^T) / 2`` (``E = R_meas R_model^T``, = ``sin(angle) · axis``)
[rad], each divided by its noise level so that mm and rad weigh by their evidence,
and by an optional weight per row. Parameters are offsets in units of their block's
``scale`` (1 mm, 1 mrad, 1 µrad/Nm, …) so that the normal equations are well
conditioned.

Rows are processed in chunks, so that the Jacobian of 250,000 rows and 100
parameters never exists at once: :meth:`Problem.normal_equations` (for LM) and
:meth:`Problem.r_factor` (the triangular factor of ``[J r]``, for score tests and
covariances) reduce chunk by chunk.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.structured_jacobian import StructuredJacobian
from hybrid_pk.calibration.twists import residual_columns
from hybrid_pk.calibration.work import count as count_work
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import quat_to_matrix

__all__ = ["ParamBlock", "Problem", "param_blocks"]


@dataclass(frozen=True)
class ParamBlock:
    """One fitted parameter tensor: module path, report label, size, scale, unit."""

    name: str
    label: str
    size: int
    scale: float
    unit: str


def param_blocks(
    model: ExtendedModel, free: Sequence[str] | None, position_only: bool
) -> tuple[ParamBlock, ...]:
    """The parameter blocks of ``model`` to fit: frames first, then every effect.

    Args:
        free: labels (an effect's ``label``, ``kind:joint``, or ``"base_frame.rotation"``)
            or module paths of the blocks to keep; ``None`` keeps all.
        position_only: drop the tool rotation (unobservable from points).
    """
    blocks = []
    frames = {
        "base.dp": ("base_frame.translation", "m"),
        "base.rotvec": ("base_frame.rotation", "rad"),
        "tool.dp": ("tool_frame.translation", "m"),
        "tool.rotvec": ("tool_frame.rotation", "rad"),
    }
    for name, (label, unit) in frames.items():
        if position_only and name == "tool.rotvec":
            continue  # the tool's orientation is unobservable from points
        blocks.append(ParamBlock(name, label, 3 * model.base.sets, model.base.scale, unit))
    for i, e in enumerate(model.effects):
        blocks.append(ParamBlock(f"effects.{i}.value", e.label, e.value.numel(), e.scale, e.unit))
    if free is not None:
        wanted = {free} if isinstance(free, str) else set(free)
        known = {x for b in blocks for x in (b.label, b.name)} | set(frames)
        known |= {label for label, _ in frames.values()}  # tool rotation dropped: no error
        if wanted - known:
            raise HybridPKError(
                f"free: {', '.join(sorted(wanted - known))} not in this model; its blocks: "
                + ", ".join(b.label for b in blocks)
            )
        blocks = [b for b in blocks if b.label in wanted or b.name in wanted]
    return tuple(blocks)


# Memory of one chunk's Jacobian work [bytes]: twists, columns and their copies.
CHUNK_BYTES = 96 * 2**20
# At most one progress message per this many seconds from inside a Jacobian.
PROGRESS_INTERVAL_S = 2.0


class Problem:
    """The weighted least-squares problem of fitting ``blocks`` of ``model`` to ``data``.

    ``residual(theta)`` maps the scaled parameter offsets ``theta`` (zero = the model's
    current values) to noise-normalised residuals: ``3 N`` position [mm / sigma_pos]
    then, with orientation data, ``3 N`` rotation [rad / sigma_rot], then the rows of
    ``extra``.

    Args:
        row_weights: ``(N,)`` weight of each row's residuals (robust fits); None = 1.
        extra: ``theta -> (r_extra (p,), J_extra (p, n))``, residual rows appended to
            the data's (priors, constraints), in the same scaled units.
        chunk_rows: rows per chunk (default: from :data:`CHUNK_BYTES`).
        progress: called with a short text at most every few seconds while a
            Jacobian is built.
    """

    def __init__(
        self,
        model: ExtendedModel,
        data: MeasuredData,
        cond: Conditions,
        blocks: tuple[ParamBlock, ...],
        sigma_pos_mm: float,
        sigma_rot_rad: float,
        *,
        row_weights: Tensor | None = None,
        extra: Callable[[Tensor], tuple[Tensor, Tensor]] | None = None,
        chunk_rows: int | None = None,
        progress: Callable[[str], None] | None = None,
    ) -> None:
        self.model, self.data, self.cond, self.blocks = model, data, cond, blocks
        self.sigma_pos_mm, self.sigma_rot_rad = sigma_pos_mm, sigma_rot_rad
        self.params = dict(model.named_parameters())
        dtype = model.robot.dtype
        self.x0 = torch.cat(
            [torch.zeros(0, dtype=dtype)]
            + [self.params[b.name].detach().reshape(-1) for b in blocks]
        )
        self.scale = torch.cat(
            [torch.zeros(0, dtype=dtype)]
            + [torch.full((b.size,), b.scale, dtype=dtype) for b in blocks]
        )
        self.R_meas = None if data.quat is None else quat_to_matrix(data.quat)
        self.row_weights = None if row_weights is None else row_weights.to(dtype)
        self.extra = extra
        n_par = self.x0.numel()
        per_row = 8 * (6 * 4 * max(n_par, 1) + 800)
        self.chunk_rows = chunk_rows or max(256, CHUNK_BYTES // per_row)
        self.progress = progress
        self._structure = StructuredJacobian(model, blocks)
        self._last_message = time.monotonic()
        self.kept: list[Tensor] | None = None  # a list: every data chunk built goes in
        # set where ``kept`` came from elsewhere (a shared point): its blocks, noise levels
        self.kept_blocks: tuple[ParamBlock, ...] | None = None
        self.kept_sigmas: tuple[float, float] | None = None

    @property
    def n_residuals(self) -> int:
        """Residual count ``m``: 3 or 6 per row, and the extra rows."""
        per_row = 3 if self.R_meas is None else 6
        n_extra = 0 if self.extra is None else int(self.extra(torch.zeros_like(self.x0))[0].numel())
        return per_row * self.data.n + n_extra

    def _chunks(self) -> Iterator[slice]:
        for start in range(0, self.data.n, self.chunk_rows):
            yield slice(start, min(start + self.chunk_rows, self.data.n))

    def unpack(self, theta: Tensor) -> dict[str, Tensor]:
        values, start = {}, 0
        for b in self.blocks:
            chunk = self.x0[start : start + b.size] + theta[start : start + b.size] * b.scale
            values[b.name] = chunk.reshape(self.params[b.name].shape)
            start += b.size
        return values

    def residual(self, theta: Tensor) -> Tensor:
        """``(m,)`` noise-normalised residuals at scaled offsets ``theta``."""
        values = self.unpack(theta)
        pos, rot = [], []
        count_work(self.data.n)
        for rows in self._chunks():
            args = (self.data.q[rows], self.cond.subset(rows))
            T = torch.func.functional_call(self.model, values, args)
            p, r = self._residual_parts(T, rows)
            pos.append(p)
            rot.append(r)
        out = [torch.cat(pos).reshape(-1)]
        if self.R_meas is not None:
            out.append(torch.cat(rot).reshape(-1))
        if self.extra is not None:
            out.append(self.extra(theta)[0])
        return torch.cat(out)

    def residual_of_pose(self, T: Tensor) -> Tensor:
        """Noise-normalised residuals of predicted poses ``T (N, 4, 4)`` (no extra rows)."""
        p, r = self._residual_parts(T, slice(None))
        return p.reshape(-1) if r is None else torch.cat([p.reshape(-1), r.reshape(-1)])

    def _residual_parts(self, T: Tensor, rows: slice) -> tuple[Tensor, Tensor | None]:
        """``(n, 3)`` position and rotation residuals of the chunk ``rows``."""
        w = None if self.row_weights is None else self.row_weights[rows, None]
        pos = (self.data.position[rows] - T[:, :3, 3]) * (1000.0 / self.sigma_pos_mm)
        pos = pos if w is None else pos * w
        if self.R_meas is None:
            return pos, None
        E = self.R_meas[rows] @ T[:, :3, :3].transpose(-1, -2)
        vee = torch.stack(
            [E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], -1
        )
        rot = (0.5 / self.sigma_rot_rad) * vee
        return pos, rot if w is None else rot * w

    @contextmanager
    def _at(self, theta: Tensor) -> Iterator[None]:
        """The model's parameters at ``theta`` for the duration of the block."""
        saved = {k: v.detach().clone() for k, v in self.params.items()}
        self.write(theta)
        try:
            yield
        finally:
            with torch.no_grad():
                for k, v in saved.items():
                    self.params[k].copy_(v)

    def linearised_chunks(self, theta: Tensor) -> Iterator[tuple[Tensor, Tensor]]:
        """``(r_c, J_c)`` residuals and Jacobian rows chunk by chunk at ``theta`` (rows
        of a chunk in an order of their own; the ``extra`` rows come last)."""
        for M in self.augmented_chunks(theta):
            yield M[:, -1], M[:, :-1]

    def augmented_chunks(self, theta: Tensor) -> Iterator[Tensor]:
        """``[J_c r_c]`` chunk by chunk at ``theta``, as :meth:`linearised_chunks`
        (each chunk written into one buffer, not concatenated)."""
        with self._at(theta):
            for rows in self._chunks():
                M = self._chunk_rows(rows)
                if self.kept is not None and self.kept_blocks is None:  # not a shared point's
                    self.kept.append(M)
                yield M
                self._report(rows.stop)
        if self.extra is not None:
            r_x, J_x = self.extra(theta)
            yield torch.cat([J_x, r_x[:, None]], 1)

    def _chunk_rows(self, rows: slice) -> Tensor:
        key = (self.data.q, rows.start, rows.stop)
        pt = self._structure.pose_twists(self.data.q[rows], self.cond.subset(rows), key)
        pos, rot = self._residual_parts(pt.T, rows)
        E = None
        if self.R_meas is not None:
            E = self.R_meas[rows] @ pt.T[:, :3, :3].transpose(-1, -2)
        w = None if self.row_weights is None else self.row_weights[rows]
        n_rows, n = pt.twists.shape[0], pt.twists.shape[-1]
        count_work(rows.stop - rows.start, n)
        if torch.is_grad_enabled() and pt.twists.requires_grad:  # out= records no derivative
            cols = residual_columns(pt.twists, E, self.sigma_pos_mm, self.sigma_rot_rad, w)
            J = torch.cat([c.reshape(-1, n) for c in cols if c is not None])
            r = torch.cat([p.reshape(-1) for p in (pos, rot) if p is not None])
            return torch.cat([J, r[:, None]], 1)
        M = pt.twists.new_empty((3 if rot is None else 6) * n_rows, n + 1)
        out = [M[: 3 * n_rows, :n].view(n_rows, 3, n), None]
        M[: 3 * n_rows, n] = pos.reshape(-1)
        if rot is not None:
            out[1] = M[3 * n_rows :, :n].view(n_rows, 3, n)
            M[3 * n_rows :, n] = rot.reshape(-1)
        residual_columns(pt.twists, E, self.sigma_pos_mm, self.sigma_rot_rad, w, out=out)
        return M

    def _report(self, done: int) -> None:
        if self.progress is None:
            return
        now = time.monotonic()
        if now - self._last_message >= PROGRESS_INTERVAL_S:
            self._last_message = now
            self.progress(f"Jacobian rows {done:,}/{self.data.n:,}")

    def jacobian(self, theta: Tensor) -> tuple[Tensor, Tensor]:
        """Residual ``(m,)`` and Jacobian ``(m, n)`` at ``theta``, rows as in
        :meth:`residual` (the whole Jacobian in memory: small problems only)."""
        pos_r, rot_r, pos_j, rot_j = [], [], [], []
        with self._at(theta):
            for rows in self._chunks():
                M = self._chunk_rows(rows)
                r_c, J_c = M[:, -1], M[:, :-1]
                n_pos = 3 * (rows.stop - rows.start)
                pos_r.append(r_c[:n_pos])
                pos_j.append(J_c[:n_pos])
                rot_r.append(r_c[n_pos:])
                rot_j.append(J_c[n_pos:])
        if self.extra is not None:
            r_x, J_x = self.extra(theta)
            rot_r.append(r_x)
            rot_j.append(J_x)
        return torch.cat(pos_r + rot_r), torch.cat(pos_j + rot_j)

    def normal_equations(self, theta: Tensor) -> tuple[Tensor, Tensor, float]:
        """``J^T J (n, n)``, ``J^T r (n,)`` and ``r^T r`` at ``theta``, by chunks."""
        n = self.x0.numel()
        A = torch.zeros(n, n, dtype=self.x0.dtype)
        g = torch.zeros(n, dtype=self.x0.dtype)
        cost = 0.0
        for r_c, J_c in self.linearised_chunks(theta):
            A.addmm_(J_c.T, J_c)
            g.addmv_(J_c.T, r_c)
            cost += float(r_c @ r_c)
        return A, g, cost

    def r_factor(self, theta: Tensor) -> Tensor:
        """Upper-triangular ``R`` of ``[J r] = Q R`` at ``theta``, ``(<= n + 1, n + 1)``.

        Its columns are an isometric image of ``J``'s and ``r``'s: every norm, inner
        product and projection among them is the same on ``R`` as on the ``m`` rows.
        """
        R = None
        for M in self.augmented_chunks(theta):
            if R is not None:
                M = torch.cat([R, M], 0)
            R = torch.linalg.qr(M, mode="r").R
        return R

    @torch.no_grad()
    def write(self, theta: Tensor) -> None:
        """Store ``theta`` into the model's parameters."""
        for name, v in self.unpack(theta).items():
            self.params[name].copy_(v)


def subset_rows(n: int, max_rows: int) -> Tensor:
    """Indices of an even subset of at most ``max_rows`` of ``n`` rows."""
    return torch.arange(0, n, max(1, -(-n // max_rows)))


def subset_jacobian(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    blocks: tuple,
    max_rows: int,
) -> tuple[Tensor, Tensor, MeasuredData, Conditions]:
    """``(r, J, sub, cond_sub)``: residual and Jacobian [mm and mrad per scaled unit]
    of ``blocks`` at their start, on an even subset ``sub`` (conditions ``cond_sub``)
    of at most ``max_rows`` rows."""
    rows = subset_rows(data.n, max_rows)
    sub, cond_sub = data.subset(rows), cond.subset(rows)
    problem = Problem(model, sub, cond_sub, blocks, 1.0, 1e-3)  # mm and mrad
    r, J = problem.jacobian(torch.zeros_like(problem.x0))
    return r, J, sub, cond_sub

"""The z-aligned chain: forward kinematics without derivatives, batch last.

Every joint frame turned so that its axis is its z axis: with ``Q_i`` a rotation whose
third column is the unit axis ``a_i``, ``O_i Rot(a_i, q) = O_i Q_i Rot_z(q) Q_i^T``, and
``Q_i^T`` moves into the next origin. Then ``P_0 = B_0``, ``P_i = P_{i-1} X_i(q_{i-1})``,
``T = P_n`` with constant ``B_i = Q_{i-1}^T O_i Q_i`` (``B_n`` the tip) and ``X_i =
Rot_z(q) B_i`` (revolute: two rows of ``B_i`` mixed by ``cos q`` and ``sin q``) or
``Trans_z(q) B_i`` (prismatic: ``q`` added to row 2's translation). ``P_i`` is the frame of
joint ``i`` itself (third column its axis, fourth its origin). Frames are batch-last and
column-major, ``(4 columns, 3 rows, M)``: a column is one ``(3, M)`` block.

Used where no derivative is wanted and many configurations are evaluated at once: the
pose and the frames after each joint of :class:`~hybrid_pk.robot.Robot` (its own
parameters, or an extended model's shared ones: :class:`AlignedFK`) and the IK kernel
(:mod:`hybrid_pk.robot.kernel`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.robot.chain import ChainTerms, KinematicParams, plain_inputs

__all__ = [
    "ALIGNED_MIN_BATCH",
    "AlignedChain",
    "AlignedFK",
    "aligned_chain",
    "aligned_fk",
    "aligned_frames",
    "aligned_pose",
]


class AlignedChain(NamedTuple):
    """Constants of the z-aligned chain (no gradients): ``first (4, 3, 1)`` the frame
    ``B_0``, ``rows`` the three rows of ``B_1 .. B_n``, each ``(n, 4, 1, 1)``, and
    ``e3 (n, 4, 1, 1)`` the unit row of the translation column."""

    first: Tensor
    rows: tuple[Tensor, Tensor, Tensor]
    e3: Tensor


def _axis_frames(axis: Tensor) -> Tensor:
    """Homogeneous rotations ``(n, 4, 4)`` whose third column is the unit ``axis``."""
    a = axis / axis.norm(dim=-1, keepdim=True)
    helper = torch.zeros_like(a)  # the coordinate axis least aligned with a
    helper.scatter_(-1, a.abs().argmin(-1, keepdim=True), 1.0)
    x = helper - (helper * a).sum(-1, keepdim=True) * a
    x = x / x.norm(dim=-1, keepdim=True)
    Q = a.new_zeros(a.shape[0], 4, 4)
    Q[:, :3, :3] = torch.stack([x, torch.linalg.cross(a, x), a], -1)
    Q[:, 3, 3] = 1.0
    return Q


def _after_joints(terms: ChainTerms) -> Tensor:
    """``(n, 4, 4)``: the inverses of ``O_{i+1} Q_{i+1}`` (``i < n - 1``) and of the tip
    (``i = n - 1``) of shared, unfolded ``terms``, that take the aligned frames of
    :func:`aligned_frames` back to the frames after each joint."""
    with torch.no_grad():
        Q = _axis_frames(terms.axis)
        M = torch.cat([terms.M0[1:] @ Q[1:], terms.tip[None]])
        R_t = M[:, :3, :3].transpose(-1, -2)
        inv = torch.zeros_like(M)
        inv[:, :3, :3] = R_t
        inv[:, :3, 3] = -(R_t @ M[:, :3, 3:])[..., 0]
        inv[:, 3, 3] = 1.0
        return inv


def aligned_chain(
    terms: ChainTerms, base: Tensor | None = None, tool: Tensor | None = None
) -> AlignedChain:
    """The z-aligned constants of shared (unbatched) ``terms``, with an optional base
    ``(4, 4)`` before the chain and tool ``(4, 4)`` after the tip folded in."""
    with torch.no_grad():
        O, tip = terms.M0.clone(), terms.tip
        if base is not None:
            O[0] = base.to(O) @ O[0]
        if tool is not None:
            tip = tip @ tool.to(tip)
        Q = _axis_frames(terms.axis)
        B = torch.cat([O @ Q, tip[None]])  # (n + 1, 4, 4)
        B[1:] = Q.transpose(-1, -2) @ B[1:]
        e3 = B.new_zeros(B.shape[0] - 1, 4, 1, 1)
        e3[:, 3] = 1.0
        rows = tuple(B[1:, r, :, None, None].contiguous() for r in range(3))
        return AlignedChain(B[0, :3].T[..., None].contiguous(), rows, e3)


def _in_dtype(C: AlignedChain, dtype: torch.dtype) -> AlignedChain:
    """``C``'s constants cast to ``dtype`` (``C`` itself when already in it)."""
    if C.first.dtype == dtype:
        return C
    return AlignedChain(C.first.to(dtype), tuple(r.to(dtype) for r in C.rows), C.e3.to(dtype))


def _motion(C: AlignedChain, qt: Tensor, revolute: Tensor, all_revolute: bool):
    """Rows ``(k, 4, 1, M)`` of ``X`` for chain joint values ``qt (k, M)`` (``C``'s rows
    and ``revolute`` already cut to the same ``k`` joints)."""
    b0, b1, b2 = C.rows
    q4 = qt[:, None, None]  # (k, 1, 1, M)
    c, s = torch.cos(q4), torch.sin(q4)
    if not all_revolute:
        rev = revolute[:, None, None, None]
        c, s = torch.where(rev, c, 1.0), torch.where(rev, s, 0.0)
        b2 = torch.addcmul(b2, torch.where(rev, 0.0, q4), C.e3)
    return torch.mul(c, b0).addcmul_(s, b1, value=-1), torch.mul(s, b0).addcmul_(c, b1), b2


def aligned_frames(C: AlignedChain, qt: Tensor, revolute: Tensor, all_revolute: bool) -> Tensor:
    """Joint frames ``P (n + 1, 4, 3, M)`` at chain joint values ``qt (n, M)``:
    ``P[i, 2]`` the axis and ``P[i, 3]`` the origin of joint ``i < n``, ``P[n]`` the end
    pose (``P[n, :3]`` its rotation, transposed)."""
    n, M = qt.shape
    x0, x1, x2 = (x.unbind(0) for x in _motion(C, qt, revolute, all_revolute))
    P = qt.new_empty(n + 1, 4, 3, M)
    P[0] = C.first
    # every frame and every column (1, 3, M) as views made once: a view costs as much to
    # make as a small operation, and a call makes ~40 of them
    frames, columns = P.unbind(0), P.view(4 * (n + 1), 1, 3, M).unbind(0)
    for i in range(1, n + 1):
        p0, p1, p2, origin = columns[4 * i - 4 : 4 * i]
        out = torch.mul(x0[i - 1], p0, out=frames[i])
        out.addcmul_(x1[i - 1], p1).addcmul_(x2[i - 1], p2)
        columns[4 * i + 3].add_(origin)
    return P


def aligned_pose(C: AlignedChain, qt: Tensor, revolute: Tensor, all_revolute: bool) -> Tensor:
    """End pose ``(4, 3, M)`` (column-major, batch-last) at ``qt (n, M)``; one joint's
    motion at a time, so the working set stays a few frames whatever ``n``."""
    P = C.first
    for i in range(qt.shape[0]):
        sl = slice(i, i + 1)
        one = AlignedChain(C.first, tuple(r[sl] for r in C.rows), C.e3[sl])
        x0, x1, x2 = (x[0] for x in _motion(one, qt[sl], revolute[sl], all_revolute))
        p0, p1, p2, p3 = P[:, None].unbind(0)
        nxt = torch.mul(x0, p0).addcmul_(x1, p1).addcmul_(x2, p2)
        nxt[3] += p3[0]
        P = nxt
    return P.expand(4, 3, qt.shape[1])


# Batch size from which aligned_fk beats the balanced product of Robot.fk: below it the
# per-joint loop's ~10 operations per joint cost more than log2(n) batched 4x4 matmuls.
# bench/fk_layouts.py (ur10, rx160, float32/64, one thread): tree/align 0.6-0.8 at
# 256-512 configurations, 1.4-1.6 at 1000.
ALIGNED_MIN_BATCH = 1000


def aligned_fk(C: AlignedChain, q: Tensor, revolute: Tensor, all_revolute: bool) -> Tensor:
    """End pose ``(*B, 4, 4)`` at chain joint values ``q (*B, n)`` by :func:`aligned_pose`
    (constants ``C`` in ``q``'s dtype)."""
    qt = q.reshape(-1, q.shape[-1]).T
    P = aligned_pose(C, qt, revolute, all_revolute)  # (4 columns, 3 rows, M)
    T = q.new_empty(qt.shape[1], 4, 4)
    T[:, :3] = P.permute(2, 1, 0)
    T[:, 3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=q.dtype, device=q.device)
    return T.view(*q.shape[:-1], 4, 4)


def _applies(terms: ChainTerms, q: Tensor) -> bool:
    """Whether the z-aligned path serves ``terms`` at ``q``: enough configurations
    (:data:`ALIGNED_MIN_BATCH`), shared terms and no derivatives through either."""
    if q[..., 0].numel() < ALIGNED_MIN_BATCH or terms.M0.dim() > 3:
        return False
    return plain_inputs(q, terms.M0, terms.tip, terms.axis)


class AlignedFK:
    """:meth:`Robot.fk`'s path without derivatives: the z-aligned chain (built in float64
    from the robot's shared chain terms, cast, kept per dtype while the terms object,
    renewed on every parameter change, stays the same), from ``ALIGNED_MIN_BATCH``
    configurations on."""

    def __init__(self, revolute: Tensor) -> None:
        self.revolute, self.all_revolute = revolute, bool(revolute.all())
        self._memo: dict[torch.dtype, tuple[ChainTerms, AlignedChain]] = {}

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_memo": {}}  # never pickle cached tensors

    def constants(self, terms: ChainTerms, dtype: torch.dtype) -> AlignedChain:
        memo = self._memo.get(dtype)
        if memo is None or memo[0] is not terms:
            memo = (terms, _in_dtype(aligned_chain(terms), dtype))
            self._memo[dtype] = memo
        return memo[1]

    def with_params(self, terms: ChainTerms, q: Tensor) -> Tensor | None:
        """End pose ``(*B, 4, 4)`` at chain joint values ``q (*B, n)`` of shared (unbatched)
        chain ``terms`` built from parameters other than the robot's own (an extended
        model's), or None where this path does not apply (few configurations, per-sample
        terms, or derivatives)."""
        if not _applies(terms, q):
            return None
        return aligned_fk(_in_dtype(aligned_chain(terms), q.dtype), q, self.revolute,
                          self.all_revolute)  # fmt: skip

    def link_frames(self, terms: ChainTerms, q: Tensor) -> Tensor | None:
        """:meth:`Robot.link_frames` ``(*B, n + 1, 4, 4)`` at chain joint values ``q (*B,
        n)`` of shared, unfolded chain ``terms``, or None where this path does not apply
        (as :meth:`with_params`). The frame after joint ``i`` is the aligned frame of the
        next joint before it turns, ``P_{i+1} = F_i O_{i+1} Q_{i+1}`` (the tip in place of
        ``O_n Q_n``), times that constant's inverse."""
        if not _applies(terms, q):
            return None
        n = q.shape[-1]
        C, after = _in_dtype(aligned_chain(terms), q.dtype), _after_joints(terms)
        qt = q.reshape(-1, n).T
        P = aligned_frames(C, qt, self.revolute, self.all_revolute)  # (n + 1, 4, 3, M)
        F = torch.einsum("ikrm,ikc->icrm", P[1:, :3], after[:, :3].to(q.dtype))
        F[:, 3] += P[1:, 3]  # (n, 4 columns, 3 rows, M)
        out = q.new_empty(qt.shape[1], n + 1, 4, 4)
        out[:, :n, :3] = F.permute(3, 0, 2, 1)
        out[:, n, :3] = P[n].permute(2, 1, 0)
        out[:, :, 3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=q.dtype, device=q.device)
        return out.view(*q.shape[:-1], n + 1, 4, 4)

    def __call__(self, robot, q: Tensor, params: KinematicParams | None = None) -> Tensor | None:
        """End pose ``(*B, 4, 4)`` of ``robot`` (or of its chain with shared ``params``)
        at chain joint values ``q (*B, n)``, or None where this path does not apply (few
        configurations, per-sample parameters, or derivatives)."""
        if params is not None:
            if params.origin_xyz.dim() > 2:
                return None
            return self.with_params(robot.chain_terms(q.dtype, params), q)
        own = (q, robot.origin_xyz, robot.origin_rotvec, robot.axis)
        if q[..., 0].numel() < ALIGNED_MIN_BATCH or not plain_inputs(*own):
            return None
        C = self.constants(robot.chain_terms(torch.float64), q.dtype)
        return aligned_fk(C, q, self.revolute, self.all_revolute)

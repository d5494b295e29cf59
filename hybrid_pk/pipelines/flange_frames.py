"""Base and tool frames fitted to fixed flange poses: the frames of any model whose
flange pose does not depend on them (an extended model, a hybrid: the networks correct
the flange in robot coordinates), each fitted the same way.

``T_meas = B · E · X``: with the flange poses ``E (n, 4, 4)`` fixed, only ``B`` and ``X``
move. Levenberg-Marquardt on the residuals of
:class:`~hybrid_pk.calibration.problem.Problem` (position [mm] over its noise, the
small-angle rotation [rad] over its noise), from given frames; a frame's component the
data do not determine (the tool rotation on position-only data, a base-tool trade-off
of one flange orientation) stays where it starts, held by the damping.

:func:`fit_flange_frames` fits one frame set; :func:`held_out_errors` predicts every row
with frames fitted without it (leave one out, or folds beyond :data:`MAX_FOLDS` rows).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.calibration.least_squares import levenberg_marquardt
from hybrid_pk.geometry import skew, so3_exp, so3_left_jacobian, transform, vee_antisym

__all__ = [
    "BLOCKS",
    "MAX_FOLDS",
    "FlangeRows",
    "fit_flange_frames",
    "fold_of_rows",
    "frames_at",
    "held_out_errors",
]

# Folds of the held-out prediction: leave one out up to this many rows, this many folds
# beyond. Each fold's frames are then fitted on at least 98 % of the rows (as the final
# fit's, on all of them), and the cost stays that of 50 small fits.
MAX_FOLDS = 50
# Iterations of one fit: a frames-only fit from nearby frames converges in a few.
_MAX_ITER = 50
# Units of the fitted offsets: translations in mm, rotations in mrad (well conditioned).
_MM, _MRAD = 1e-3, 1e-3
# Blocks of the 12 offsets, in order (the labels of calibration.fit).
BLOCKS = (
    "base_frame.translation",
    "base_frame.rotation",
    "tool_frame.translation",
    "tool_frame.rotation",
)


@dataclass(frozen=True)
class FlangeRows:
    """Rows to fit frames to: flange poses ``E (n, 4, 4)`` in the robot root frame,
    measured points ``position (n, 3)`` [m] and rotations ``R_meas (n, 3, 3)`` (None:
    position only), the noise levels that weigh them and the rows' robust weights
    ``(n,)`` (None: all 1), which scale their squared residuals."""

    E: Tensor
    position: Tensor
    R_meas: Tensor | None
    sigma_mm: float
    sigma_rad: float
    weights: Tensor | None = None

    @property
    def n(self) -> int:
        return self.E.shape[0]

    def predict(self, B: Tensor, X: Tensor) -> Tensor:
        """``(n, 4, 4)`` predicted measured poses with frames ``B``, ``X``."""
        return B @ self.E @ X

    def residual(self, theta: Tensor, B0: Tensor, X0: Tensor, rows: Tensor) -> Tensor:
        """Noise-normalised residuals of ``rows`` at offsets ``theta (12,)`` from ``B0``,
        ``X0``."""
        B, X = frames_at(theta, B0, X0)
        T = B @ self.E[rows] @ X
        w = 1.0 if self.weights is None else self.weights[rows, None].to(T.dtype).sqrt()
        pos = (self.position[rows] - T[:, :3, 3]) * (1e3 / self.sigma_mm) * w
        if self.R_meas is None:
            return pos.reshape(-1)
        D = self.R_meas[rows] @ T[:, :3, :3].transpose(-1, -2)
        vee = vee_antisym(D)
        return torch.cat([pos.reshape(-1), ((0.5 / self.sigma_rad) * vee * w).reshape(-1)])

    def jacobian(
        self, theta: Tensor, B0: Tensor, X0: Tensor, rows: Tensor
    ) -> tuple[Tensor, Tensor]:
        """:meth:`residual` ``(m,)`` at ``theta`` and its Jacobian ``(m, 12)``, in closed
        form (forward mode through the residual took torch's slow reference path at
        every product with a constant: a fit ~5 times the time).

        With ``T = B E X``, ``B = (exp(w_b) R_B0, p_B0 + t_b)``, ``X = (R_X0 exp(w_x),
        p_X0 + t_x)``: the point moves by ``dt_b``, ``-[R_B v]x J_l(w_b) dw_b`` (``v`` the
        tool point in the base) and ``R_B R_E dt_x``; ``D = R_meas R^T`` turns by
        ``-D [a]x`` (base, ``a = J_l(w_b) dw_b``) or ``-[c]x D`` (tool, ``c = R_meas
        J_r(w_x) dw_x``), so ``vee(D - D^T)`` by ``-(tr D - D^T) a`` or ``-(tr D - D) c``."""
        r = self.residual(theta, B0, X0, rows)
        B, X = frames_at(theta, B0, X0)
        E = self.E[rows]
        n, dt = E.shape[0], theta.dtype
        w = torch.ones(n, dtype=dt) if self.weights is None else self.weights[rows].to(dt).sqrt()
        k_pos = -(1e3 / self.sigma_mm) * w[:, None, None]  # residual = measured - predicted
        v = E[:, :3, :3] @ X[:3, 3] + E[:, :3, 3]  # the tool point in the base's frame
        J_lb = so3_left_jacobian(theta[3:6] * _MRAD) * _MRAD
        J_rx = so3_left_jacobian(-theta[9:12] * _MRAD) * _MRAD
        RBE = B[:3, :3] @ E[:, :3, :3]
        pos = torch.zeros(n, 3, 12, dtype=dt)
        pos[:, :, 0:3] = torch.eye(3, dtype=dt) * _MM
        pos[:, :, 3:6] = -skew(v @ B[:3, :3].T) @ J_lb
        pos[:, :, 6:9] = RBE * _MM
        J = [(k_pos * pos).reshape(-1, 12)]
        if self.R_meas is not None:
            R_meas = self.R_meas[rows]
            D = R_meas @ (RBE @ X[:3, :3]).transpose(-1, -2)
            trace = D.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=dt)
            rot = torch.zeros(n, 3, 12, dtype=dt)
            rot[:, :, 3:6] = -(trace - D.transpose(-1, -2)) @ J_lb
            rot[:, :, 9:12] = -(trace - D) @ R_meas @ J_rx
            J.append(((0.5 / self.sigma_rad) * w[:, None, None] * rot).reshape(-1, 12))
        return r, torch.cat(J)


def frames_at(theta: Tensor, B0: Tensor, X0: Tensor) -> tuple[Tensor, Tensor]:
    """Frames at offsets ``theta`` = base translation [mm], base rotation [mrad] (in the
    measurement frame), tool translation [mm], tool rotation [mrad] (in the tool frame)."""
    B = transform(so3_exp(theta[3:6] * _MRAD) @ B0[:3, :3], B0[:3, 3] + theta[0:3] * _MM)
    X = transform(X0[:3, :3] @ so3_exp(theta[9:12] * _MRAD), X0[:3, 3] + theta[6:9] * _MM)
    return B, X


def fit_flange_frames(
    rows: FlangeRows, B0: Tensor, X0: Tensor, free: tuple[str, ...], subset: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Frames ``(B, X)`` fitted to ``rows`` (or the boolean ``subset`` of them), the
    ``free`` blocks of :data:`BLOCKS` moved from ``B0``, ``X0``."""
    idx = torch.arange(rows.n) if subset is None else torch.nonzero(subset).reshape(-1)
    cols = [i for i, b in enumerate(BLOCKS) if b in free and _moves(rows, b)]
    if not cols or idx.numel() == 0:
        return B0, X0
    mask = torch.zeros(12, dtype=torch.bool)
    for i in cols:
        mask[3 * i : 3 * i + 3] = True

    def full(t_free: Tensor) -> Tensor:  # the 12 offsets, the fixed blocks at 0
        return torch.zeros(12, dtype=rows.E.dtype).masked_scatter(mask, t_free)

    def res(t_free: Tensor) -> Tensor:
        return rows.residual(full(t_free), B0, X0, idx)

    def jac(t_free: Tensor) -> tuple[Tensor, Tensor]:
        r, J = rows.jacobian(full(t_free), B0, X0, idx)
        return r, J[:, mask]

    start = torch.zeros(int(mask.sum()), dtype=rows.E.dtype)
    x = levenberg_marquardt(res, start, max_iter=_MAX_ITER, jac=jac).x
    B, X = frames_at(full(x), B0, X0)
    return B.detach(), X.detach()


def _moves(rows: FlangeRows, block: str) -> bool:
    """Whether the data see ``block``: the tool rotation only through orientations."""
    return block != BLOCKS[3] or rows.R_meas is not None


def fold_of_rows(n: int) -> tuple[Tensor, int]:
    """``(n,)`` fold of each row and the number of folds: one row each up to
    :data:`MAX_FOLDS` rows (leave one out), else rows dealt in turn to that many folds."""
    folds = min(n, MAX_FOLDS)
    return torch.arange(n) % folds, folds


def held_out_errors(
    rows: FlangeRows, B0: Tensor, X0: Tensor, free: tuple[str, ...], group: Tensor | None = None
) -> Tensor:
    """``(n, 4, 4)`` predicted poses of every row with frames fitted without its fold
    (:func:`fold_of_rows`; each frame set ``group`` fitted on its own rows, ``B0``, ``X0``
    ``(G, 4, 4)`` the starts)."""
    fold, folds = fold_of_rows(rows.n)
    group = torch.zeros(rows.n, dtype=torch.long) if group is None else group
    T = torch.empty_like(rows.E)
    for f in range(folds):
        held = fold == f
        for g in torch.unique(group[held]).tolist():
            B, X = fit_flange_frames(rows, B0[g], X0[g], free, (~held) & (group == g))
            out = held & (group == g)
            T[out] = B @ rows.E[out] @ X
    return T

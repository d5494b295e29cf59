"""Closed-form initial guesses of the base and tool frames.

Measured poses satisfy ``T_meas_i ≈ B · F_i · X`` with ``F_i`` the model's flange pose,
``B = T_meas_root`` (where the tracker stands) and ``X = T_end_point`` (where the
target sits on the flange). Least-squares fits start from these guesses so that they
never start in a wrong basin (a tracker can stand anywhere, at any yaw).

- Full poses: ``R_meas_i R_meas_j^T = R_B (R_F_i R_F_j^T) R_B^T``, so the rotation
  vectors of the relative rotations satisfy ``a_ij = R_B b_ij`` (hand-eye, solved by
  Kabsch); then ``R_X`` is the chordal mean of ``R_F_i^T R_B^T R_meas_i`` and the two
  translations follow from one linear least-squares problem.
- Positions only: alternate a Kabsch fit of ``R_B, p_B`` (with the current flange
  offset ``p_X``) and a linear fit of ``p_B, p_X`` (with ``R_B`` fixed).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry.rotations import nearest_rotation, so3_log, transform

__all__ = ["kabsch", "register_frames"]


def kabsch(a: Tensor, b: Tensor, with_translation: bool = True) -> tuple[Tensor, Tensor]:
    """Rotation ``R`` and translation ``p`` minimising ``sum |R a_i + p - b_i|^2``.

    Args:
        a, b: ``(N, 3)`` corresponding points (or directions, ``with_translation=False``).
    """
    if with_translation:
        ca, cb = a.mean(0), b.mean(0)
    else:
        ca = cb = torch.zeros(3, dtype=a.dtype)
    R = nearest_rotation((b - cb).T @ (a - ca))
    return R, cb - R @ ca


def _pairs(n: int, generator: torch.Generator, count: int = 2000) -> tuple[Tensor, Tensor]:
    i = torch.randint(0, n, (count,), generator=generator)
    j = torch.randint(0, n, (count,), generator=generator)
    keep = i != j
    return i[keep], j[keep]


# Ridge on the tool translation, relative to the mean information of the translations:
# it only keeps the solve regular where the flange orientation never varies at all.
TOOL_RIDGE = 1e-6
# Prior std of the tool translation around the end link's origin [m]: tracker targets
# and tool points sit within a few decimetres of the flange.
TOOL_STD_M = 0.1


def _held_tool(A2: Tensor, n: int, residual_rms_m: float, tool_std_m: float) -> Tensor:
    """``(3, k)``: the tool-translation directions the data determine (columns).

    After the base translation has compensated what it can (Schur complement), a
    direction ``u`` of the tool moves the points by ``s`` m per m (rms per row). An
    unmodelled error as large as the residual rms ``e``, which no row count averages
    away when it is systematic, moves the tool along ``u`` by ``e / s``; where that
    exceeds the prior's ``tool_std_m`` the data do not determine ``u`` and the tool
    stays at the end link's origin along it.
    """
    H = A2.T @ A2
    S = H[3:, 3:] - H[:3, 3:].T @ torch.linalg.solve(H[:3, :3], H[:3, 3:])
    lam, U = torch.linalg.eigh(S / n)
    sens = lam.clamp_min(0).sqrt()
    return U[:, sens * tool_std_m > residual_rms_m]


def _translations(A: Tensor, rhs: Tensor, tool_std_m: float = TOOL_STD_M) -> Tensor:
    """``(p_B, p_X)`` from ``A (N, 3, 6) x = rhs (N, 3)``; the tool translation's
    directions the data do not determine (:func:`_held_tool`) stay at zero."""
    n = A.shape[0]
    A2, b = A.reshape(-1, 6), rhs.reshape(-1)
    H = A2.T @ A2
    ridge = torch.zeros(6, dtype=H.dtype)
    ridge[3:] = TOOL_RIDGE * float(H.diagonal().mean())
    sol = torch.linalg.solve(H + torch.diag(ridge), A2.T @ b)
    rms = float((b - A2 @ sol).reshape(n, 3).pow(2).sum(1).mean().sqrt())
    Q = _held_tool(A2, n, rms, tool_std_m)
    if Q.shape[1] == 3:
        return sol
    M = torch.cat([A2[:, :3], A2[:, 3:] @ Q], 1)
    part = torch.linalg.lstsq(M, b[:, None]).solution[:, 0]
    return torch.cat([part[:3], Q @ part[3:]])


# Below this largest relative flange rotation [rad] the hand-eye rotation is noise.
MIN_ROTATION_SPREAD = 0.05


def register_frames(
    T_end: Tensor,
    position: Tensor,
    quat_rot: Tensor | None = None,
    iterations: int = 20,
) -> tuple[Tensor, Tensor]:
    """Initial ``T_meas_root`` and ``T_end_point``, each ``(4, 4)``.

    Args:
        T_end: ``(N, 4, 4)`` model flange poses in the robot root frame [m].
        position: ``(N, 3)`` measured points in the measurement frame [m].
        quat_rot: ``(N, 3, 3)`` measured orientations, or None for position-only data.
        iterations: alternations of the position-only solver.
    """
    n = position.shape[0]
    if n < 3:
        raise HybridPKError(f"frame registration needs at least 3 poses, found {n}")
    R_F, p_F = T_end[:, :3, :3], T_end[:, :3, 3]
    gen = torch.Generator().manual_seed(0)
    if quat_rot is not None:
        i, j = _pairs(n, gen)
        a = so3_log(quat_rot[i] @ quat_rot[j].transpose(-1, -2))
        b = so3_log(R_F[i] @ R_F[j].transpose(-1, -2))
        if float(b.norm(dim=-1).max()) < MIN_ROTATION_SPREAD:
            # The flange never turns (e.g. ISO 9283 cube poses): relative rotations are
            # noise. Register the points instead; the tool rotation follows from R_B.
            base, tool = register_frames(T_end, position, None, iterations)
            R_X = nearest_rotation((R_F.transpose(-1, -2) @ base[:3, :3].T @ quat_rot).sum(0))
            return base, transform(R_X, tool[:3, 3])
        R_B, _ = kabsch(b, a, with_translation=False)
        R_X = nearest_rotation((R_F.transpose(-1, -2) @ R_B.T @ quat_rot).sum(0))
        # p_meas - R_B p_F = p_B + (R_B R_F) p_X : linear in (p_B, p_X)
        A = torch.cat([torch.eye(3, dtype=p_F.dtype).expand(n, 3, 3), R_B @ R_F], -1)
        sol = _translations(A, position - p_F @ R_B.T)
        return transform(R_B, sol[:3]), transform(R_X, sol[3:])
    p_X = torch.zeros(3, dtype=p_F.dtype)
    A_cols = None
    for _ in range(iterations):
        R_B, p_B = kabsch(p_F + (R_F @ p_X[:, None])[..., 0], position)
        A_cols = torch.cat([torch.eye(3, dtype=p_F.dtype).expand(n, 3, 3), R_B @ R_F], -1)
        sol = _translations(A_cols, position - p_F @ R_B.T)
        p_B, p_X = sol[:3], sol[3:]
    eye = torch.eye(3, dtype=p_F.dtype)
    return transform(R_B, p_B), transform(eye, p_X)

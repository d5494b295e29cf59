"""Analytic IK branches from EAIK, the oracle that numerical solutions are checked against.

EAIK (``pip install eaik``, a test/bench extra) solves 6R arms whose axes allow a
subproblem decomposition (the RX160's spherical wrist, the UR10's three parallel
axes) in closed form. The EAIK robot is built here from the chain itself (joint axes
and axis points in the zero configuration, and the end link's rotation there), not
from the URDF, so both sides use the very same geometry; :func:`eaik_robot` checks its
forward kinematics against ours before it is trusted.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hybrid_pk.errors import HybridPKError
from hybrid_pk.ik.dedup import REVOLUTE_TOL
from hybrid_pk.robot import Robot

__all__ = ["branch_coverage", "eaik_branches", "eaik_robot"]

# An EAIK solution counts as exact when its pose error is below these [m], [rad].
_EXACT_POSITION = 1e-8
_EXACT_ROTATION = 1e-8


def eaik_robot(robot: Robot, check: int = 16):
    """EAIK robot with the geometry of ``robot`` (all-revolute 6-DOF chains).

    Args:
        robot: the chain; its current kinematic parameters are used.
        check: number of random configurations on which EAIK's forward kinematics must
            match ``robot.fk`` to 1e-9 m / 1e-9.

    Raises:
        HybridPKError: eaik is missing, the chain is not 6R, EAIK knows no
            decomposition for it, or its forward kinematics disagrees.
    """
    try:
        import eaik.pybindings.EAIK as EAIK
    except ImportError as exc:  # pragma: no cover - eaik is a dev extra
        raise HybridPKError("analytic IK needs eaik: pip install eaik") from exc
    if robot.dof != 6 or not bool(robot.revolute.all()):
        raise HybridPKError(f"EAIK needs a 6R arm; {robot.name} has joints {robot.joint_types}")
    with torch.no_grad():
        frames = robot.link_frames(torch.zeros(robot.dof, dtype=torch.float64)).numpy()
        a = robot.axis.detach().to(torch.float64)
        a = (a / a.norm(dim=-1, keepdim=True)).numpy()
    H = np.stack([frames[i, :3, :3] @ a[i] for i in range(6)])
    points = np.vstack([np.zeros(3), frames[:, :3, 3]])  # root, joint points, end link
    P = np.diff(points, axis=0)  # (7, 3) offsets between successive axis points
    eaik = EAIK.Robot(H.T, P.T, frames[6, :3, :3], [], True)
    if not eaik.has_known_decomposition():
        raise HybridPKError(f"EAIK has no closed-form decomposition for {robot.name}")
    q = robot.sample_q(check, torch.Generator().manual_seed(0))
    with torch.no_grad():
        T = robot.fk(q).numpy()
    worst = max(
        float(np.abs(eaik.fwdkin(qi) - Ti).max()) for qi, Ti in zip(q.numpy(), T, strict=True)
    )
    if worst > 1e-9:
        raise HybridPKError(f"EAIK forward kinematics differs from {robot.name}'s by {worst:.1e}")
    return eaik


def _wrap(q: np.ndarray) -> np.ndarray:
    return (q + math.pi) % (2 * math.pi) - math.pi


def eaik_branches(robot: Robot, targets: torch.Tensor, eaik=None) -> list[np.ndarray]:
    """Exact analytic solutions of each target that have a representative within limits.

    Args:
        robot: the chain (6R).
        targets: ``(N, 4, 4)`` poses of the end link in the root frame [m].
        eaik: an :func:`eaik_robot` of ``robot`` (built when omitted).

    Returns:
        ``N`` arrays ``(n_i, 6)`` of distinct branches [rad] wrapped to ``[-pi, pi)``:
        least-squares (inexact) EAIK answers are dropped, and so are branches with no
        ``q + 2 pi k`` inside the joint limits; branches are deduplicated with the
        contract's rule (1e-3 rad modulo 2 pi).
    """
    eaik = eaik or eaik_robot(robot)
    lower = robot.lower.detach().numpy()
    upper = robot.upper.detach().numpy()
    T = targets.detach().to(torch.float64).reshape(-1, 4, 4).numpy()
    out = []
    for sol, Tt in zip(eaik.calculate_IK_batched(list(T), 1), T, strict=True):
        kept: list[np.ndarray] = []
        for q in np.asarray(sol.Q).reshape(-1, 6):
            Tq = eaik.fwdkin(q)
            if np.linalg.norm(Tq[:3, 3] - Tt[:3, 3]) > _EXACT_POSITION:
                continue
            if np.abs(Tq[:3, :3] - Tt[:3, :3]).max() > _EXACT_ROTATION:
                continue
            w = _wrap(q)
            # Some w + 2 pi k within the limits, joint by joint (k in -2..2 covers +-4 pi).
            shifts = w[:, None] + 2 * math.pi * np.arange(-2, 3)[None, :]
            inside = (shifts >= lower[:, None] - 1e-12) & (shifts <= upper[:, None] + 1e-12)
            if not inside.any(-1).all():
                continue
            if any(np.abs(_wrap(w - k)).max() <= REVOLUTE_TOL for k in kept):
                continue
            kept.append(w)
        out.append(np.array(kept).reshape(-1, 6))
    return out


def branch_coverage(
    found: list[np.ndarray], reference: list[np.ndarray], tol: float = REVOLUTE_TOL
) -> tuple[int, int, list[tuple[int, np.ndarray]]]:
    """How many reference branches some found solution matches (modulo 2 pi).

    Args:
        found: per target ``(k_i, dof)`` solutions [rad].
        reference: per target ``(n_i, dof)`` branches [rad].
        tol: largest wrapped joint difference of a match [rad].

    Returns:
        ``(matched, total, missed)`` with ``missed`` the ``(target, branch)`` pairs.
    """
    matched, total, missed = 0, 0, []
    for i, (f, ref) in enumerate(zip(found, reference, strict=True)):
        f = np.asarray(f).reshape(-1, ref.shape[-1] if ref.size else 6)
        for b in ref:
            total += 1
            if len(f) and (np.abs(_wrap(f - b)).max(-1) <= tol).any():
                matched += 1
            else:
                missed.append((i, b))
    return matched, total, missed

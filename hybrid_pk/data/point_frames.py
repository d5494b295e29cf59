"""Base frame and tool point registered on positions: ``p ≈ R_B (R_F p_X + p_F) + p_B``.

``R_F, p_F``: the nominal flange poses of the rows; ``R_B, p_B``: the robot base in the
tracker frame; ``p_X``: the measured point on the flange [m]. Used by the time-offset
search (:mod:`hybrid_pk.data.time_offset`) and the clock-jump test
(:mod:`hybrid_pk.data.clock_jump`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["PointFrames"]


class PointFrames:
    """Least-squares base frame and tool point from positions: ``p ≈ R_B (R_F p_X + p_F) + p_B``.

    Gauss-Newton from a closed-form registration, warm-started at each call so the
    residual is the converged least-squares value (a smooth function of the offset).
    """

    def __init__(self, T_end: torch.Tensor, pose: tuple[np.ndarray, ...]) -> None:
        """Frames on flange poses ``T_end (K, 4, 4)`` starting at ``pose = (R_B, p_B, p_X)``."""
        T = T_end.double().numpy()
        self.R_F, self.p_F = T[:, :3, :3], T[:, :3, 3]
        self.R_B, self.p_B, self.p_X = (np.array(x, dtype=np.float64) for x in pose)

    @classmethod
    def from_guess(cls, T_end: torch.Tensor, guess: tuple[torch.Tensor, torch.Tensor]):
        """Frames starting at ``guess = (T_base (4, 4), T_tool (4, 4))``."""
        base, tool = (g.double().numpy() for g in guess)
        return cls(T_end, (base[:3, :3], base[:3, 3], tool[:3, 3]))

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The starting ``(R_B, p_B, p_X)``."""
        return self.R_B, self.p_B, self.p_X

    def points(self, R_B: np.ndarray, p_B: np.ndarray, p_X: np.ndarray) -> np.ndarray:
        """``(K, 3)`` model points [m] in the tracker frame."""
        return (np.einsum("kij,j->ki", self.R_F, p_X) + self.p_F) @ R_B.T + p_B

    def jacobian(self, R_B: np.ndarray, p_X: np.ndarray) -> np.ndarray:
        """``(K, 3, 9)`` d(points) / (base rotation ``w`` in ``R_B <- exp(w) R_B``,
        ``p_B``, ``p_X``)."""
        b = (np.einsum("kij,j->ki", self.R_F, p_X) + self.p_F) @ R_B.T
        J = np.zeros((len(b), 3, 9))
        J[:, 0, 1], J[:, 0, 2] = b[:, 2], -b[:, 1]  # -[b]x
        J[:, 1, 0], J[:, 1, 2] = -b[:, 2], b[:, 0]
        J[:, 2, 0], J[:, 2, 1] = b[:, 1], -b[:, 0]
        J[:, :, 3:6] = np.eye(3)
        J[:, :, 6:9] = R_B @ self.R_F
        return J

    @staticmethod
    def update(R_B, p_B, p_X, step: np.ndarray):
        """``(R_B, p_B, p_X)`` moved by a step of the first 9 unknowns of :meth:`jacobian`."""
        w = step[:3]
        angle = float(np.linalg.norm(w))
        if angle > 0:
            K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / angle
            R_B = (np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K) @ R_B
        return R_B, p_B + step[3:6], p_X + step[6:9]

    def fit(self, p: np.ndarray, iterations: int = 8):
        """Converged ``(R_B, p_B, p_X)`` for measured points ``p (K, 3)`` [m]."""
        R_B, p_B, p_X = self.R_B.copy(), self.p_B.copy(), self.p_X.copy()
        for _ in range(iterations):
            r = self.points(R_B, p_B, p_X) - p
            Jf = self.jacobian(R_B, p_X).reshape(-1, 9)
            step = -np.linalg.solve(Jf.T @ Jf, Jf.T @ r.reshape(-1))
            R_B, p_B, p_X = self.update(R_B, p_B, p_X, step)
            if float(np.abs(step).max()) < 1e-12:
                break
        return R_B, p_B, p_X

    def rms_mm(self, p: np.ndarray, iterations: int = 8) -> float:
        r = self.points(*self.fit(p, iterations)) - p
        return 1e3 * math.sqrt(float((r * r).sum(-1).mean()))

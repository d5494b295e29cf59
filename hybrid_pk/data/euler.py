"""Which Euler sequence a column of three angles uses, decided on the data.

The reference is a rotation of the same poses in other frames (e.g. the flange
orientation from the joint angles). The pairwise angle ``angle(R_i^T R_j)`` is
invariant to the unknown base and tool frames, but also to transposing every
rotation: it cannot tell intrinsic ``XYZ`` from extrinsic ``zyx`` fed the same three
numbers. So each candidate is ranked by the residual after fitting the constant
frames, ``R_i ≈ A R_ref_i B`` [deg RMS]; the pairwise residual is reported beside it.
:mod:`hybrid_pk.data.ipa` gives the results on the published UR10 data.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hybrid_pk.geometry import nearest_rotation

__all__ = [
    "EULER_SEQUENCES",
    "ConventionScore",
    "EulerDetection",
    "describe_sequence",
    "detect_euler_convention",
]

_AXES = ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx", "xyx", "xzx", "yxy", "yzy", "zxz", "zyz")
EULER_SEQUENCES = _AXES + tuple(s.upper() for s in _AXES)  # extrinsic, then intrinsic
# Sequences whose fits differ by less than this (relative) are indistinguishable.
_TIE_RTOL = 1e-7


def describe_sequence(seq: str) -> str:
    """E.g. ``"intrinsic 'XYZ' (R = Rx(a) Ry(b) Rz(c))"`` for angles ``(a, b, c)``."""
    factors = [f"R{axis.lower()}({angle})" for axis, angle in zip(seq, "abc", strict=True)]
    if seq.islower():  # extrinsic: later rotations multiply from the left
        return f"extrinsic {seq!r} (R = {' '.join(reversed(factors))})"
    return f"intrinsic {seq!r} (R = {' '.join(factors)})"


@dataclass(frozen=True)
class ConventionScore:
    """How well one Euler sequence explains the data.

    Attributes:
        sequence: scipy sequence (lower case extrinsic, upper case intrinsic).
        fit_deg: RMS angle [deg] between ``R_i`` and ``A R_ref_i B`` with fitted
            constant rotations ``A`` (base) and ``B`` (tool).
        pair_deg: RMS difference [deg] of ``angle(R_i^T R_j)`` and
            ``angle(R_ref_i^T R_ref_j)`` over random pairs (frame invariant).
    """

    sequence: str
    fit_deg: float
    pair_deg: float


@dataclass(frozen=True)
class EulerDetection:
    """Result of :func:`detect_euler_convention`; ``scores`` is sorted best first."""

    convention: str
    scores: tuple[ConventionScore, ...]
    equivalent: tuple[str, ...]  # fit exactly as well as ``convention`` (frames absorb them)

    @property
    def best(self) -> ConventionScore:
        """Score of ``convention``."""
        return next(s for s in self.scores if s.sequence == self.convention)

    @property
    def runner_up(self) -> ConventionScore:
        """Best score of a sequence that is not equivalent to ``convention``."""
        return next(s for s in self.scores if s.sequence not in self.equivalent)

    def summary(self) -> str:
        """One line: winner, its residual and the runner-up's."""
        b, r = self.best, self.runner_up
        return (
            f"{describe_sequence(b.sequence)}: {b.fit_deg:.4g} deg RMS; "
            f"runner-up {r.sequence!r}: {r.fit_deg:.4g} deg"
        )


def _polar(S: np.ndarray) -> np.ndarray:
    """Rotation nearest to ``S`` (3, 3)."""
    return nearest_rotation(torch.from_numpy(S)).numpy()


def _fit_frames(
    R: np.ndarray, G: np.ndarray, left: np.ndarray | None, i: np.ndarray, j: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit ``R_n ≈ A G_n B``; returns ``A`` (or ``left``), ``B`` and the angles [rad] left."""
    Rt, Gt = R.transpose(0, 2, 1), G.transpose(0, 2, 1)
    if left is None:
        # R_i R_j^T = A (G_i G_j^T) A^T: the rotation axes of relative rotations are
        # turned by A (Kabsch on rotation vectors), whatever B is.
        m = Rotation.from_matrix(R[i] @ Rt[j]).as_rotvec()
        g = Rotation.from_matrix(G[i] @ Gt[j]).as_rotvec()
        A = _polar(m.T @ g)
    else:
        A = np.asarray(left, dtype=np.float64)
    for _ in range(5):  # block coordinate descent on sum ||R_n - A G_n B||^2
        B = _polar(np.tensordot(G, A.T @ R, axes=([0, 1], [0, 1])))  # sum G_n^T A^T R_n
        if left is not None:
            break
        A = _polar(np.tensordot(R, G @ B, axes=([0, 2], [0, 2])))  # sum R_n B^T G_n^T
    return A, B, _angle(Rt @ A @ G @ B)


def _angle(R: np.ndarray) -> np.ndarray:
    """Rotation angles [rad] of ``(N, 3, 3)`` matrices, accurate near 0 and pi."""
    vee = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]])
    return np.arctan2(np.linalg.norm(vee, axis=0) / 2, (np.trace(R, axis1=1, axis2=2) - 1) / 2)


def detect_euler_convention(
    angles: np.ndarray,
    reference: np.ndarray,
    *,
    degrees: bool = True,
    left: np.ndarray | None = None,
    candidates: Sequence[str] = EULER_SEQUENCES,
    n_pairs: int = 4000,
    seed: int = 0,
) -> EulerDetection:
    """Find the Euler sequence under which ``angles`` match ``reference`` rotations.

    Each candidate is scored by the residual after fitting constant base and tool
    rotations (``R_i ≈ A R_ref_i B``); the frame-invariant pairwise-angle residual is
    reported too. Sequences that fit equally well cannot be told apart by any data
    (constant frames absorb an axis relabelling); among them the one whose axes follow
    the angle columns (x, y, z) wins, then the order of ``candidates``.

    Args:
        angles: ``(N, 3)`` Euler angles, in column order.
        reference: ``(N, 3, 3)`` rotations of the same poses in other frames.
        degrees: whether ``angles`` are in degrees (else radians).
        left: known constant rotation ``A`` (3, 3); None fits it.
        candidates: scipy sequences to try.
        n_pairs: random row pairs for the pairwise test and the initial ``A``.
        seed: seed of the pair sampling.
    """
    angles = np.asarray(angles, dtype=np.float64)
    G = np.asarray(reference, dtype=np.float64)
    if angles.ndim != 2 or angles.shape[1] != 3 or G.shape != (len(angles), 3, 3):
        raise ValueError(
            f"need (N, 3) angles and (N, 3, 3) rotations, got {angles.shape}, {G.shape}"
        )
    if len(angles) < 3:
        raise ValueError("need at least 3 poses to detect an Euler convention")
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, len(angles), size=(2, n_pairs))
    i, j = i[i != j], j[i != j]
    ref_pair = _angle(G[i].transpose(0, 2, 1) @ G[j])
    scores = []
    for seq in candidates:
        R = Rotation.from_euler(seq, angles, degrees=degrees).as_matrix()
        pair = _angle(R[i].transpose(0, 2, 1) @ R[j]) - ref_pair
        fit = _fit_frames(R, G, left, i, j)[2]
        rms = [float(np.degrees(np.sqrt(np.mean(x**2)))) for x in (fit, pair)]
        scores.append(ConventionScore(seq, *rms))
    best = min(s.fit_deg for s in scores)
    tied = {s.sequence for s in scores if s.fit_deg <= best * (1 + _TIE_RTOL) + 1e-12}
    pos = {seq: k for k, seq in enumerate(candidates)}
    # Winner first, then its equivalents, then the rest by residual.
    scores.sort(
        key=lambda s: (
            (0, s.sequence.lower() != "xyz", pos[s.sequence])
            if s.sequence in tied
            else (1, s.fit_deg)
        )
    )
    equivalent = tuple(s.sequence for s in scores if s.sequence in tied)
    return EulerDetection(equivalent[0], tuple(scores), equivalent)

"""ISO 9283 pose accuracy (AP) and pose repeatability (RP) where poses repeat.

Rows whose commanded joints agree within a tolerance are visits of one pose
(:func:`group_repeated_poses`). For a pose visited ``n`` times with attained positions
``x_j`` (measured) and commanded position ``x_c`` (the model's prediction of that pose
in the measurement frame, e.g. a calibrated model, or nominal + fitted frames):

- barycentre ``x̄ = mean_j x_j``; position accuracy ``AP_P = |x̄ - x_c|`` with
  components ``AP_x, AP_y, AP_z = x̄ - x_c`` (ISO 9283 §7.2.1);
- ``l_j = |x_j - x̄|``, ``l̄ = mean_j l_j``, ``S_l = sqrt(sum (l_j - l̄)² / (n - 1))``;
  position repeatability ``RP_l = l̄ + 3 S_l`` (§7.2.2);
- orientation: ``a, b, c`` are the angles about the x, y, z axes of the measurement
  frame. Deviations are small, so they are taken as the components of the rotation
  vector ``log(R_j R_c^T)`` (the small-angle equivalent of the standard's angle
  differences): ``AP_a = mean_j a_j`` (and b, c), ``RP_a = ±3 S_a`` with ``S_a`` the
  sample standard deviation of ``a_j`` about its mean.

The standard asks for 30 cycles per pose; fewer give noisier RP (reported ``n``).
Without a commanded pose only RP is computed. With Gaussian noise of ``σ`` per
coordinate and nothing else, ``RP_l ≈ 3.6 σ`` and ``RP_a ≈ 3 σ_angle``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.distributions import chi2_ppf
from hybrid_pk.errors import DataError, ShapeError
from hybrid_pk.geometry import nearest_rotation, quat_to_matrix, so3_log

__all__ = ["ISO_CYCLES", "Iso9283Result", "expected_rp_mm", "group_repeated_poses", "iso9283"]

ISO_CYCLES = 30  # cycles per pose that ISO 9283 prescribes
# [rad, m] joints closer than this are one pose: above the rounding of logged encoder
# values (the shared UR10 series repeat poses within 2e-5 .. 7e-5 rad), far below the
# step between distinct poses of a campaign (> 0.1 rad there).
JOINT_TOLERANCE = 1e-4


def group_repeated_poses(q: Tensor | np.ndarray, tol: float = JOINT_TOLERANCE) -> np.ndarray:
    """Pose id per row: rows whose joints all agree within ``tol`` share an id.

    Args:
        q: ``(N, dof)`` commanded joint values [rad, m].
        tol: largest per-joint difference [rad, m] between visits of one pose.

    Returns:
        ``(N,)`` int ids ``0..P-1`` numbered in order of first visit; chains of close
        rows are one pose (connected components under the max-norm).
    """
    q_np = np.asarray(q.detach().cpu() if isinstance(q, Tensor) else q, dtype=np.float64)
    if q_np.ndim != 2:
        raise ShapeError(f"q must have shape (N, dof), found {q_np.shape}")
    n = len(q_np)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(q_np).query_pairs(r=tol, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    # renumber by first visit
    _, first = np.unique(labels, return_index=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[labels]


@dataclass(frozen=True)
class Iso9283Result:
    """Per-pose ISO 9283 figures and their summary.

    Attributes:
        poses: one row per repeated pose (columns below).
        pose_of_row: ``(N,)`` pose id of every input row (also single visits).
        has_accuracy: whether AP was computed (a commanded pose was given).
        has_orientation: whether orientation figures were computed.

    Columns of ``poses``: ``pose`` (id), ``n`` (visits), ``first_row`` (0-based index of
    the first visit), ``q_spread`` [rad] (largest joint difference between visits),
    ``x_mean, y_mean, z_mean`` [m] barycentre; with a commanded pose
    ``x_cmd, y_cmd, z_cmd`` [m], ``AP_p_mm, AP_x_mm, AP_y_mm, AP_z_mm``; always
    ``l_mean_mm, S_l_mm, RP_l_mm``; with orientation ``RP_a_deg, RP_b_deg, RP_c_deg``
    (±) and with a commanded pose ``AP_a_deg, AP_b_deg, AP_c_deg``; ``ss_mm2``,
    ``ss_deg2``: sums of squared deviations from the barycentre (pooled noise).

    The summary adds the pooled per-axis noise level ``sigma_pooled_mm`` (and
    ``_deg``) over all poses, ``sqrt(sum |x_j - x̄|² / (3 sum (n_p - 1)))``: the
    measurement + repeatability floor, well estimated even from 2 visits per pose,
    its outlier-robust twin ``sigma_robust_mm`` (median over poses, scaled by the
    chi-square median), and the ``RP_l`` the robust level implies for 30 cycles.
    """

    poses: pd.DataFrame
    pose_of_row: np.ndarray
    has_accuracy: bool
    has_orientation: bool

    def summary(self) -> dict[str, Any]:
        """JSON-ready: counts, and mean / max over poses of every figure."""
        p = self.poses
        out: dict[str, Any] = {
            "n_poses": len(p),
            "cycles": {"min": int(p["n"].min()), "max": int(p["n"].max())},
            "iso_cycles": ISO_CYCLES,
        }
        figures = ["RP_l_mm"]
        if self.has_accuracy:
            figures = ["AP_p_mm", *figures]
        if self.has_orientation:
            figures += ["RP_a_deg", "RP_b_deg", "RP_c_deg"]
            if self.has_accuracy:
                figures += ["AP_a_deg", "AP_b_deg", "AP_c_deg"]
        for name in figures:
            col = p[name].abs()
            out[name] = {"mean": float(col.mean()), "max": float(col.max())}
        dof = 3 * float((p["n"] - 1).sum())
        out["sigma_pooled_mm"] = float(np.sqrt(p["ss_mm2"].sum() / dof))
        if self.has_orientation:
            out["sigma_pooled_deg"] = float(np.sqrt(p["ss_deg2"].sum() / dof))
        # robust twin: median over poses of ss_p / median(chi2_k), k = 3 (n_p - 1)
        k = 3 * (p["n"].to_numpy() - 1)
        out["sigma_robust_mm"] = float(np.sqrt(np.median(p["ss_mm2"] / chi2_ppf(0.5, k))))
        out["RP_l_mm_expected_30_cycles"] = expected_rp_mm(out["sigma_robust_mm"])
        return out

    def lines(self) -> list[str]:
        """Human summary, one line per pose then the overall figures."""
        rows = []
        for _, r in self.poses.iterrows():
            text = f"pose {int(r['pose'])} (n={int(r['n'])}): RP {r['RP_l_mm']:.4f} mm"
            if self.has_accuracy:
                text = (
                    f"pose {int(r['pose'])} (n={int(r['n'])}): AP {r['AP_p_mm']:.4f} mm, "
                    f"RP {r['RP_l_mm']:.4f} mm"
                )
            if self.has_orientation:
                rp = ", ".join(f"{r[f'RP_{k}_deg']:.4f}" for k in "abc")
                text += f"; RP a,b,c ±({rp}) deg"
                if self.has_accuracy:
                    ap = ", ".join(f"{r[f'AP_{k}_deg']:+.4f}" for k in "abc")
                    text += f", AP a,b,c ({ap}) deg"
            rows.append(text)
        few = int((self.poses["n"] < ISO_CYCLES).sum())
        if few:
            rows.append(f"note: {few} pose(s) have fewer than the {ISO_CYCLES} cycles of ISO 9283")
        return rows


def _chordal_mean(R: Tensor) -> Tensor:
    """Rotation nearest to the mean of ``R (n, 3, 3)``."""
    return nearest_rotation(R.mean(0))


def iso9283(
    data: MeasuredData,
    T_command: Tensor | None = None,
    *,
    tol: float = JOINT_TOLERANCE,
    min_visits: int = 2,
) -> Iso9283Result:
    """ISO 9283 pose accuracy and repeatability of the repeated poses of ``data``.

    Args:
        data: measured rows (positions [m] and, if present, orientations).
        T_command: ``(N, 4, 4)`` commanded pose of every row in the measurement frame
            [m] (a model's prediction); None computes repeatability only.
        tol: joint tolerance [rad, m] of :func:`group_repeated_poses`.
        min_visits: poses visited fewer times are left out of the table.

    Raises:
        DataError: no pose is visited ``min_visits`` times.
        ShapeError: ``T_command`` of the wrong shape.
    """
    if min_visits < 2:
        raise ValueError(f"min_visits must be >= 2 (a spread needs two visits), got {min_visits}")
    if T_command is not None and tuple(T_command.shape) != (data.n, 4, 4):
        raise ShapeError(
            f"T_command must have shape ({data.n}, 4, 4), found {tuple(T_command.shape)}"
        )
    pose_of_row = group_repeated_poses(data.q, tol)
    ids, counts = np.unique(pose_of_row, return_counts=True)
    repeated = ids[counts >= min_visits]
    if repeated.size == 0:
        raise DataError(
            f"no commanded joint configuration is repeated {min_visits} times (tolerance "
            f"{tol:g} rad); ISO 9283 AP/RP need repeated poses",
            file=", ".join(data.sources),
        )
    R_meas = None if data.quat is None else quat_to_matrix(data.quat)
    records = []
    for pid in repeated:
        rows = torch.as_tensor(np.flatnonzero(pose_of_row == pid))
        x = data.position[rows]  # (n, 3) [m]
        bary = x.mean(0)
        l_mm = 1e3 * (x - bary).norm(dim=-1)
        n = len(rows)
        s_l = float(l_mm.std(unbiased=True))
        rec: dict[str, Any] = {
            "pose": int(pid),
            "n": n,
            "first_row": int(rows[0]),
            "q_spread": float((data.q[rows].max(0).values - data.q[rows].min(0).values).max()),
            "x_mean": float(bary[0]),
            "y_mean": float(bary[1]),
            "z_mean": float(bary[2]),
        }
        if T_command is not None:
            Tc = T_command[rows].to(torch.float64)
            x_c = Tc[:, :3, 3].mean(0)
            ap = 1e3 * (bary - x_c)
            rec.update(x_cmd=float(x_c[0]), y_cmd=float(x_c[1]), z_cmd=float(x_c[2]))
            rec.update(AP_p_mm=float(ap.norm()), AP_x_mm=float(ap[0]))
            rec.update(AP_y_mm=float(ap[1]), AP_z_mm=float(ap[2]))
        rec.update(l_mean_mm=float(l_mm.mean()), S_l_mm=s_l, RP_l_mm=float(l_mm.mean()) + 3 * s_l)
        rec["ss_mm2"] = float((l_mm**2).sum())  # for the pooled noise level
        if R_meas is not None:
            R = R_meas[rows]
            reference = _chordal_mean(R) if T_command is None else _chordal_mean(Tc[:, :3, :3])
            w = torch.rad2deg(so3_log(R @ reference.T))  # (n, 3) [deg] about x, y, z
            spread = w.std(0, unbiased=True)
            for k, axis in enumerate("abc"):
                rec[f"RP_{axis}_deg"] = 3 * float(spread[k])
                if T_command is not None:
                    rec[f"AP_{axis}_deg"] = float(w[:, k].mean())
            rec["ss_deg2"] = float(((w - w.mean(0)) ** 2).sum())
        records.append(rec)
    return Iso9283Result(
        pd.DataFrame.from_records(records), pose_of_row, T_command is not None, R_meas is not None
    )


def expected_rp_mm(sigma_mm: float, n: int = ISO_CYCLES) -> float:
    """Expected ``RP_l`` [mm] of ``n`` visits with isotropic Gaussian noise ``σ`` per axis.

    ``l_j`` is ``σ sqrt((n-1)/n)`` times a chi variable with 3 degrees of freedom:
    mean ``2 sqrt(2/π)``, standard deviation ``sqrt(3 - 8/π)``.
    """
    scale = sigma_mm * math.sqrt((n - 1) / n)
    return scale * (2 * math.sqrt(2 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi))

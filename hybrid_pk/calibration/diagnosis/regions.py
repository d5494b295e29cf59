"""The regions of joint space the blocked hold-out leaves out in turn (:mod:`.blocked`).

The fit rows are cut into contiguous regions along the joints that move the measured
point most (each row's angle times the joint's median lever, in metres of point
motion) by k-means, and, with several files, into whole files; the folds are the
regions (across files) and the files.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.blocked import Folds
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.effects import ExtendedModel

__all__ = ["KMEANS_STARTS", "joint_levers", "make_folds"]

# The regions are the tightest (least spread within regions) of this many k-means++
# starts: one start ends in a local minimum that depends on the seed, so the regions,
# and the causes judged on them, were the seed's rather than the data's; ten starts,
# the customary count, make one near the best all but certain.
KMEANS_STARTS = 10


def make_folds(model: ExtendedModel, split: Split, seed: int) -> Folds | None:
    """Regions of joint space and, with several files, whole files; None when the fit
    rows are too few for two regions and come from one file."""
    data = split.train
    files = data.file_index if len(data.sources) > 1 else torch.zeros(data.n, dtype=torch.long)
    n_files = int(files.max()) + 1 if data.n else 1
    tuning = diagnosis_tuning()
    k = min(tuning.region_blocks, data.n // tuning.min_block_rows)
    joints, region = [], torch.zeros(data.n, dtype=torch.long)
    if k >= 2:
        joints, x = _lever_coordinates(model, split)
        region = _kmeans(x, k, seed)
    else:
        k = 1
    folds = [tuple(f * k + r for f in range(n_files)) for r in range(k)] if k >= 2 else []
    if n_files > 1:
        folds += [tuple(f * k + r for r in range(k)) for f in range(n_files)]
    if not folds:
        return None
    names = model.robot.joint_names
    description = {
        "regions": k if k >= 2 else 0,
        "region_joints": [names[j] for j in joints],
        "files": n_files if n_files > 1 else 0,
        "linearised": True,
    }
    return Folds(files * k + region, n_files * k, tuple(folds), description)


@torch.no_grad()
def joint_levers(model: ExtendedModel, q: Tensor, cond) -> list[float]:
    """Per joint the median over the rows ``q`` of how far the measured point moves per
    radian (or metre) of that joint [m per unit]."""
    p0 = model(q, cond)[:, :3, 3]
    step = 1e-6  # [rad or m] finite-difference step of the point Jacobian
    levers = []
    for j in range(q.shape[1]):
        dq = torch.zeros_like(q)
        dq[:, j] = step
        p1 = model(q + dq, cond)[:, :3, 3]
        levers.append(float(((p1 - p0) / step).norm(dim=-1).median()))
    return levers


def _lever_coordinates(model: ExtendedModel, split: Split) -> tuple[list[int], Tensor]:
    """The joints that move the measured point most (the tuning's ``lever_share``) and
    each fit row's coordinates along them in metres (angle x median lever)."""
    data = split.train
    levers = joint_levers(model, data.q, split.cond_fit)
    top = max(levers)
    share = diagnosis_tuning().lever_share
    joints = [j for j, v in enumerate(levers) if v >= share * top and v > 0]
    x = torch.stack([data.q[:, j] * levers[j] for j in joints], 1)
    return joints, x


def _kmeans(x: Tensor, k: int, seed: int) -> Tensor:
    """Cluster index of each row of ``x``: the tightest (least within-cluster sum of
    squares) of ``KMEANS_STARTS`` k-means++ starts (seeded) with Lloyd iterations."""
    g = torch.Generator().manual_seed(seed)
    best, spread = None, math.inf
    for _ in range(KMEANS_STARTS):
        label = _lloyd(x, k, g)
        centres = torch.stack([x[label == i].mean(0) for i in range(int(label.max()) + 1)])
        within = float(((x - centres[label]) ** 2).sum())
        if within < spread:
            best, spread = label, within
    return best


def _lloyd(x: Tensor, k: int, g: torch.Generator) -> Tensor:
    """Cluster index of each row of ``x``: k-means++ start drawn from ``g``, Lloyd
    iterations; empty clusters dropped (consecutive indices)."""
    n = x.shape[0]
    centres = [x[int(torch.randint(n, (1,), generator=g))]]
    for _ in range(1, k):
        d = torch.cdist(x, torch.stack(centres)).min(1).values ** 2
        centres.append(x[int(torch.multinomial(d / d.sum().clamp_min(1e-300), 1, generator=g))])
    c = torch.stack(centres)
    for _ in range(diagnosis_tuning().kmeans_iterations):
        label = torch.cdist(x, c).argmin(1)
        c = torch.stack([x[label == i].mean(0) if (label == i).any() else c[i] for i in range(k)])
    label = torch.cdist(x, c).argmin(1)
    _, label = torch.unique(label, return_inverse=True)
    return label

"""Ambiguity: effects that the data cannot tell apart from a frame or from each other.

Four kinds, each an entry ``{"effects": [a, b], "why": ...}`` of the diagnosis (a
fifth, a candidate that named causes together stand in for: :mod:`.stand_ins`):

- a candidate whose signature lies inside what the fitted frames explain (no data of
  this kind can separate them);
- a chosen cause whose correction another candidate could make nearly as well;
- estimates whose correlation is close to +-1;
- a cyclic joint error whose neighbouring order would explain nearly as much
  (:mod:`.settle`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybrid_pk.calibration.covariance import MAX_CONDITION, parameter_names
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.calibration.problem import ParamBlock
from hybrid_pk.calibration.tuning import diagnosis_tuning

__all__ = [
    "correlated_groups",
    "equivalent_to_frame",
    "explained_fraction",
    "frame_of_equivalence",
    "near_duplicates",
    "projector_residual",
]


def projector_residual(Jc: Tensor, Q: Tensor) -> Tensor:
    """Columns ``Jc`` with their part in the span of orthonormal ``Q`` removed."""
    return Jc - Q @ (Q.T @ Jc)


def explained_fraction(v: Tensor, B: Tensor) -> float:
    """|cosine| between ``v`` and its projection on the column space of ``B``: how much
    of the correction ``v`` another candidate could make as well."""
    Qb, _ = torch.linalg.qr(B)
    return float((Qb.T @ v).norm() / v.norm().clamp_min(1e-300))


def frame_of_equivalence(Jc: Tensor, J_cur: Tensor, blocks: tuple[ParamBlock, ...]) -> str:
    """Which of base/tool frame (or which effect) explains a candidate's signature."""
    start, groups = 0, {}
    for b in blocks:
        key = b.label.split(".")[0]
        groups.setdefault(key, []).append(slice(start, start + b.size))
        start += b.size
    best, best_frac = "the fitted frames", math.inf
    for key, slices in groups.items():
        cols = torch.cat([J_cur[:, s] for s in slices], 1)
        Q, _ = torch.linalg.qr(cols)
        frac = float(projector_residual(Jc, Q).norm() ** 2 / Jc.norm().clamp_min(1e-300) ** 2)
        if frac < best_frac:
            best, best_frac = key, frac
    return best


def equivalent_to_frame(label: str, other: str, frac: float) -> dict:
    """Entry for a candidate that moves the pose exactly as ``other`` does."""
    return {
        "effects": [label, other],
        "why": f"{label} moves the measured pose exactly as {other} "
        f"does (signature {100 * (1 - frac):.4f} % inside it): "
        "no data of this kind can separate them, the fitted frame "
        "absorbs it",
    }


def near_duplicates(label: str, fitted: Tensor, signatures: dict[str, Tensor]) -> list[dict]:
    """Entries for the candidates whose signature could make ``label``'s correction
    ``fitted`` nearly as well (|cos| above the tuning's ``ambiguity_cosine``)."""
    out = []
    for other, Jo in signatures.items():
        if other == label:
            continue
        cos = explained_fraction(fitted, Jo)
        if cos > diagnosis_tuning().ambiguity_cosine:
            out.append(
                {
                    "effects": [label, other],
                    "why": f"signatures {100 * cos:.1f} % alike in this data "
                    f"(|cos| = {cos:.4f}); chose {label} by score, "
                    f"{other} would explain nearly as much",
                }
            )
    return out


def correlated_groups(res: FitResult) -> list[dict]:
    """Entries for strongly correlated estimates (frames included, frame pairs not).
    Where the two share a direction the data do not determine at all (a group of
    :meth:`FitResult.undetermined`, e.g. the components along parallel joint axes of
    two link lengths), the entry says only their combination is determined."""
    out, seen = [], set()
    group_of = dict(zip(*parameter_names(res.blocks), strict=True))  # name -> effect/frame
    exact = [g for g in res.undetermined(MAX_CONDITION) if len(g) > 1]
    for a, _, b, _, r in res.correlated_pairs(diagnosis_tuning().ambiguity_correlation):
        if (a, b) in seen or (a.endswith("_frame") and b.endswith("_frame")):
            continue
        seen.add((a, b))
        group = next((g for g in exact if {group_of[n] for n in g} >= {a, b}), None)
        why = (
            f"estimates correlated at {abs(r):.3f}: the data barely separates them, their "
            "values trade off"
        )
        if group is not None:
            why = (
                f"a combination of {', '.join(group)} moves nothing these data measure: "
                "only the combination is determined, the split between them (and their "
                "stds there) is the minimum-norm one, not a measurement"
            )
        out.append({"effects": [a, b], "why": why})
    return out

"""The parameter covariance of a fit from the SVD of its Jacobian, and the groups of
parameters its data cannot separate.

With the Jacobian's columns scaled to unit norm (``J D^-1 = U diag(s) V^T``; scaled
parameters, noise-weighted residuals) the covariance is ``s2 · D^-1 V diag(1/s²) V^T
D^-1`` over the singular values above the rank cut (below): a pseudo-inverse that
leaves out the directions the data do not determine at all. Built as ``W W^T`` with
``W = V / s`` it is positive semi-definite by construction, so every correlation (the
cosine of two rows of ``W``) lies in [-1, 1]. The pseudo-inverse of ``J^T J`` squares
the condition number instead; on an over-parameterised fit its rounding errors made it
indefinite (correlations of 1e148).

A group that cannot be separated is a set of parameters that move together along a
direction of the unit-column Jacobian whose singular value is below ``s_max /
max_condition``: the data change (almost) nothing when the group moves that way, so
only other combinations of its members are measured.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "MAX_CONDITION",
    "correlated_pairs",
    "determined",
    "parameter_names",
    "svd_covariance",
    "undetermined_groups",
]

# Above this condition number of the scaled identification Jacobian a fit is not
# identifiable from the data (well-posed calibrations here stay below 1e5).
MAX_CONDITION = 1e8


def parameter_names(blocks) -> tuple[list[str], list[str]]:
    """``(names, groups)`` of every scalar parameter of ``blocks`` in order: a name adds
    the component to the block label (``link_length:joint_3[2]``), a group is the label
    up to its first ``.`` (``base_frame``)."""
    names, groups = [], []
    for b in blocks:
        for k in range(b.size):
            names.append(f"{b.label}[{k}]" if b.size > 1 else b.label)
            groups.append(b.label.split(".")[0])
    return names, groups


def correlated_pairs(
    names: list[str], groups: list[str], corr: Tensor, threshold: float
) -> list[tuple[str, str, str, str, float]]:
    """``(group_a, name_a, group_b, name_b, r)`` of the parameter pairs of different
    groups correlated at ``|r| >= threshold`` or undetermined (NaN), in parameter order."""
    pairs = []
    for i in range(corr.shape[0]):
        for j in range(i + 1, corr.shape[0]):
            r = float(corr[i, j])
            if groups[i] != groups[j] and not abs(r) < threshold:
                pairs.append((groups[i], names[i], groups[j], names[j], r))
    return pairs


def determined(s: Tensor, n_obs: int, n_params: int) -> Tensor:
    """Which singular values ``s`` (descending, of a Jacobian with ``n_obs`` rows and
    ``n_params`` columns) are measurements: those above ``s_max · max(rows, parameters)
    · machine epsilon``, the level of the Jacobian's rounding errors (numpy's
    ``matrix_rank`` rule). Below it a direction is an exact degeneracy whose singular
    value is round-off, and changes with the order of any sum that built the Jacobian."""
    tiny = torch.finfo(s.dtype).tiny
    return s > (s[:1] * max(n_obs, n_params) * torch.finfo(s.dtype).eps).clamp_min(tiny)


def svd_covariance(J: Tensor, n_obs: int, s2: float) -> dict:
    """Covariance of the scaled parameters of Jacobian ``J (m, n)`` (or its R factor;
    ``n_obs`` rows in all) at residual variance ``s2``, from the SVD of ``J`` with
    unit-norm columns (so the result does not depend on the parameters' units).

    Returns ``cov``, ``corr`` (a parameter the data do not see at all has zero
    correlations), ``singular_values`` and ``singular_vectors`` ``(n, n)`` (rows) of the
    unit-column Jacobian."""
    tiny = torch.finfo(J.dtype).tiny
    norms = J.norm(dim=0).clamp_min(tiny)
    _, s, vh = torch.linalg.svd(J / norms, full_matrices=True)
    keep = determined(s, n_obs, J.shape[1])  # the rest is round-off: left out
    W = vh[: s.numel()][keep].T / s[keep]  # (n, rank), unit columns: cov = W W^T · s2
    unit = W / W.norm(dim=1, keepdim=True).clamp_min(tiny)
    return {
        "cov": (W @ W.T) * s2 / (norms[:, None] * norms[None, :]),
        "corr": (unit @ unit.T).clamp(-1.0, 1.0),  # cosines: the clamp only removes rounding
        "singular_values": s,
        "singular_vectors": vh,
    }


def _sparse_basis(weak: Tensor) -> Tensor:
    """A basis of the row space of ``weak (k, n)`` in reduced row-echelon form (full
    pivoting): each row has a 1 at its own pivot parameter and 0 at the others', so two
    independent trade-offs that an SVD returns mixed come apart again."""
    A = weak.clone()
    pivots: list[int] = []
    for r in range(A.shape[0]):
        rest = A[r:].abs()
        rest[:, pivots] = 0
        i, c = divmod(int(rest.argmax()), A.shape[1])
        if float(rest[i, c]) == 0.0:
            return A[:r]
        A[[r, r + i]] = A[[r + i, r]]
        A[r] = A[r] / A[r, c]
        others = torch.arange(A.shape[0]) != r
        A[others] -= A[others, c : c + 1] * A[r]
        pivots.append(c)
    return A


def undetermined_groups(
    singular_values: Tensor, singular_vectors: Tensor, max_condition: float
) -> list[list[int]]:
    """Index groups of parameters the data cannot separate, in parameter order.

    Args:
        singular_values: ``(<= n,)`` of the Jacobian with unit-norm columns, descending.
        singular_vectors: ``(n, n)`` its right singular vectors (rows, same order; rows
            beyond the singular values span the null space of a short Jacobian).
        max_condition: a direction with ``s < s_max / max_condition`` is not determined.
    """
    n = singular_vectors.shape[0]
    s = torch.zeros(n, dtype=singular_vectors.dtype)
    s[: singular_values.numel()] = singular_values
    weak = singular_vectors[s < s[0] / max_condition]
    groups: list[set[int]] = []
    for row in _sparse_basis(weak):
        # A member carries at least an even share (1/n) of the trade-off's squared
        # length; rounding-level entries (~1e-16) never do.
        share = row**2 / (row**2).sum()
        members = {int(i) for i in torch.nonzero(share >= 1.0 / n).flatten()}
        for g in [g for g in groups if g & members]:  # trade-offs sharing a parameter
            members |= g
            groups.remove(g)
        groups.append(members)
    return sorted(sorted(g) for g in groups)

"""The predicted poses of the last few (model point, rows) pairs, for the questions that
evaluate a point already evaluated.

A diagnosis evaluates its fit rows at the refit's optimum when the fit ends (its
errors), again to screen the cyclic orders and to F-test the refit, and the hold-out
rows of the current model at every step although the step before evaluated them. The
point is what :mod:`.shared_jacobian` compares (frames, non-zero effects' values,
exactly), the rows the very tensors of joint values and conditions: a pose kept is the
pose the model would compute.
"""

from __future__ import annotations

import threading

from torch import Tensor

from hybrid_pk.calibration.shared_jacobian import model_point, same_point
from hybrid_pk.effects import Conditions, ExtendedModel

__all__ = ["keep_poses", "kept_poses"]

# Rows of poses kept per thread (16 floats a row): 100,000 rows are ~13 MB; a larger
# set of rows is not kept (the next question evaluates it again).
MAX_KEPT_ROWS = 100_000
# Points kept: the fit rows and the hold-out rows of the current model and the next.
MAX_KEPT = 4

_local = threading.local()


def _store() -> list:
    if not hasattr(_local, "kept"):
        _local.kept = []  # [(point, q, cond, T, q's version)], the newest last
    return _local.kept


def kept_poses(model: ExtendedModel, q: Tensor, cond: Conditions) -> Tensor | None:
    """The poses kept for ``model``'s point on exactly these rows (``q``, ``cond``)."""
    store = _store()
    if not store:
        return None
    point = model_point(model)
    for entry in reversed(store):
        same_rows = entry[1] is q and entry[4] == q._version and entry[2] is cond
        if same_rows and same_point(entry[0], point):
            return entry[3]
    return None


def keep_poses(model: ExtendedModel, q: Tensor, cond: Conditions, T: Tensor) -> None:
    """Keep ``T``, the poses of ``model`` on the rows ``q`` under ``cond`` (plain values)."""
    if T.requires_grad or q.shape[0] > MAX_KEPT_ROWS:
        return
    store = _store()
    # q's version counter: rows changed in place since are other rows; T: the caller's
    store.append((model_point(model), q, cond, T.clone(), q._version))
    while len(store) > MAX_KEPT or sum(e[1].shape[0] for e in store) > MAX_KEPT_ROWS:
        store.pop(0)

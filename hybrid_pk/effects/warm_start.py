"""Where the compliance fixed point of a set of rows last settled: its next start.

A fit evaluates the same rows again and again at parameters that move by a fraction
of a std; the true joint values ``q*`` move with them by ~1e-8 rad. Started there
instead of at ``q_kin`` (an error of ``c g ~ 1e-3`` rad), the fixed point needs one or
two steps instead of three. The stopping rule is the same (the estimated error below
the tolerance), so the values it returns are the same to that tolerance; a stale start
(other compliance values) only costs the steps a cold start takes.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import torch
from torch import Tensor

__all__ = ["keep_start", "kept_start"]

# Rows of settled values kept per thread: a 100,000-row campaign's fit and hold-out
# rows at 7 joints are ~11 MB with their commanded values; larger sets thrash (only
# the oldest go), which costs nothing but the steps saved.
MAX_KEPT_ROWS = 100_000

_local = threading.local()


def _store() -> OrderedDict:
    if not hasattr(_local, "kept"):
        _local.kept = OrderedDict()  # key -> (commanded q, settled q*)
    return _local.kept


def _key(q: Tensor) -> tuple:
    return (q.data_ptr(), tuple(q.shape), q.stride(), q.dtype)


def kept_start(q: Tensor) -> Tensor | None:
    """The settled ``q*`` last kept for exactly these commanded rows ``q``, or None."""
    kept = _store().get(_key(q))
    if kept is None or not torch.equal(kept[0], q):
        return None
    return kept[1].clone()  # the caller's to change


def keep_start(q: Tensor, q_star: Tensor) -> None:
    """Keep ``q_star`` (plain values) as the next start of the commanded rows ``q``."""
    n = q.reshape(-1, q.shape[-1]).shape[0] if q.dim() else 0
    if n > MAX_KEPT_ROWS:
        return
    store = _store()
    store.pop(_key(q), None)
    store[_key(q)] = (q.detach().clone(), q_star.detach().clone())
    while sum(v[0].reshape(-1, v[0].shape[-1]).shape[0] for v in store.values()) > MAX_KEPT_ROWS:
        store.popitem(last=False)

"""Broadcasting of batch shapes without torch's first-call cost.

``torch.broadcast_shapes`` imports its symbolic-shape machinery (sympy) the first time
it runs: 0.4-0.8 s added to every command that checks a batch, longer than many of
them take. The rule itself is a few lines.
"""

from __future__ import annotations

import torch

__all__ = ["broadcast_shapes"]


def broadcast_shapes(*shapes) -> torch.Size:
    """The shape ``torch.broadcast_shapes(*shapes)`` gives (shapes are sequences of
    ints, or ints for 1-D shapes); RuntimeError where they do not broadcast, as there."""
    dims = [(s,) if isinstance(s, int) else tuple(int(d) for d in s) for s in shapes]
    ndim = max((len(s) for s in dims), default=0)
    out = [1] * ndim
    for s in dims:
        for i, d in enumerate(s, ndim - len(s)):
            if d < 0:
                raise RuntimeError(f"broadcast_shapes: negative dimension {d} in {s}")
            if d == 1 or d == out[i]:
                continue
            if out[i] != 1:
                raise RuntimeError(
                    "shape mismatch: objects cannot be broadcast to a single shape: "
                    + ", ".join(str(x) for x in dims)
                )
            out[i] = d
    return torch.Size(out)

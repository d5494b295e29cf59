"""Constants that carry a (zero) forward-mode tangent.

Under ``torch.func.vmap`` over ``torch.func.jvp`` (torch 2.13), arithmetic between a
constant (a Python number, or a tensor without a tangent) and a differentiated tensor
runs torch's Python reference implementation, about three times the time of the
compiled batching rule, and imports ``torch._dynamo`` on first use (~2 s). Passing
the constant through :func:`carried` first gives it a zero tangent, so that both
operands carry one and torch takes the compiled path; values are unchanged.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["carried"]


# Whether a tensor is one of torch.func's (vmap, jvp, grad) wrappers; without the
# (private) test every call carries, which is only slower.
_wrapped = getattr(torch._C._functorch, "is_functorch_wrapped_tensor", lambda t: True)


def carried(const: Tensor | float, like: Tensor) -> Tensor | float:
    """``const`` broadcast against ``like``: the same values, with a zero tangent (and
    zero gradient to ``like``) wherever ``like`` is differentiated; ``const`` itself
    when ``like`` is a plain tensor (outside ``torch.func``: nothing to carry)."""
    if not _wrapped(like):
        return const
    true = torch.ones((), dtype=torch.bool, device=like.device)
    return torch.where(true, const, like)

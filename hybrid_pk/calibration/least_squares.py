"""Levenberg–Marquardt least squares in torch.

Residual counts are large (6 per measured pose, thousands of poses) and parameter
counts small (tens), so the Jacobian is built in forward mode (``torch.func.jacfwd``:
one vectorised pass over the parameter directions), or a problem supplies its normal
equations directly (built chunk by chunk over the rows), and each step solves the
small normal equations with Marquardt's diagonal scaling, which makes the step
invariant to the units of the parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["LMResult", "StoppedFit", "jacobian", "levenberg_marquardt"]


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes:
        x: ``(n,)`` solution.
        residual: ``(m,)`` residuals at ``x``.
        cost: ``sum(residual**2)``.
        iterations: accepted steps.
        converged: a tolerance was met (not just the iteration limit).
    """

    x: Tensor
    residual: Tensor
    cost: float
    iterations: int
    converged: bool


class StoppedFit(Exception):
    """Raised by :func:`levenberg_marquardt` where its ``stop`` test held at an
    accepted step; ``x`` is that step's point."""

    def __init__(self, x: Tensor) -> None:
        super().__init__("the fit's stop test held at an accepted step")
        self.x = x


def jacobian(
    fun: Callable[[Tensor], Tensor], x: Tensor, chunk_size: int | None = 8
) -> tuple[Tensor, Tensor]:
    """Residual ``(m,)`` and Jacobian ``(m, n)`` of ``fun`` at ``x``, in forward mode.

    ``chunk_size`` parameter directions are pushed through ``fun`` at once (vmap over
    jvp), which bounds memory for large ``m`` while keeping the passes vectorised.
    """
    with torch.no_grad():
        r = fun(x)

    def directional(v: Tensor) -> Tensor:
        return torch.func.jvp(fun, (x,), (v,))[1]

    eye = torch.eye(x.numel(), dtype=x.dtype, device=x.device)
    Jt = torch.func.vmap(directional, chunk_size=chunk_size)(eye)  # (n, m)
    return r.detach(), Jt.T.detach()


def levenberg_marquardt(
    fun: Callable[[Tensor], Tensor],
    x0: Tensor,
    *,
    max_iter: int = 50,
    ftol: float = 1e-10,
    xtol: float = 1e-10,
    lam0: float = 1e-3,
    jac: Callable[[Tensor], tuple[Tensor, Tensor]] | None = None,
    normal: Callable[[Tensor], tuple[Tensor, Tensor, float]] | None = None,
    progress: Callable[[str], None] | None = None,
    drop_tol: float = 0.0,
    stop: Callable[[Tensor], bool] | None = None,
) -> LMResult:
    """Minimise ``sum(fun(x)**2)`` from ``x0``.

    Args:
        fun: residual function ``(n,) -> (m,)``, differentiable in forward mode.
        x0: ``(n,)`` start.
        max_iter: most Jacobian evaluations.
        ftol: stop when an accepted step lowers the cost by less than this fraction.
        xtol: stop when the step is below this fraction of ``|x| + xtol``.
        lam0: initial damping.
        jac: ``x -> (residual, Jacobian)``; default forward-mode autodiff of ``fun``.
        normal: ``x -> (J^T J, J^T r, r^T r)`` instead of ``jac``: the normal equations
            of a problem too large to hold its Jacobian (built chunk by chunk).
        progress: called with a short text after every accepted step.
        drop_tol: stop, without another Jacobian, when the next step is predicted to
            lower the cost by less than this fraction of it. The prediction assumes
            the drops shrink at least geometrically, by the ratio of the last two
            undamped ones: ``drop_k^2 / drop_(k-1)`` (Gauss–Newton near a solution
            converges linearly or faster). 0: only ``ftol`` and ``xtol`` stop.
        stop: a test of each accepted point; where it holds, :class:`StoppedFit` is
            raised (the caller has no use for the fit from there on).
    """
    if normal is None:
        jac = jac or (lambda x: jacobian(fun, x))

        def normal(x: Tensor) -> tuple[Tensor, Tensor, float]:
            r, J = jac(x)
            return J.T @ J, J.T @ r, float(r @ r)

    x = x0.detach().clone()
    A, g, cost = normal(x)
    r = None
    lam, it, converged = lam0, 0, False
    last_drop = 0.0  # no drop yet: no prediction
    eye = torch.eye(x.numel(), dtype=x.dtype, device=x.device)
    while it < max_iter:
        d = A.diagonal().clamp_min(1e-12 * float(A.diagonal().max().clamp_min(1e-300)))
        improved = False
        for _ in range(12):  # raise the damping until a step lowers the cost
            step = -torch.linalg.solve(A + lam * torch.diag(d) + 1e-15 * eye, g)
            x_new = x + step
            with torch.no_grad():
                r_new = fun(x_new)
            cost_new = float(r_new @ r_new)
            if cost_new < cost and torch.isfinite(r_new).all():
                improved = True
                break
            lam *= 10.0
        if not improved:
            converged = True  # no descent left at any damping: at a minimum
            break
        it += 1
        if stop is not None and stop(x_new):
            raise StoppedFit(x_new)
        drop = cost - cost_new
        rel_drop = drop / max(cost, 1e-300)
        undamped = lam <= lam0  # a damped step's drop says little about the next one
        predicted = drop * drop / last_drop if last_drop > 0 and undamped else math.inf
        small_step = float(step.norm()) < xtol * (float(x.norm()) + xtol)
        x, r, cost, last_drop = x_new, r_new, cost_new, drop
        lam = max(lam / 10.0, 1e-12)
        if progress is not None:
            progress(f"LM iteration {it}: cost {cost:.6g} ({100 * rel_drop:.2g} % lower)")
        if rel_drop < ftol or small_step or predicted < drop_tol * cost:
            converged = True
            break
        if it < max_iter:  # the last iteration's Jacobian would be unused
            A, g, cost = normal(x)
    if r is None:
        with torch.no_grad():
            r = fun(x)
    return LMResult(x=x, residual=r, cost=cost, iterations=it, converged=converged)

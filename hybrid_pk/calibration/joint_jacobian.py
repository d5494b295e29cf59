"""``dq_kin / dtheta`` of the joint-space effects, one effect at a time.

The joint-space effects act in sequence, ``q <- f_e(q, theta_e)``. Pushing every
parameter direction through the whole sequence (forward mode over all of them) costs
effects x directions evaluations: quadratic in the candidates a diagnosis scores. But
each joint effect changes only its own joint's value, from that value alone (an offset,
a gear ratio, a periodic error, backlash by the approach direction), so by the chain
rule ``dq_j/dtheta`` of everything before effect ``e`` at joint ``j`` is multiplied by
``df_e/dq_j``, and ``e``'s own columns are ``df_e/dtheta_e``: two forward passes through
``e`` for its input and one per own parameter, linear in the effects.

That structure is checked on every call (exact zeros and identities in the forward
derivatives); an effect that acts otherwise (a plug-in coupling two joints) returns
None and the caller pushes every direction through the whole sequence.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hybrid_pk.effects import Conditions, ExtendedModel

__all__ = ["joint_effect_jacobian"]


class _Apply(nn.Module):
    """One effect's ``apply_q`` as a module forward, for ``functional_call``."""

    def __init__(self, effect: nn.Module) -> None:
        super().__init__()
        self.effect = effect

    def forward(self, q: Tensor, cond: Conditions) -> Tensor:
        return self.effect.apply_q(q, cond)


def _effect_derivatives(effect, q: Tensor, cond: Conditions, j: int, block):
    """``(q_out, d q_out_j / d q_j (n,), d q_out_j / d theta (size, n) or None)`` of one
    effect, or None when it changes another joint or reads another joint's value.

    An effect with ``joint_derivatives`` (a map of its own joint alone, derivatives in
    closed form: the built-in ones) gives them directly; any other goes through forward
    mode (one pass per direction, all in one batch) and is checked to be such a map.
    """
    closed = getattr(effect, "joint_derivatives", None)
    if closed is not None:
        with torch.no_grad():
            # at zero (a candidate scored) a built-in map passes q itself: Effect.inert
            out = q if effect.inert() else effect.apply_q(q, cond)
            along, own = closed(q, cond, 0.0 if block is None else block.scale)
        return out, along, own if block is not None else None
    wrapper, value = _Apply(effect), effect.value.detach()
    n, dof = q.shape

    def f(qv: Tensor, v: Tensor) -> Tensor:
        return torch.func.functional_call(wrapper, {"effect.value": v}, (qv, cond))

    size = 0 if block is None else block.size
    eye = torch.eye(dof, dtype=q.dtype)
    along, across = eye[j].expand(n, dof), (1 - eye[j]).expand(n, dof)
    t_q = torch.stack([along, across, *[torch.zeros_like(q)] * size])
    t_v = torch.zeros(2 + size, value.numel(), dtype=value.dtype)
    if size:
        t_v[2:] = torch.eye(size, dtype=value.dtype) * block.scale
    t_v = t_v.reshape(2 + size, *value.shape)
    # The value itself comes out of the same pass (unbatched: it reads no direction).
    out, d = torch.func.vmap(
        lambda a, b: torch.func.jvp(f, (q, value), (a, b)), out_dims=(None, 0)
    )(t_q, t_v)
    if not torch.equal(d[1], across) or bool((d[0] * across != 0).any()):
        return None
    if size and bool((d[2:] * across != 0).any()):
        return None
    return out, d[0][:, j], d[2:, :, j] if size else None


def joint_effect_jacobian(
    model: ExtendedModel, q: Tensor, cond: Conditions, blocks
) -> Tensor | None:
    """``dq_kin/dtheta (n, dof, k)`` of the parameter ``blocks`` (scaled offsets, as
    :class:`~.structured_jacobian.StructuredJacobian` fits them) at the current values
    (zero columns for blocks of other stages), or None when some joint effect is not a
    map of its own joint alone.
    """
    n, dof = q.shape
    where, k = {}, 0
    for b in blocks:
        where[b.name] = (k, b)
        k += b.size
    D = q.new_zeros(n, dof, k)
    q = q.detach()
    for i, e in enumerate(model.effects):
        if e.stage != "joint":
            continue
        j = getattr(e, "joint_index", None)
        start, block = where.get(f"effects.{i}.value", (0, None))
        step = None if j is None else _effect_derivatives(e, q, cond, j, block)
        if step is None:
            return None  # not a map of its joint alone
        q, d_along, own = step
        if not bool((d_along == 1).all()):  # (a candidate at zero passes q_j through)
            D[:, j, :] *= d_along[:, None]  # the chain through this effect
        if own is not None:
            D[:, j, start : start + block.size] += own.T
    return D

"""What the IK solver needs of a forward model, and adapters that provide it.

The solver sees a model as an :class:`IKModel`: a pose function, a pose-and-Jacobian
function, and the joint limits. :func:`as_ik_model` builds one from

- a :class:`~hybrid_pk.robot.Robot` (analytic Jacobian),
- an :class:`~hybrid_pk.effects.ExtendedModel` (analytic Jacobian when it has no error
  effects, i.e. robot + base/tool frames; autograd otherwise),
- any differentiable callable ``q (M, dof) -> T (M, 4, 4)`` (e.g. a hybrid model with
  residual networks), with an optional analytic Jacobian.

Shapes: ``M`` joint configurations being solved at once; ``rows (M,)`` says which
target each configuration belongs to (it picks that target's operating conditions).
Jacobians are geometric, ``(M, 6, dof)`` with rows ``[v; omega]``: the velocity of the
pose's origin [m/rad] and the angular velocity [rad/rad], both in the frame the poses
are expressed in. The solver's inner loop calls :meth:`IKModel.evaluate`, the same in
batch-last layout (see ``hybrid_pk.geometry.batch_last``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import NamedTuple

import torch
from torch import Tensor

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import HybridPKError, ShapeError
from hybrid_pk.geometry import vee_antisym
from hybrid_pk.robot import Robot
from hybrid_pk.robot.kernel import ChainKernel

__all__ = [
    "IKModel",
    "as_ik_model",
    "autograd_pose_jacobian",
    "least_singular_values",
    "no_autograd",
    "plain",
    "smallest_singular_value",
]

PoseFn = Callable[[Tensor, Tensor], Tensor]
PoseJacobianFn = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
BatchLastFn = Callable[[Tensor], tuple[Tensor, Tensor, Tensor]]


@dataclass(frozen=True)
class IKModel:
    """A forward model as the solver uses it.

    Attributes:
        pose: ``(q (M, dof), rows (M,)) -> T (M, 4, 4)`` [m].
        pose_and_jacobian: ``(q, rows) -> (T (M, 4, 4), J (M, 6, dof))``.
        lower: ``(dof,)`` lower joint limits [rad or m] (``-inf`` for continuous joints).
        upper: ``(dof,)`` upper joint limits.
        revolute: ``(dof,)`` bool, True for revolute and continuous joints.
        joint_names: the ``dof`` joint names, in the order of ``q``'s columns.
        analytic: True when the Jacobian is analytic (no autograd).
        batch_last: optional fast path of :meth:`evaluate`, ``qt (dof, M) -> (R, p, J)``
            (the chain kernel; models without per-target conditions only).
    """

    pose: PoseFn
    pose_and_jacobian: PoseJacobianFn
    lower: Tensor
    upper: Tensor
    revolute: Tensor
    joint_names: tuple[str, ...]
    analytic: bool
    batch_last: BatchLastFn | None = None

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    def evaluate(self, qt: Tensor, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Batch-last pose and Jacobian at ``qt (dof, M)``: ``R (3, 3, M)``, ``p (3, M)``
        [m], ``J (6, dof, M)``."""
        if self.batch_last is not None:
            return self.batch_last(qt)
        T, J = self.pose_and_jacobian(qt.T, rows)
        T, J = T.to(torch.float64), J.to(torch.float64)
        return T[:, :3, :3].permute(1, 2, 0), T[:, :3, 3].T, J.permute(1, 2, 0)


def autograd_pose_jacobian(pose: PoseFn, q: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
    """Pose and geometric Jacobian of any differentiable pose function, by autograd.

    Rows of the Jacobian: the position derivative, and ``omega`` from
    ``[omega]x = dR/dq R^T`` (taken as the derivative of the antisymmetric part of
    ``R(q) R(q0)^T`` at ``q0``). One forward pass and six reverse passes.

    Args:
        pose: ``(q (M, dof), rows (M,)) -> (M, 4, 4)``, differentiable in ``q``.
        q: ``(M, dof)`` joint values [rad or m].
        rows: ``(M,)`` target index of each configuration.

    Returns:
        ``T (M, 4, 4)`` (detached) and ``J (M, 6, dof)``.
    """
    with torch.enable_grad():
        qv = q.detach().requires_grad_(True)
        T = pose(qv, rows)
        R = T[:, :3, :3]
        omega = vee_antisym(R @ R.detach().transpose(-1, -2)) / 2
        y = torch.cat([T[:, :3, 3], omega], -1)  # (M, 6)
        cols = []
        for k in range(6):
            (g,) = torch.autograd.grad(y[:, k].sum(), qv, retain_graph=k < 5, allow_unused=True)
            cols.append(torch.zeros_like(qv) if g is None else g)
    return T.detach(), torch.stack(cols, 1)


def _subset(cond: Conditions | None, rows: Tensor) -> Conditions | None:
    return None if cond is None else cond.subset(rows)


def _check_cond(cond: Conditions | None, n_targets: int | None) -> None:
    if cond is None or n_targets is None:
        return
    for f in fields(cond):
        value = getattr(cond, f.name)
        if value is not None and value.shape[:1] != (n_targets,):
            raise ShapeError(
                f"cond.{f.name}: expected one entry per target ({n_targets}), found shape "
                f"{tuple(value.shape)}"
            )


class _Adapter(NamedTuple):
    robot: Robot
    pose: PoseFn
    pose_and_jacobian: PoseJacobianFn
    analytic: bool
    batch_last: BatchLastFn | None = None


def _robot_adapter(model: Robot) -> _Adapter:
    """The chain kernel's analytic Jacobian."""
    kernel = ChainKernel.of(model)

    def pose(q: Tensor, rows: Tensor) -> Tensor:
        return model.fk(q)

    def pose_jac(q: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
        return kernel(q)

    return _Adapter(model, pose, pose_jac, True, kernel.soa)


def _extended_adapter(model: ExtendedModel, cond: Conditions | None) -> _Adapter:
    """Frames only: the chain kernel with the frames folded in; else autograd."""
    if len(model.effects) == 0 and model.base.sets == 1:
        with torch.no_grad():
            base, tool = model.base.matrix()[0].detach(), model.tool.matrix()[0].detach()

        def pose(q: Tensor, rows: Tensor) -> Tensor:
            return base.to(q.dtype) @ model.robot.fk(q) @ tool.to(q.dtype)

        kernel = ChainKernel(model.robot, base, tool)

        def pose_jac(q: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
            return kernel(q)

        return _Adapter(model.robot, pose, pose_jac, True, kernel.soa)

    def pose(q: Tensor, rows: Tensor) -> Tensor:
        return model(q, _subset(cond, rows))

    def pose_jac(q: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
        return autograd_pose_jacobian(pose, q, rows)

    return _Adapter(model.robot, pose, pose_jac, False)


def _callable_adapter(
    fn: Callable, robot: Robot | None, jacobian: Callable | None, cond: Conditions | None
) -> _Adapter:
    """Any differentiable ``q -> T``, with its own Jacobian or autograd's."""
    if robot is None:
        raise HybridPKError(
            "IK on a callable model needs robot= (for joint names, limits and types)"
        )

    def pose(q: Tensor, rows: Tensor) -> Tensor:
        return fn(q) if cond is None else fn(q, _subset(cond, rows))

    def pose_jac(q: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
        if jacobian is None:
            return autograd_pose_jacobian(pose, q, rows)
        J = jacobian(q) if cond is None else jacobian(q, _subset(cond, rows))
        return pose(q, rows), J

    return _Adapter(robot, pose, pose_jac, jacobian is not None)


def as_ik_model(
    model: Robot | ExtendedModel | Callable | IKModel,
    *,
    cond: Conditions | None = None,
    robot: Robot | None = None,
    jacobian: Callable | None = None,
    n_targets: int | None = None,
) -> IKModel:
    """Wrap a forward model for the solver.

    Args:
        model: a ``Robot`` (pose of its end link in its root frame), an
            ``ExtendedModel`` (pose of the measured point in the measurement frame), a
            callable ``fn(q) -> (M, 4, 4)`` or, when ``cond`` is given,
            ``fn(q, cond) -> (M, 4, 4)`` (differentiable in ``q`` unless ``jacobian`` is
            given), or an ``IKModel`` (returned as is).
        cond: operating conditions per target (``payload``, ``temperature``, ...), each
            ``(n_targets, ...)``; passed to an ``ExtendedModel`` or callable, row-matched.
        robot: the robot whose joint limits and types a callable uses (required for
            a callable).
        jacobian: optional analytic ``fn(q[, cond]) -> (M, 6, dof)`` geometric Jacobian
            of a callable, rows ``[v; omega]`` in the pose's frame.
        n_targets: number of targets, to check ``cond`` against.

    Models whose parameters require gradients are evaluated with those graphs (slower):
    call ``requires_grad_(False)`` on a model that is only used for IK.

    Raises:
        HybridPKError: a callable without ``robot``; ShapeError: ``cond`` of the wrong size.
    """
    if isinstance(model, IKModel):
        return model
    _check_cond(cond, n_targets)
    if isinstance(model, Robot):
        a = _robot_adapter(model)
    elif isinstance(model, ExtendedModel):
        a = _extended_adapter(model, cond)
    elif callable(model):
        a = _callable_adapter(model, robot, jacobian, cond)
    else:
        raise HybridPKError(
            f"IK needs a Robot, an ExtendedModel or a callable q -> T, got {type(model).__name__}"
        )
    lower, upper = a.robot.joint_limits
    return IKModel(
        pose=a.pose,
        pose_and_jacobian=a.pose_and_jacobian,
        lower=lower.detach().to(torch.float64),
        upper=upper.detach().to(torch.float64),
        revolute=a.robot.revolute.clone(),
        joint_names=tuple(a.robot.joint_names),
        analytic=a.analytic,
        batch_last=a.batch_last,
    )


def no_autograd(ikm: IKModel):
    """The chain kernel needs no autograd at all: inference mode skips the view and
    version bookkeeping of the iteration's many small tensor operations (~15 % of an
    IK call, bench/ik.py); other models may need autograd for their Jacobian. Only for
    pure tensor work: a model's caches filled in it would be inference tensors."""
    return torch.inference_mode() if ikm.batch_last is not None else torch.no_grad()


def plain(*values):
    """``values`` with inference tensors copied into ordinary ones (others as they are)."""
    return tuple(v.clone() if isinstance(v, Tensor) and v.is_inference() else v for v in values)


def smallest_singular_value(
    ikm: IKModel, q: Tensor, rows: Tensor, rotation_weight: float, position_only: bool
) -> Tensor:
    """``(M,)`` [m/rad] smallest singular value of the Jacobian at ``q (M, dof)``: its
    velocity rows and its angular rows times ``rotation_weight`` [m/rad] (the solver's
    weighting; velocity rows only for position-only targets). Of a redundant arm the
    smallest of its ``min(6, dof)``: how near the task directions are to losing one."""
    if q.shape[0] == 0:
        return q.new_zeros(0, dtype=torch.float64)
    with no_autograd(ikm):  # the batch-last path: the chain kernel where there is one
        J = ikm.evaluate(q.T.to(torch.float64).contiguous(), rows)[2].permute(2, 0, 1)
        J = J[:, :3] if position_only else torch.cat([J[:, :3], rotation_weight * J[:, 3:]], 1)
        sigma = torch.linalg.svdvals(J)[:, -1]
    return plain(sigma)[0]


def least_singular_values(
    ikm: IKModel, q: Tensor, valid: Tensor, rotation_weight: float, position_only: bool
) -> Tensor:
    """``(N,)`` [m/rad] per target the least :func:`smallest_singular_value` of its
    solutions ``q (N, K, dof)`` (slots ``valid (N, K)``; NaN for none); target ``i``'s
    configurations are evaluated as row ``i`` (its conditions)."""
    target, slot = valid.nonzero(as_tuple=True)
    s = smallest_singular_value(ikm, q[target, slot], target, rotation_weight, position_only)
    out = torch.full((q.shape[0],), math.inf, dtype=torch.float64)
    out = out.scatter_reduce(0, target, s, "amin")
    return out.masked_fill(~valid.any(1), math.nan)

"""Deflection beyond the joint axis: the static load bends bearings, links and columns.

``joint_compliance`` is the part of a joint's elasticity *about* its axis. The same
gravity (and payload) wrench also tilts the joint's bearings and bends the link after
it about the two axes *perpendicular* to the joint axis (elasto-geometric calibration:
FIGAROH's joint elastic gains; Kamali et al., ICRA 2016). A lumped model per joint
``i`` (the virtual-joint method): the part the joint carries turns, as a rigid body,
by a small rotation ``w`` about a pivot on the axis,

- ``tilt_compliance``  value ``(c1, c2)`` [rad/Nm]: ``w = -(c1 m1 e1 + c2 m2 e2)``,
  pivot at the joint frame's origin;
- ``column_bending``   value ``(b1, b2)`` [rad/Nm/m], prismatic joints only: a column
  extended by ``q`` bends like a beam of free length ``q``, ``w = -q (b1 m1 e1 + b2 m2
  e2)`` with the moment taken about mid-extension, the pivot there (a uniform moment
  turns a beam's tip by ``M L / EI`` and moves it sideways by half that times ``L``:
  exactly a rotation about the middle). ``tilt_compliance`` of the same joint is the
  length-independent part (guides, overlap), so together ``c(q) = c + b q``.

``m_k = e_k · M`` are the components of the holding moment ``M``
(:meth:`~hybrid_pk.robot.Robot.static_wrenches`, in the joint's own frame) on the
basis ``e1, e2`` perpendicular to the joint axis (:func:`perpendicular_basis`: for an
axis along z, e1 = x and e2 = y of the joint frame). The basis turns with the joint,
so a link that is stiffer in one direction keeps its two values.

The wrench is that of the rigid chain at the true joint values: the deflection itself
changes the moment arms by ``|w|`` (≤ 1e-3 rad), a relative change of the deflection
of 1e-3, i.e. ≤ 1 µrad, which is dropped. The deflection acts on the origin after
joint ``i`` (``D_i · O_{i+1}``), so its effect reaches everything that joint carries.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.effects.base import Effect, register, sds_below
from hybrid_pk.effects.limits import DRAWN_COMPLIANCE, MAX_COMPLIANCE
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import so3_exp
from hybrid_pk.robot import KinematicParams

__all__ = ["ColumnBending", "DeflectionEffect", "TiltCompliance", "perpendicular_basis"]


def perpendicular_basis(axis: Tensor) -> Tensor:
    """``(2, 3)`` unit vectors ``e1, e2`` perpendicular to ``axis`` with ``e1 x e2 = a``.

    ``e1`` is the coordinate axis that follows the axis's largest component cyclically
    (z -> x, y -> z, x -> y), made perpendicular: an axis along z gives x and y.
    """
    a = axis / axis.norm()
    k = int(a.abs().argmax())
    e1 = torch.zeros_like(a)
    e1[(k + 1) % 3] = 1
    e1 = e1 - (e1 @ a) * a
    e1 = e1 / e1.norm()
    return torch.stack([e1, torch.linalg.cross(a, e1)])


def deflect_origin(params: KinematicParams, index: int, w: Tensor, pivot: Tensor):
    """Turn everything after joint frame ``index`` by ``w (*B, 3)`` [rad] about
    ``pivot (*B, 3)`` [m] (both in that joint frame): origin ``index + 1`` becomes
    ``Trans(p) Rot(w) Trans(-p) O``. Returns per-sample parameters ``(*B, ...)``."""
    xyz, rot = params.origin_xyz, params.origin_rot
    R_w = so3_exp(w.to(rot.dtype))  # (*B, 3, 3)
    n = xyz.shape[-2]
    new_rot = R_w @ rot[..., index + 1, :, :]
    t = xyz[..., index + 1, :] - pivot
    new_xyz = (R_w @ t[..., None])[..., 0] + pivot
    mask = torch.zeros(n, dtype=torch.bool, device=xyz.device)
    mask[index + 1] = True
    xyz = torch.where(mask[:, None], new_xyz[..., None, :], xyz)
    rot = torch.where(mask[:, None, None], new_rot[..., None, :, :], rot)
    axis = params.axis.expand(*xyz.shape[:-2], *params.axis.shape[-2:])
    return KinematicParams(xyz, rot, axis)


class DeflectionEffect(Effect):
    """Common part: a 2-vector of compliances on the basis perpendicular to the axis.

    Subclasses give :meth:`rotation`; the model computes the wrench once per forward
    pass and calls :meth:`apply_deflection`.
    """

    stage, shape, scale = "deflection", (2,), 1e-6
    joint_set = "chain"  # a physical joint of the chain (each mimic segment bends)
    positive, evidence = True, "moment"  # a load cannot bend a structure towards itself

    def __init__(self, robot, joint: str | None = None, value=None) -> None:
        super().__init__(robot, joint, value)
        axis = torch.as_tensor(robot.spec.axes[self.joint_index], dtype=robot.dtype)
        self.register_buffer("axis_unit", axis / axis.norm())
        self.register_buffer("basis", perpendicular_basis(axis))  # (2, 3)

    @classmethod
    def refused(cls, value: float | list[float], std=None) -> list[str]:
        if not cls.below_zero(value, std):
            return []
        shown = ", ".join(f"{v:.3g}" for v in value)
        return [
            f"negative {cls.kind} ({shown} {cls.unit}{sds_below(value, std)}): a load "
            "cannot bend a structure towards itself; it likely absorbs another, unmodelled error"
        ]

    def _bend(self, moment: Tensor, value: Tensor | None) -> Tensor:
        """``-(c1 m1 e1 + c2 m2 e2)`` for moments ``(*B, 3)`` in the joint frame."""
        basis = self.basis.to(moment.dtype)
        components = moment @ basis.T  # (*B, 2)
        c = self.value if value is None else value
        return -(c.to(moment.dtype) * components) @ basis

    def rotation(
        self, wrench: Tensor, q: Tensor, value: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Rotation ``w (*B, 3)`` [rad] and pivot ``(*B, 3)`` [m], joint frame, from the
        joint's wrench ``(*B, 6)`` and the chain's joint values ``q (*B, n_chain)``
        (``value``: in place of the effect's own; ``w`` is linear in it)."""
        raise NotImplementedError

    def rotation_per_unit(self, wrench: Tensor, q: Tensor, k: int) -> Tensor:
        """``d w / d value_k (*B, 3)``: the rotation at a unit value of component ``k``."""
        unit = torch.zeros(2, dtype=wrench.dtype)
        unit[k] = 1
        return self.rotation(wrench, q, unit)[0]

    def apply_deflection(self, params: KinematicParams, wrench: Tensor, q: Tensor):
        """Parameters deflected by this effect, from the joint-frame wrenches
        ``(*B, n_chain, 6)`` and the chain's true joint values ``q (*B, n_chain)``."""
        w, pivot = self.rotation(wrench[..., self.joint_index, :], q)
        return deflect_origin(params, self.joint_index, w, pivot)

    def report_value(self) -> list[float]:
        return [float(x) for x in self.value.detach().to(torch.float64)]


@register
class TiltCompliance(DeflectionEffect):
    """Bearing tilt and link bending at a joint, about the two axes perpendicular to it.

    Value ``(c1, c2)`` [rad/Nm] about ``e1, e2`` (:func:`perpendicular_basis`).
    """

    kind, unit, limit = "tilt_compliance", "rad/Nm", MAX_COMPLIANCE
    drawn = DRAWN_COMPLIANCE
    equation = "w = −(c₁M₁e₁ + c₂M₂e₂): tilt about the two axes perpendicular to the joint"
    description = (
        "the joint's bearings and the link after it tilt about the two axes e1, e2 "
        "perpendicular to the joint axis: w = −(c₁M₁e₁ + c₂M₂e₂), M the holding moment of "
        "the static gravity + payload wrench (`Robot.static_wrenches`); value [c₁, c₂] "
        "(e1, e2 = x, y of the joint frame for an axis along z)"
    )

    def rotation(self, wrench: Tensor, q: Tensor, value: Tensor | None = None):
        w = self._bend(wrench[..., 3:], value)
        return w, torch.zeros_like(w)


@register
class ColumnBending(DeflectionEffect):
    """A prismatic column bends more the further it is extended.

    Value ``(b1, b2)`` [rad/Nm/m]: tilt per unit moment and per metre of extension
    ``q`` (from the URDF's zero), about mid-extension. A telescopic column whose
    segments are mimic joints of one actuator has one per segment, each with its own
    extension.
    """

    kind, unit, joints = "column_bending", "rad/Nm/m", "prismatic"  # grows with extension
    equation = "w = −q(b₁M₁e₁ + b₂M₂e₂): a column extended by q bends, prismatic joints"
    description = (
        "prismatic joints: a column extended by q bends like a beam of free length q, "
        "w = −q(b₁M₁e₁ + b₂M₂e₂), moment and pivot at mid-extension; with the same joint's "
        "`tilt_compliance` the tilt is (c + b·q)·M"
    )

    def __init__(self, robot, joint: str | None = None, value=None) -> None:
        super().__init__(robot, joint, value)
        kind = robot.chain_joint_types[self.joint_index]
        if kind != "prismatic":
            raise HybridPKError(
                f"column_bending needs a prismatic joint; {joint} is {kind} (use "
                f"tilt_compliance:{joint})"
            )

    def rotation(self, wrench: Tensor, q: Tensor, value: Tensor | None = None):
        length = q[..., self.joint_index, None]  # (*B, 1) extension [m]
        a = self.axis_unit.to(wrench.dtype)
        force, moment = wrench[..., :3], wrench[..., 3:]
        pivot = -0.5 * length * a  # mid-extension, in the joint frame
        moment_mid = moment + torch.linalg.cross(-pivot, force)  # M about the pivot
        return length * self._bend(moment_mid, value), pivot

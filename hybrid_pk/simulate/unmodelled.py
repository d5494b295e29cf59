"""Ground-truth effects outside the vocabulary: what no calibration can fit exactly.

They exist to test the residual networks (the part of a real robot that physics
models miss) and are deliberately *not* registered in :data:`~hybrid_pk.effects.EFFECTS`,
so ``diagnose``/``calibrate`` never offer them:

- :class:`HardeningCompliance`: a joint spring that is softer near zero torque
  (harmonic drives: stiffness K1 < K2 < K3), the nonlinear part of the paper's joint
  stiffness. A joint-stage effect: ``theta_true = theta + delta(theta, conditions)``.
- :func:`smooth_field`: a smooth random displacement of the measured point over joint
  space (what many small unmodelled errors add up to), for null campaigns.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.effects.base import Effect
from hybrid_pk.effects.conditions import Conditions
from hybrid_pk.robot import Robot

__all__ = ["UNMODELLED_KINDS", "HardeningCompliance", "rms_gravity_torques", "smooth_field"]


def smooth_field(q: Tensor, rms_mm: float, rng: np.random.Generator) -> Tensor:
    """``(N, 3)`` [m]: a smooth random function of the joints (eight plane waves of
    wavelengths of a few radians), scaled to ``rms_mm`` of RMS point displacement."""
    dof = q.shape[1]
    w = torch.as_tensor(rng.normal(0.0, 0.6, (8, dof)), dtype=q.dtype)
    phase = torch.as_tensor(rng.uniform(0, 2 * math.pi, 8), dtype=q.dtype)
    amp = torch.as_tensor(rng.normal(0.0, 1.0, (8, 3)), dtype=q.dtype)
    f = torch.sin(q @ w.T + phase) @ amp
    f = f - f.mean(0)
    return f * (rms_mm * 1e-3 / f.pow(2).sum(1).mean().sqrt())


def rms_gravity_torques(
    robot: Robot, payload: float, generator: torch.Generator, n: int = 4096
) -> Tensor:
    """``(dof,)`` RMS holding torque of every joint [Nm] over ``n`` configurations drawn
    uniformly in the limits: the scale for a spring's knee torque."""
    q = robot.sample_q(n, generator)
    with torch.no_grad():
        return robot.gravity_torques(q, payload=payload).pow(2).mean(0).sqrt()


def _on_joint(q: Tensor, index: int, delta: Tensor) -> Tensor:
    onehot = torch.zeros(q.shape[-1], dtype=q.dtype, device=q.device)
    onehot[index] = 1
    return q + delta[..., None] * onehot


class HardeningCompliance(Effect):
    """Extra deflection of a hardening joint spring: ``theta - c tau0 tanh(tau / tau0)``
    with ``tau`` the holding torque at the commanded joints [Nm] (value ``c`` [rad/Nm],
    knee ``tau0`` [Nm]). Near zero torque the joint is ``c`` more compliant; far from
    it the extra deflection saturates at ``c tau0``. ``gravity``: the root-frame vector
    [m/s²] of the robot's mounting (default upright).
    """

    kind, unit, stage, scale = "hardening_compliance", "rad/Nm", "joint", 1e-6

    def __init__(self, robot: Robot, joint: str, value: float, tau0: float, gravity=None) -> None:
        super().__init__(robot, joint, value)
        self.gravity = None if gravity is None else tuple(float(g) for g in gravity)
        if not tau0 > 0:
            raise ValueError(f"tau0 must be positive [Nm], got {tau0}")
        self.tau0 = float(tau0)
        self._robot = (robot,)  # not a submodule: the robot belongs to the model

    def apply_q(self, q: Tensor, cond: Conditions) -> Tensor:
        payload = 0.0 if cond.payload is None else cond.payload
        g = {} if self.gravity is None else {"gravity": self.gravity}
        tau = self._robot[0].gravity_torques(q, payload=payload, **g)[..., self.joint_index]
        return _on_joint(q, self.joint_index, -self.value * self.tau0 * torch.tanh(tau / self.tau0))

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, tau0={self.tau0:.4g} Nm"


UNMODELLED_KINDS = (HardeningCompliance.kind,)

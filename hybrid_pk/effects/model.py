"""`ExtendedModel`: nominal robot + base and tool frames + physical error effects.

Data flow of one forward pass (all differentiable)::

    q (commanded) --joint effects--> q_kin --compliance fixed point--> q_true
    kinematic params --geometric effects--> params
    T_meas_point = T_meas_root · fk(q_true, params) · T_end_point

``T_meas_root`` (base frame: measurement frame <- robot root, e.g. a laser tracker
in the room) and ``T_end_point`` (tool frame: flange -> measured point/frame) are
estimated in every fit.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hybrid_pk.effects.base import Conditions, Effect
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.robot import Robot

__all__ = ["ExtendedModel", "RigidFrame"]

# Fixed-point iterations of the compliance model. Each contracts the error by about
# |c · dtau/dq| (1e-3 for realistic stiffness), so 4 leave ~1e-12 rad.
COMPLIANCE_ITERATIONS = 4


class RigidFrame(nn.Module):
    """A rigid transform ``T = [R0 exp(rotvec) | p0 + dp]`` around an initial guess.

    Parameters: ``dp (3,)`` [m], ``rotvec (3,)`` [rad], both zero at the initial guess,
    so identification starts at the guess and the parameters stay small.
    """

    scale = 1e-3  # conditioning scale of both parameters (mm, mrad)

    def __init__(self, initial: Tensor | None = None, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        T0 = torch.eye(4, dtype=dtype) if initial is None else initial.to(dtype).clone()
        self.register_buffer("T0", T0)
        self.dp = nn.Parameter(torch.zeros(3, dtype=dtype))
        self.rotvec = nn.Parameter(torch.zeros(3, dtype=dtype))

    def matrix(self) -> Tensor:
        """``(4, 4)`` current transform."""
        return transform(self.T0[:3, :3] @ so3_exp(self.rotvec), self.T0[:3, 3] + self.dp)

    @torch.no_grad()
    def reset_to(self, T: Tensor) -> None:
        """Make ``T`` the new initial guess and zero the parameters."""
        self.T0.copy_(T.to(self.T0.dtype))
        self.dp.zero_()
        self.rotvec.zero_()


class ExtendedModel(nn.Module):
    """Robot + frames + effects: predicts the measured pose of each sample.

    Args:
        robot: nominal robot (its own parameters are not changed by fits).
        effects: error effects, each acting on its joint or on the geometry.
        base: initial ``T_meas_root`` (4, 4); identity when omitted.
        tool: initial ``T_end_point`` (4, 4); identity when omitted.
    """

    def __init__(
        self,
        robot: Robot,
        effects: list[Effect] | tuple[Effect, ...] = (),
        base: Tensor | None = None,
        tool: Tensor | None = None,
    ) -> None:
        super().__init__()
        self.robot = robot
        self.base = RigidFrame(base, robot.dtype)
        self.tool = RigidFrame(tool, robot.dtype)
        self.effects = nn.ModuleList(effects)

    # ------------------------------------------------------------------ effects
    def effect(self, label: str) -> Effect:
        for e in self.effects:
            if e.label == label:
                return e
        raise KeyError(label)

    def add_effect(self, effect: Effect) -> None:
        self.effects.append(effect)

    def _compliance(self) -> Tensor | None:
        comp = [e for e in self.effects if e.stage == "compliance"]
        if not comp:
            return None
        c = torch.zeros(self.robot.dof, dtype=comp[0].value.dtype)
        onehot = torch.eye(self.robot.dof, dtype=c.dtype)
        for e in comp:
            c = c + e.value * onehot[e.joint_index]
        return c

    def kinematic_params(self, cond: Conditions):
        params = self.robot.kinematic_params()
        for e in self.effects:
            if e.stage == "geometry":
                params = e.apply_params(params, cond)
        return params

    def joint_values(self, q: Tensor, cond: Conditions | None = None, params=None) -> Tensor:
        """True joint values ``(*B, dof)`` for commanded ``q``."""
        cond = cond or Conditions()
        for e in self.effects:
            if e.stage == "joint":
                q = e.apply_q(q, cond)
        c = self._compliance()
        if c is not None:
            payload = 0.0 if cond.payload is None else cond.payload
            q_kin, c = q, c.to(q.dtype)
            for _ in range(COMPLIANCE_ITERATIONS):
                # gravity_torques is the holding torque g(q) (pinocchio's sign); gravity
                # itself loads the joint with -g(q), so a positive compliance sags.
                q = q_kin - c * self.robot.gravity_torques(q, payload=payload, params=params)
        return q

    # ------------------------------------------------------------------ prediction
    def end_pose(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` flange pose in the robot root frame, with every effect."""
        cond = cond or Conditions()
        params = self.kinematic_params(cond)
        q_true = self.joint_values(q, cond, params)
        return self.robot.fk(q_true, params=params)

    def forward(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` pose of the measured point/frame in the measurement frame."""
        T = self.end_pose(q, cond)
        return self.base.matrix().to(T.dtype) @ T @ self.tool.matrix().to(T.dtype)

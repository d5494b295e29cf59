"""`ExtendedModel`: nominal robot + base and tool frames + physical error effects.

Data flow of one forward pass (all differentiable)::

    kinematic params --geometric effects--> params
    gravity in the root frame (fixed, or from the base frame of a levelled tracker)
    q (commanded) --joint effects--> q_kin --compliance fixed point--> q_true
    params --deflection effects (static wrench at q_true)--> params_deflected
    T_meas_point = T_meas_root · fk(q_true, params_deflected) · T_end_point

``T_meas_root`` (base frame: measurement frame <- robot root, e.g. a laser tracker
in the room) and ``T_end_point`` (tool frame: flange -> measured point/frame) are
estimated in every fit.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from hybrid_pk.effects.base import Effect
from hybrid_pk.effects.conditions import Conditions
from hybrid_pk.effects.gravity import Gravity
from hybrid_pk.effects.warm_start import keep_start, kept_start
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.robot import Robot
from hybrid_pk.robot.chain import plain_inputs

__all__ = ["ExtendedModel", "RigidFrame"]

# Fixed-point iterations of the compliance model. Each contracts the error by about
# |c · dtau/dq| (1e-3 for realistic stiffness), so 4 leave ~1e-12 rad.
COMPLIANCE_ITERATIONS = 4
# Without derivatives to carry, the iteration stops once its estimated error is below
# this [rad]: 1e-9 mm at a metre's lever, ten million times below a tracker's noise.
COMPLIANCE_TOL_RAD = 1e-12
# ... and after at most this many steps: enough for the tolerance from a cold start
# sagging 0.1 rad at a contraction of 0.1 (0.1 x 0.1^11 = 1e-12), a joint ten times
# softer than gravity's own stiffness. Four steps, as with derivatives, left 1e-10 rad
# on a soft RX160 shoulder (c = 2.3e-5 rad/Nm: contraction ~0.01 from a 0.01 rad sag).
COMPLIANCE_MAX_SETTLING = 12


def _tensors(*values) -> list[Tensor]:
    return [v for v in values if isinstance(v, Tensor)]


class RigidFrame(nn.Module):
    """``G`` rigid transforms ``T_g = [R0_g exp(rotvec_g) | p0_g + dp_g]`` around guesses.

    One set (``G = 1``) is shared by all rows; several sets serve campaigns whose files
    were measured with a re-mounted tool or a moved tracker (one set per file).

    Parameters: ``dp (G, 3)`` [m], ``rotvec (G, 3)`` [rad], zero at the initial guess,
    so identification starts at the guess and the parameters stay small.
    """

    scale = 1e-3  # conditioning scale of both parameters (mm, mrad)

    def __init__(
        self, initial: Tensor | None = None, dtype: torch.dtype = torch.float64, sets: int = 1
    ) -> None:
        super().__init__()
        if initial is None:
            T0 = torch.eye(4, dtype=dtype).expand(sets, 4, 4).clone()
        else:
            T0 = initial.to(dtype).expand(sets, 4, 4).clone()
        self.register_buffer("T0", T0)
        self.dp = nn.Parameter(torch.zeros(sets, 3, dtype=dtype))
        self.rotvec = nn.Parameter(torch.zeros(sets, 3, dtype=dtype))

    @property
    def sets(self) -> int:
        return self.T0.shape[0]

    def matrix(self, group: Tensor | None = None) -> Tensor:
        """``(G, 4, 4)`` current transforms, or ``(*B, 4, 4)`` picked by ``group (*B,)``."""
        T = transform(self.T0[:, :3, :3] @ so3_exp(self.rotvec), self.T0[:, :3, 3] + self.dp)
        if group is None:
            return T
        return T[group]

    @torch.no_grad()
    def reset_to(self, T: Tensor, index: int | None = None) -> None:
        """Make ``T`` the new initial guess (of set ``index``, or of all) and zero it."""
        sl = slice(None) if index is None else slice(index, index + 1)
        self.T0[sl] = T.to(self.T0.dtype)
        self.dp[sl] = 0
        self.rotvec[sl] = 0


def _zero(value: Tensor) -> bool:
    """A plain value (no derivative taken through it) that is exactly zero: an effect
    being scored as a candidate, which changes nothing."""
    return plain_inputs(value) and not bool(value.detach().any())


class ExtendedModel(nn.Module):
    """Robot + frames + effects: predicts the measured pose of each sample.

    Args:
        robot: nominal robot (its own parameters are not changed by fits).
        effects: error effects, each acting on its joint or on the geometry.
        base: initial ``T_meas_root`` (4, 4) or (G, 4, 4); identity when omitted.
        tool: initial ``T_end_point`` (4, 4) or (G, 4, 4); identity when omitted.
        frame_sets: number ``G`` of independent base/tool frame sets; rows pick theirs
            with ``Conditions.group`` (e.g. one set per measurement file).
        gravity: the mounting: gravity in the root frame, or in a levelled measurement
            frame (:class:`~hybrid_pk.effects.gravity.Gravity`); default level on the
            floor, ``(0, 0, -9.80665)`` m/s² in the root frame.
    """

    def __init__(
        self,
        robot: Robot,
        effects: list[Effect] | tuple[Effect, ...] = (),
        base: Tensor | None = None,
        tool: Tensor | None = None,
        frame_sets: int = 1,
        gravity: Gravity | None = None,
    ) -> None:
        super().__init__()
        self.robot = robot
        self.base = RigidFrame(base, robot.dtype, frame_sets)
        self.tool = RigidFrame(tool, robot.dtype, frame_sets)
        for e in effects:
            if not isinstance(e, Effect):
                raise HybridPKError(
                    f"effects must be Effect objects (hybrid_pk.make_effect(robot, "
                    f"'kind:joint', value)), got {type(e).__name__} {e!r}"
                )
        self.effects = nn.ModuleList(effects)
        self.gravity = gravity or Gravity()

    def with_effects(self, effects: list[Effect] | tuple[Effect, ...]) -> ExtendedModel:
        """Same robot, gravity and frame values (copied), with ``effects`` instead."""
        out = ExtendedModel(
            self.robot, list(effects), frame_sets=self.base.sets, gravity=self.gravity
        )
        for mine, theirs in ((self.base, out.base), (self.tool, out.tool)):
            with torch.no_grad():
                for name in ("T0", "dp", "rotvec"):
                    getattr(theirs, name).copy_(getattr(mine, name))
        return out

    # ------------------------------------------------------------------ gravity
    def gravity_root(self, cond: Conditions | None = None) -> Tensor:
        """Gravity in the robot root frame [m/s²]: ``(3,)``, or ``(*B, 3)`` per row
        when a levelled measurement frame and several base frames give each row its own."""
        g = torch.tensor(self.gravity.vector, dtype=self.robot.dtype)
        if not self.gravity.levelled:
            return g
        group = None if cond is None else cond.group
        R = self.base.matrix()[..., :3, :3]  # T_meas_root: p_meas = R p_root + t
        if group is None or self.base.sets == 1:
            return R[0].transpose(-1, -2) @ g
        return (R[group].transpose(-1, -2) @ g.to(R.dtype)[:, None])[..., 0]

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
            if e.stage == "geometry" and not e.inert():  # candidates at zero: no copies
                params = e.apply_params(params, cond)
        return params

    def kinematic_joint_values(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """Joint values after the joint-space effects, before compliance: ``q_kin``."""
        cond = cond or Conditions()
        for e in self.effects:
            if e.stage == "joint" and not e.inert():  # candidates at zero: q itself
                q = e.apply_q(q, cond)
        return q

    def joint_values(
        self,
        q: Tensor,
        cond: Conditions | None = None,
        params=None,
        gravity: Tensor | None = None,
    ) -> Tensor:
        """True joint values ``(*B, dof)`` for commanded ``q`` (``gravity``: the root-frame
        vector of :meth:`gravity_root`, computed when omitted)."""
        cond = cond or Conditions()
        commanded, q = q, self.kinematic_joint_values(q, cond)
        c = self._compliance()
        if c is not None and _zero(c):
            c = None  # every compliance zero (candidates scored): q_kin - 0 g(q) is q_kin
        if c is not None:
            payload = 0.0 if cond.payload is None else cond.payload
            q_kin, c = q, c.to(q.dtype)
            g = self.gravity_root(cond) if gravity is None else gravity

            # gravity_torques is the holding torque g(q) (pinocchio's sign); gravity
            # itself loads the joint with -g(q), so a positive compliance sags.
            def step(q_now: Tensor, p=params) -> Tensor:
                tau = self.robot.gravity_torques(q_now, payload=payload, gravity=g, params=p)
                return q_kin - c * tau

            # Converge without derivatives, then differentiate the last two steps: the
            # derivative error shrinks like (c dtau/dq)^2 ~ 1e-6 relative, at a quarter
            # of the cost of differentiating every iteration.
            own = tuple(self.robot.parameters()) if params is None else params
            if plain_inputs(q_kin, c, g, *own, *_tensors(payload)):  # no derivative to carry
                start = kept_start(commanded)  # where these rows last settled
                q = self._settled(step, q_kin if start is None else start, start is not None)
                keep_start(commanded, q)
                return q
            detached = params  # plain values (no_grad fits): the same object keeps the
            if params is not None and not plain_inputs(*params):  # chain constants cached
                detached = type(params)(*(t.detach() for t in params))
            q = q_kin.detach()
            with torch.no_grad():
                for _ in range(COMPLIANCE_ITERATIONS - 2):
                    q = q_kin.detach() - c.detach() * self.robot.gravity_torques(
                        q, payload=payload, gravity=g.detach(), params=detached
                    )
            for _ in range(2):
                q = step(q)
        return q

    @staticmethod
    def _settled(step, q: Tensor, warm: bool = False) -> Tensor:
        """The fixed point of ``step`` from ``q``, stopped once the error left,
        estimated from the last two changes (their ratio is the contraction), is below
        :data:`COMPLIANCE_TOL_RAD`; at most :data:`COMPLIANCE_MAX_SETTLING` steps.
        ``warm``: ``q`` is where the same rows settled before (:mod:`.warm_start`):
        when the first step moves it by less than the tolerance, it is the fixed point
        within that (the step contracts its error by |c dtau/dq| ~ 1e-3) and is returned
        as it is, so the same point evaluated again gives the same values, bit for bit
        (a start within round-off of the fixed point moves by round-off, from which no
        contraction can be read)."""
        last = math.inf  # no change yet: no contraction to estimate
        for k in range(COMPLIANCE_MAX_SETTLING):
            q_new = step(q)
            change = float((q_new - q).abs().max()) if q.numel() else 0.0
            if warm and k == 0 and change <= COMPLIANCE_TOL_RAD:
                return q
            q = q_new
            rate = change / last  # 0 after the first step: not yet an estimate
            if change == 0.0 or (
                0 < rate < 0.5 and change * rate / (1 - rate) <= COMPLIANCE_TOL_RAD
            ):
                break
            last = change
        return q

    def static_wrenches(
        self, q_true: Tensor, params, cond: Conditions, gravity=None, frames=None
    ) -> Tensor:
        """``(*B, n_chain, 6)`` holding wrench of every chain joint, in its own frame
        (``frames``: the robot's link frames at ``q_true`` and ``params``, if computed)."""
        payload = 0.0 if cond.payload is None else cond.payload
        g = self.gravity_root(cond) if gravity is None else gravity
        return self.robot.static_wrenches(
            q_true, payload=payload, gravity=g, params=params, frame="joint", frames=frames
        )

    def deflected_params(
        self, q_true: Tensor, params, cond: Conditions, gravity=None, wrenches=None
    ):
        """``params`` bent by the deflection effects at ``q_true`` (unchanged without).

        ``wrenches``: precomputed :meth:`static_wrenches` (the identification Jacobian
        holds them fixed); computed from the rigid ``params`` when omitted.
        """
        bending = [e for e in self.effects if e.stage == "deflection" and not _zero(e.value)]
        if not bending:
            return params
        if wrenches is None:
            wrenches = self.static_wrenches(q_true, params, cond, gravity)
        q_chain = self.robot.chain_q(q_true)
        for e in bending:
            params = e.apply_deflection(params, wrenches, q_chain)
        return params

    # ------------------------------------------------------------------ prediction
    def end_pose(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` flange pose in the robot root frame, with every effect."""
        cond = cond or Conditions()
        q = self.robot.check_q(q)  # a list / array, or a wrong joint count, said up front
        cond.check_batch(q.shape[:-1])
        params = self.kinematic_params(cond)
        gravity = self.gravity_root(cond) if self.loaded_effects() else None
        q_true = self.joint_values(q, cond, params, gravity)
        params = self.deflected_params(q_true, params, cond, gravity)
        return self.robot.fk(q_true, params=params)

    def loaded_effects(self) -> list[Effect]:
        """The effects that read the static load (compliance, deflection): those gravity
        and its mounting act on."""
        return [e for e in self.effects if e.stage in ("compliance", "deflection")]

    def forward(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` pose of the measured point/frame in the measurement frame [m].

        ``q``: ``(*B, dof)`` commanded joints [rad or m] (a tensor, list or array);
        ``cond``: :class:`Conditions` with fields of batch ``*B`` or broadcastable.
        """
        T = self.end_pose(q, cond)
        group = None if cond is None else cond.group
        if group is None or self.base.sets == 1:
            base, tool = self.base.matrix()[0], self.tool.matrix()[0]
        else:
            base, tool = self.base.matrix(group), self.tool.matrix(group)
        return base.to(T.dtype) @ T @ tool.to(T.dtype)

"""`Robot`: the nominal geometric + static model of one serial arm.

Dimension names used throughout the package: ``B`` any leading batch shape, ``dof`` the
robot's (independent) joints, ``n_chain`` the movable joints on the chain (more than ``dof``
when some are URDF mimic joints), ``n_params`` identified parameters.

Mimic joints: the chain's joint values follow the robot's joints through the affine coupling
``q_chain = q @ A.T + b`` (:meth:`Robot.coupling`). Every public method takes and returns
the robot's joints: ``fk(q)``, ``jacobian(q) = J_chain @ A`` and ``gravity_torques(q) =
A.T tau_chain`` (virtual work; a leader off the chain gets its mimic joints' torques too).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from hybrid_pk.errors import ShapeError
from hybrid_pk.geometry import broadcast_shapes, so3_exp
from hybrid_pk.robot.aligned import AlignedFK
from hybrid_pk.robot.chain import (
    ChainTerms,
    KinematicParams,
    batch_last_terms,
    chain_terms,
    local_transforms,
    pose_jacobian_batch_last,
    product,
)
from hybrid_pk.robot.chain_spec import BranchBody, ChainSpec, load_chain_spec
from hybrid_pk.robot.dh import from_dh
from hybrid_pk.robot.statics import gravity_values

__all__ = ["STANDARD_GRAVITY", "Robot"]

STANDARD_GRAVITY = 9.80665  # [m/s^2]


class Robot(nn.Module):
    """Serial arm read from a URDF, with learnable kinematic parameters.

    Parameters (``nn.Parameter``, all differentiable together with ``q``), one per
    chain joint (``n_chain``; equal to ``dof`` without mimic joints):
        origin_xyz: ``(n_chain + 1, 3)`` [m] translation of each joint origin (and the tip).
        origin_rotvec: ``(n_chain + 1, 3)`` [rad] rotation of each origin relative to the
            URDF's, ``R = R_urdf · exp(origin_rotvec)``; zero for the nominal robot.
            (A rotation vector, not RPY, so it stays well conditioned at any pose —
            RPY is singular at pitch ±90°, which the UR10 URDF uses.)
        axis: ``(n_chain, 3)`` joint axes in their joint frames, normalised on use.

    Masses and centres of mass are buffers (the statics of :meth:`gravity_torques`).
    """

    def __init__(self, spec: ChainSpec, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.spec = spec
        f = {"dtype": dtype}
        self.origin_xyz = nn.Parameter(torch.tensor(spec.origins[:, :3, 3], **f))
        self.origin_rotvec = nn.Parameter(torch.zeros(spec.chain_dof + 1, 3, **f))
        self.axis = nn.Parameter(torch.tensor(spec.axes, **f))
        self.register_buffer("origin_rot_urdf", torch.tensor(spec.origins[:, :3, :3], **f))
        self.register_buffer("lower", torch.tensor(spec.lower, **f))
        self.register_buffer("upper", torch.tensor(spec.upper, **f))
        self.register_buffer("segment_mass", torch.tensor(spec.segment_mass, **f))
        self.register_buffer("segment_com", torch.tensor(spec.segment_com, **f))
        rev = [t in ("revolute", "continuous") for t in spec.joint_types]
        self.register_buffer("revolute", torch.tensor(rev, dtype=torch.bool))
        rev = [t in ("revolute", "continuous") for t in spec.chain_joint_types]
        self.register_buffer("chain_revolute", torch.tensor(rev, dtype=torch.bool))
        self.register_buffer("source", torch.as_tensor(spec.source, dtype=torch.long))
        self.register_buffer("multiplier", torch.tensor(spec.multiplier, **f))
        self.register_buffer("offset", torch.tensor(spec.offset, **f))
        A = torch.zeros(spec.chain_dof, spec.dof, **f)
        A[torch.arange(spec.chain_dof), self.source] = self.multiplier
        self.register_buffer("coupling_matrix", A)
        self._has_mimic = spec.has_mimic  # read on every call: not recomputed
        self._cache: dict[tuple, ChainTerms] = {}
        self._params_memo: dict[bool, tuple] = {}
        self._no_grad_fk = AlignedFK(self.chain_revolute)  # fk's path without derivatives

    def __getstate__(self) -> dict:  # caches may hold a finished transform's tensors
        return {**self.__dict__, "_cache": {}, "_params_memo": {}}

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(
        cls, urdf: str | Path, end_link: str | None = None, dtype: torch.dtype = torch.float64
    ) -> Robot:
        """Robot from a URDF path or a shipped name (``"rx160"``, ``"ur10"``).

        Args:
            urdf: URDF file or shipped robot name.
            end_link: link whose pose :meth:`fk` returns; default the single leaf link.
            dtype: of parameters and buffers; float64 (default) keeps the URDF's every digit.
                :meth:`fk` computes in the dtype of ``q`` (float32: from a cached cast).
        """
        return cls(load_chain_spec(urdf, end_link), dtype=dtype)

    from_dh = classmethod(from_dh)  # a DH / modified-DH table: hybrid_pk.robot.dh

    # ------------------------------------------------------------------ description
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def joint_names(self) -> list[str]:
        """The robot's joints (the data's columns, IK's variables), in chain order; a
        mimic joint's leader takes the place of its first mimic joint on the chain."""
        return list(self.spec.joint_names)

    @property
    def chain_joint_names(self) -> list[str]:
        """Movable joints on the chain, in chain order (mimic joints included)."""
        return list(self.spec.chain_joint_names)

    @property
    def chain_joint_types(self) -> list[str]:
        return list(self.spec.chain_joint_types)

    @property
    def chain_dof(self) -> int:
        """``n_chain``: movable joints on the chain."""
        return self.spec.chain_dof

    @property
    def has_mimic(self) -> bool:
        return self._has_mimic

    @property
    def joint_types(self) -> list[str]:
        return list(self.spec.joint_types)

    @property
    def dof(self) -> int:
        return self.spec.dof

    @property
    def end_link(self) -> str:
        return self.spec.end_link

    @property
    def root_link(self) -> str:
        return self.spec.root_link

    @property
    def joint_limits(self) -> tuple[Tensor, Tensor]:
        """``(lower, upper)``, each ``(dof,)`` [rad or m]; ``±inf`` for continuous joints."""
        return self.lower, self.upper

    @property
    def n_kinematic_params(self) -> int:
        return sum(p.numel() for p in (self.origin_xyz, self.origin_rotvec, self.axis))

    @property
    def dtype(self) -> torch.dtype:
        return self.origin_xyz.dtype

    def sample_q(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """``(n, dof)`` joint values uniform within the limits (continuous: ±pi)."""
        lo = torch.where(torch.isfinite(self.lower), self.lower, -torch.pi)
        hi = torch.where(torch.isfinite(self.upper), self.upper, torch.pi)
        u = torch.rand(n, self.dof, generator=generator, dtype=self.dtype)
        return lo + u.to(lo.device) * (hi - lo)

    # ------------------------------------------------------------------ kinematics
    def kinematic_params(self) -> KinematicParams:
        """Current kinematic parameters as plain (differentiable) tensors."""
        rot = self.origin_rot_urdf @ so3_exp(self.origin_rotvec)
        return KinematicParams(self.origin_xyz, rot, self.axis)

    def coupling(self) -> tuple[Tensor, Tensor]:
        """``(A (n_chain, dof), b (n_chain,))`` with ``q_chain = q @ A.T + b``."""
        return self.coupling_matrix, self.offset

    def chain_q(self, q: Tensor) -> Tensor:
        """Joint values of the chain's movable joints: ``(*B, dof) -> (*B, n_chain)``."""
        if not self.has_mimic:
            return q
        mul, off = self.multiplier.to(q.dtype), self.offset.to(q.dtype)
        return torch.addcmul(off, q.index_select(-1, self.source), mul)

    def chain_terms(
        self, dtype: torch.dtype | None = None, params: KinematicParams | None = None
    ) -> ChainTerms:
        """Constant matrices of the chain (see :mod:`hybrid_pk.robot.chain`), tip not
        folded; cached while the parameters do not change."""
        return self._terms(params, dtype or self.dtype)

    def _terms(
        self, params: KinematicParams | None, dtype: torch.dtype, fold_tip: bool = False
    ) -> ChainTerms:
        def build(p: KinematicParams) -> ChainTerms:
            p = KinematicParams(*(t.to(dtype) for t in p))
            return chain_terms(p, self.chain_revolute, fold_tip)

        reverse_graph = torch.is_grad_enabled() and any(t.requires_grad for t in params or ())
        if params is not None and reverse_graph:
            return build(params)
        if params is not None:
            # One-slot memo keyed on the params object (held, so its id is not reused):
            # callers passing the same parameters to several calls (fk plus gravity torques
            # of a compliance fixed point) build the constants once. Not with a reverse-mode
            # graph (a second backward would find it freed).
            memo = self._params_memo.get(fold_tip)
            if memo is not None and memo[0] is params and memo[1] == dtype:
                return memo[2]
            terms = build(params)
            self._params_memo[fold_tip] = (params, dtype, terms)
            return terms
        own = (self.origin_xyz, self.origin_rotvec, self.axis)
        if torch.is_grad_enabled() and any(p.requires_grad for p in own):
            return build(self.kinematic_params())  # a cached graph can't be reused by backward
        # Without gradients to the parameters the constant matrices are cached; the key
        # changes whenever a parameter is modified in place (its _version counter).
        key = (dtype, self.origin_xyz.device, fold_tip, *(p._version for p in own), *map(id, own))
        if key not in self._cache:
            with torch.no_grad():
                if len(self._cache) > 8:
                    self._cache.clear()
                self._cache[key] = build(self.kinematic_params())
        return self._cache[key]

    def check_q(self, q: Tensor) -> Tensor:
        """``q`` (a tensor, list or array) as a float tensor ``(*B, dof)``, else ShapeError."""
        if not isinstance(q, Tensor):
            q = torch.as_tensor(q, dtype=self.dtype, device=self.origin_xyz.device)
        if not q.is_floating_point():
            raise ShapeError(f"q must be a floating tensor, found dtype {q.dtype}")
        if q.shape[-1:] != (self.dof,):
            raise ShapeError(
                f"q must have shape (*B, {self.dof}) for joints {self.joint_names}, "
                f"found {tuple(q.shape)}"
            )
        return q

    def fk(self, q: Tensor, params: KinematicParams | None = None) -> Tensor:
        """Pose of the end link in the root frame; differentiable in ``q`` and parameters.

        Args:
            q: ``(*B, dof)`` joint values [rad or m].
            params: kinematic parameters to use instead of the robot's own (e.g. a
                perturbed copy from an error effect).

        Returns:
            ``(*B, 4, 4)`` homogeneous transforms ``T_root_end`` [m].
        """
        q = self.chain_q(self.check_q(q))
        if (T := self._no_grad_fk(self, q, params)) is not None:
            return T
        terms = self._terms(params, q.dtype, fold_tip=True)  # the tip costs no extra matmul
        return product(local_transforms(q, terms, self.chain_revolute))

    forward = fk  # robot(q) is fk(q); lets torch.func.functional_call drive the module

    def link_frames(self, q: Tensor, params: KinematicParams | None = None) -> Tensor:
        """Frames ``(*B, n_chain + 1, 4, 4)`` of every segment after its joint, and of the
        end link, at the robot's joint values ``q (*B, dof)`` [rad or m]: index ``i <
        n_chain`` is the frame of chain joint ``i + 1`` (whose origin lies on that joint's
        axis), index ``n_chain`` the end link (without derivatives: the z-aligned chain's)."""
        q = self.chain_q(self.check_q(q))
        terms = self._terms(params, q.dtype)
        if (fast := self._no_grad_fk.link_frames(terms, q)) is not None:
            return fast
        local = local_transforms(q, terms, self.chain_revolute)
        frames = [local[..., 0, :, :]]
        for i in range(1, self.chain_dof):
            frames.append(frames[-1] @ local[..., i, :, :])
        frames.append(frames[-1] @ terms.tip)
        if terms.tip.dim() > 2:  # per-sample parameters: frames may broadcast wider than q
            shape = broadcast_shapes(*(f.shape for f in frames))
            frames = [f.expand(shape) for f in frames]
        return torch.stack(frames, -3)

    def _axes_world(self, frames: Tensor, params: KinematicParams | None) -> Tensor:
        axis = self.axis if params is None else params.axis
        a = (axis / axis.norm(dim=-1, keepdim=True)).to(frames.dtype)
        return (frames[..., : self.chain_dof, :3, :3] @ a[..., None])[..., 0]  # (*B, n, 3)

    def jacobian(self, q: Tensor, params: KinematicParams | None = None) -> Tensor:
        """Geometric Jacobian of the end link: ``(*B, 6, dof)``, rows ``[v; omega]``.

        ``v`` [m/rad] is the velocity of the end-link origin, ``omega`` the angular
        velocity, both in the root frame. With mimic joints ``J = J_chain @ A``.
        Evaluated batch last (:func:`~hybrid_pk.robot.chain.pose_jacobian_batch_last`),
        differentiable.
        """
        q = self.chain_q(self.check_q(q))
        terms = self._terms(params, q.dtype)
        batch = broadcast_shapes(q.shape[:-1], terms.tip.shape[:-2])
        n = self.chain_dof
        qt = q.expand(*batch, n).reshape(-1, n).T
        _, _, J = pose_jacobian_batch_last(batch_last_terms(terms, batch), qt, self.chain_revolute)
        J = J.permute(2, 0, 1).reshape(*batch, 6, n)
        return J @ self.coupling_matrix.to(J.dtype) if self.has_mimic else J

    # ------------------------------------------------------------------ statics
    def _gravity(self, gravity, frames: Tensor) -> Tensor:
        """Gravity as ``(*G, 3)`` [m/s^2]: one vector, or one per sample."""
        g = torch.as_tensor(gravity, dtype=frames.dtype, device=frames.device)
        if g.shape[-1:] != (3,):
            raise ShapeError(f"gravity must have shape (*B, 3) [m/s^2], found {tuple(g.shape)}")
        return g

    def _subtree_loads(
        self, q: Tensor, frames: Tensor, payload: float | Tensor
    ) -> tuple[Tensor, Tensor]:
        """Mass ``(*B, n)`` [kg] and first moment about each chain joint frame's origin
        ``(*B, n, 3)`` [kg m] of everything chain joint ``i`` carries: segments ``k >= i``,
        the off-chain bodies riding on them and the payload at the end-link origin (root
        frame)."""
        dtype, n = frames.dtype, self.chain_dof
        R, p = frames[..., :, :3, :3], frames[..., :, :3, 3]
        m = self.segment_mass[1:].to(dtype)  # segments moving with chain joints 1..n
        c = (R[..., :n, :, :] @ self.segment_com[1:].to(dtype)[..., None])[..., 0]
        moment = m[:, None] * (c + p[..., :n, :])  # (*B, n, 3) m_k * c_k
        for b in self.spec.branches:
            if b.segment > 0:  # its mass rides on the chain joints before its segment
                _, lever, o = self._branch_lever(b, q, frames)
                m = m + torch.zeros_like(m).index_fill(0, torch.tensor(b.segment - 1), b.mass)
                moment = moment.index_add(
                    -2, torch.tensor([b.segment - 1]), (b.mass * (lever + o))[..., None, :]
                )
        payload = torch.as_tensor(payload, dtype=dtype, device=frames.device)
        # Suffix sums: mass and first moment carried by joint i (all segments k >= i).
        mass_out = m.flip(-1).cumsum(-1).flip(-1) + payload[..., None]
        moment_out = moment.flip(-2).cumsum(-2).flip(-2)
        moment_out = moment_out + payload[..., None, None] * p[..., n : n + 1, :]
        arm = moment_out - mass_out[..., None] * p[..., :n, :]  # sum_k m_k (c_k - o_i)
        return mass_out, arm

    def gravity_torques(
        self,
        q: Tensor,
        payload: float | Tensor = 0.0,
        gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -STANDARD_GRAVITY),
        params: KinematicParams | None = None,
    ) -> Tensor:
        """Static joint torques that hold the arm against gravity.

        Same sign as the ``g(q)`` term of ``M(q) q'' + C q' + g(q) = tau``: the torque
        each motor must apply at rest (values alone: ``statics.gravity_values``).

        Args:
            q: ``(*B, dof)`` joint values [rad or m].
            payload: mass [kg] at the end-link origin; float or ``(*B,)`` tensor.
            gravity: gravity acceleration in the root frame [m/s^2], ``(3,)`` or per
                sample ``(*B, 3)`` (a robot on a ceiling, a wall or a tilted base).
            params: kinematic parameters to use instead of the robot's own.

        Returns:
            ``(*B, dof)`` torques [Nm] (forces [N] for prismatic joints).
        """
        q = self.check_q(q)
        if (fast := gravity_values(self, q, payload, gravity, params)) is not None:
            return fast[0]
        frames = self.link_frames(q, params)
        g, dtype = self._gravity(gravity, frames), frames.dtype
        mass_out, arm = self._subtree_loads(q, frames, payload)
        gj = g[..., None, :]
        z = self._axes_world(frames, params)
        tau_rev = (z * torch.linalg.cross(gj.expand_as(arm), arm)).sum(-1)
        tau_pri = -mass_out * (z * gj).sum(-1)
        tau = torch.where(self.chain_revolute, tau_rev, tau_pri)
        if not self.has_mimic and not self.spec.branches:
            return tau
        tau = tau @ self.coupling_matrix.to(dtype)  # A.T tau_chain, per sample
        for b in self.spec.branches:
            z_b, lever, _ = self._branch_lever(b, q, frames)
            if b.joint_type == "prismatic":
                tau_b = -b.mass * (z_b * g).sum(-1).expand(lever.shape[:-1])
            else:
                tau_b = b.mass * (z_b * torch.linalg.cross(g.expand_as(lever), lever)).sum(-1)
            tau = tau.index_add(-1, torch.tensor([b.source]), b.multiplier * tau_b[..., None])
        return tau

    def _branch_lever(self, b: BranchBody, q: Tensor, frames: Tensor):
        """Axis ``z (*B, 3)`` of an off-chain joint, its body's centre of mass relative to
        the joint ``lever = c - o (*B, 3)`` and the joint's origin ``o``, root frame."""
        dtype = frames.dtype
        O = torch.as_tensor(b.origin, dtype=dtype, device=frames.device)
        F = O if b.segment == 0 else frames[..., b.segment - 1, :, :] @ O  # joint frame
        R, o = F[..., :3, :3], F[..., :3, 3]
        a = torch.as_tensor(b.axis, dtype=dtype, device=frames.device)
        com = torch.as_tensor(b.com, dtype=dtype, device=frames.device)
        qb = b.multiplier * q[..., b.source].to(dtype) + b.offset
        if b.joint_type == "prismatic":
            c_local = com + qb[..., None] * a
        else:  # Rodrigues: the centre of mass turned by qb about a
            s, k = torch.sin(qb)[..., None], (1 - torch.cos(qb))[..., None]
            axc = torch.linalg.cross(a, com)
            c_local = com + s * axc + k * torch.linalg.cross(a, axc)
        lever = (R @ c_local[..., None])[..., 0]
        return (R @ a).expand_as(lever), lever, o.expand_as(lever)

    def static_wrenches(
        self,
        q: Tensor,
        payload: float | Tensor = 0.0,
        gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -STANDARD_GRAVITY),
        params: KinematicParams | None = None,
        frame: str = "root",
        frames: Tensor | None = None,
    ) -> Tensor:
        """The full static wrench each chain joint transmits to hold what it carries.

        :meth:`gravity_torques` is its component along each joint's axis (summed over a
        leader's mimic joints); the other five components load the bearings and bend
        the links (what ``tilt_compliance`` and ``column_bending`` read). Same sign as
        pinocchio's ``data.f`` after ``rnea`` at zero velocity and acceleration: the
        wrench the parent side exerts on the subtree of chain joint ``i`` (segments
        ``k >= i``, the off-chain bodies on them and the payload).

        Args:
            q: ``(*B, dof)`` joint values [rad or m].
            payload: mass [kg] at the end-link origin; float or ``(*B,)`` tensor.
            gravity: ``(3,)`` or ``(*B, 3)`` gravity in the root frame [m/s^2].
            params: kinematic parameters to use instead of the robot's own.
            frame: ``"root"``, or ``"joint"``: each in its joint's frame (pinocchio's ``data.f``).
            frames: :meth:`link_frames` of ``q`` and ``params``, when already computed.

        Returns:
            ``(*B, n_chain, 6)``: force [N], moment [Nm] about the origin of chain joint ``i``'s
            frame (on its axis, :meth:`link_frames` index ``i``), root frame (or that frame).
        """
        if frame not in ("root", "joint"):
            raise ValueError(f"frame must be 'root' or 'joint', got {frame!r}")
        q = self.check_q(q)
        frames = self.link_frames(q, params) if frames is None else frames
        g = self._gravity(gravity, frames)[..., None, :]
        mass_out, arm = self._subtree_loads(q, frames, payload)
        force = (-mass_out[..., None] * g).expand_as(arm)
        moment = torch.linalg.cross(g.expand_as(arm), arm)  # -(arm x m g) summed
        if frame == "joint":
            Rt = frames[..., : self.chain_dof, :3, :3].transpose(-1, -2)
            force, moment = (Rt @ force[..., None])[..., 0], (Rt @ moment[..., None])[..., 0]
        return torch.cat([force, moment], -1)

    def extra_repr(self) -> str:
        chain = f", chain={self.chain_joint_names}" if self.has_mimic else ""
        return (
            f"name={self.name!r}, dof={self.dof}, joints={self.joint_names}{chain}, "
            f"end_link={self.end_link!r}, dtype={self.dtype}"
        )

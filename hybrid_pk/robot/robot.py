"""`Robot`: the nominal geometric + static model of one serial arm.

Dimension names used throughout the package: ``B`` any leading batch shape, ``dof``
actuated joints, ``n_params`` identified parameters.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from hybrid_pk.errors import ShapeError
from hybrid_pk.geometry import so3_exp
from hybrid_pk.robot.chain import (
    ChainTerms,
    KinematicParams,
    chain_terms,
    local_transforms,
    product,
)
from hybrid_pk.robot.chain_spec import ChainSpec, load_chain_spec

__all__ = ["STANDARD_GRAVITY", "Robot"]

STANDARD_GRAVITY = 9.80665  # [m/s^2]


class Robot(nn.Module):
    """Serial arm read from a URDF, with learnable kinematic parameters.

    Parameters (``nn.Parameter``, all differentiable together with ``q``):
        origin_xyz: ``(dof + 1, 3)`` [m] translation of each joint origin (and the tip).
        origin_rotvec: ``(dof + 1, 3)`` [rad] rotation of each origin relative to the
            URDF's, ``R = R_urdf · exp(origin_rotvec)``; zero for the nominal robot.
            (A rotation vector, not RPY, so it stays well conditioned at any pose —
            RPY is singular at pitch ±90°, which the UR10 URDF uses.)
        axis: ``(dof, 3)`` joint axes in their joint frames, normalised on use.

    Masses and centres of mass are buffers (the statics of :meth:`gravity_torques`).
    """

    def __init__(self, spec: ChainSpec, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.spec = spec
        f = {"dtype": dtype}
        self.origin_xyz = nn.Parameter(torch.tensor(spec.origins[:, :3, 3], **f))
        self.origin_rotvec = nn.Parameter(torch.zeros(spec.dof + 1, 3, **f))
        self.axis = nn.Parameter(torch.tensor(spec.axes, **f))
        self.register_buffer("origin_rot_urdf", torch.tensor(spec.origins[:, :3, :3], **f))
        self.register_buffer("lower", torch.tensor(spec.lower, **f))
        self.register_buffer("upper", torch.tensor(spec.upper, **f))
        self.register_buffer("segment_mass", torch.tensor(spec.segment_mass, **f))
        self.register_buffer("segment_com", torch.tensor(spec.segment_com, **f))
        revolute = [t in ("revolute", "continuous") for t in spec.joint_types]
        self.register_buffer("revolute", torch.tensor(revolute, dtype=torch.bool))
        self._cache: dict[tuple, ChainTerms] = {}
        self._params_memo: dict[bool, tuple] = {}

    def __getstate__(self) -> dict:
        # Caches may hold tensors of a finished functorch transform: never pickle them.
        state = self.__dict__.copy()
        state["_cache"], state["_params_memo"] = {}, {}
        return state

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(
        cls, urdf: str | Path, end_link: str | None = None, dtype: torch.dtype = torch.float64
    ) -> Robot:
        """Robot from a URDF path or a shipped name (``"rx160"``, ``"ur10"``).

        Args:
            urdf: URDF file or shipped robot name.
            end_link: link whose pose :meth:`fk` returns; default the single leaf link.
            dtype: floating dtype of parameters and buffers. float64 by default so
                that the URDF's figures keep every digit; :meth:`fk` computes in the
                dtype of ``q`` (a float32 ``q`` gets float32 math from a cached cast).
        """
        return cls(load_chain_spec(urdf, end_link), dtype=dtype)

    # ------------------------------------------------------------------ description
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def joint_names(self) -> list[str]:
        """Actuated joints in chain order."""
        return list(self.spec.joint_names)

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

    def pk_chain(self):
        """The pytorch-kinematics ``SerialChain`` of the same URDF and end link."""
        import pytorch_kinematics as pk

        data = Path(self.spec.urdf_path).read_bytes()
        chain = pk.build_serial_chain_from_urdf(data, self.spec.end_link, self.spec.root_link)
        return chain.to(dtype=self.dtype, device=self.origin_xyz.device)

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

    def _terms(
        self, params: KinematicParams | None, dtype: torch.dtype, fold_tip: bool = False
    ) -> ChainTerms:
        def build(p: KinematicParams) -> ChainTerms:
            return chain_terms(KinematicParams(*(t.to(dtype) for t in p)), self.revolute, fold_tip)

        reverse_graph = torch.is_grad_enabled() and any(t.requires_grad for t in params or ())
        if params is not None and reverse_graph:
            return build(params)
        if params is not None:
            # One-slot memo keyed on the params object: callers that pass the same
            # parameters to several calls (fk plus gravity torques of a compliance
            # fixed point) build the chain constants once. The entry holds the params
            # object, so its id cannot be reused while it is cached. Not used when a
            # reverse-mode graph is built (a second backward would find it freed).
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
        key = (dtype, self.origin_xyz.device, fold_tip, *(p._version for p in own))
        key += tuple(id(p) for p in own)
        if key not in self._cache:
            with torch.no_grad():
                if len(self._cache) > 8:
                    self._cache.clear()
                self._cache[key] = build(self.kinematic_params())
        return self._cache[key]

    def _check_q(self, q: Tensor) -> Tensor:
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
        """Pose of the end link in the root frame.

        Args:
            q: ``(*B, dof)`` joint values [rad or m].
            params: kinematic parameters to use instead of the robot's own (e.g. a
                perturbed copy from an error effect).

        Returns:
            ``(*B, 4, 4)`` homogeneous transforms ``T_root_end`` [m].
        """
        q = self._check_q(q)
        terms = self._terms(params, q.dtype, fold_tip=True)  # the tip costs no extra matmul
        return product(local_transforms(q, terms, self.revolute))

    forward = fk  # robot(q) is fk(q); lets torch.func.functional_call drive the module

    def link_frames(self, q: Tensor, params: KinematicParams | None = None) -> Tensor:
        """Frames of every segment after its joint, and of the end link.

        Returns:
            ``(*B, dof + 1, 4, 4)``: index ``i < dof`` is the frame of joint ``i + 1``
            (whose origin lies on that joint's axis), index ``dof`` the end link.
        """
        q = self._check_q(q)
        terms = self._terms(params, q.dtype)
        local = local_transforms(q, terms, self.revolute)
        frames = [local[..., 0, :, :]]
        for i in range(1, self.dof):
            frames.append(frames[-1] @ local[..., i, :, :])
        frames.append(frames[-1] @ terms.tip)
        if terms.tip.dim() > 2:  # per-sample parameters: frames may broadcast wider than q
            shape = torch.broadcast_shapes(*(f.shape for f in frames))
            frames = [f.expand(shape) for f in frames]
        return torch.stack(frames, -3)

    def _axes_world(self, frames: Tensor, params: KinematicParams | None) -> Tensor:
        axis = self.axis if params is None else params.axis
        a = (axis / axis.norm(dim=-1, keepdim=True)).to(frames.dtype)
        return (frames[..., : self.dof, :3, :3] @ a[..., None])[..., 0]  # (*B, dof, 3)

    def jacobian(self, q: Tensor, params: KinematicParams | None = None) -> Tensor:
        """Geometric Jacobian of the end link: ``(*B, 6, dof)``, rows ``[v; omega]``.

        ``v`` [m/rad] is the velocity of the end-link origin, ``omega`` the angular
        velocity, both in the root frame.
        """
        frames = self.link_frames(q, params)
        z = self._axes_world(frames, params)
        o = frames[..., : self.dof, :3, 3]
        p_end = frames[..., self.dof : self.dof + 1, :3, 3]
        rev = self.revolute[:, None]
        v = torch.where(rev, torch.linalg.cross(z, p_end - o), z)
        w = torch.where(rev, z, 0.0)
        return torch.cat([v, w], -1).transpose(-1, -2)

    # ------------------------------------------------------------------ statics
    def _subtree_loads(self, frames: Tensor, payload: float | Tensor) -> tuple[Tensor, Tensor]:
        """Mass ``(*B, dof)`` [kg] and first moment about each joint frame origin
        ``(*B, dof, 3)`` [kg m] of everything joint ``i`` carries (segments ``k >= i``
        and the payload at the end-link origin), root frame."""
        dtype = frames.dtype
        R, p = frames[..., :, :3, :3], frames[..., :, :3, 3]
        m = self.segment_mass[1:].to(dtype)  # segments moving with joints 1..dof
        c = (R[..., : self.dof, :, :] @ self.segment_com[1:].to(dtype)[..., None])[..., 0]
        moment = m[:, None] * (c + p[..., : self.dof, :])  # (*B, dof, 3) m_k * c_k
        payload = torch.as_tensor(payload, dtype=dtype, device=frames.device)
        # Suffix sums: mass and first moment carried by joint i (all segments k >= i).
        mass_out = m.flip(-1).cumsum(-1).flip(-1) + payload[..., None]
        moment_out = moment.flip(-2).cumsum(-2).flip(-2)
        moment_out = moment_out + payload[..., None, None] * p[..., self.dof : self.dof + 1, :]
        arm = moment_out - mass_out[..., None] * p[..., : self.dof, :]  # sum_k m_k (c_k - o_i)
        return mass_out, arm

    def _gravity(self, gravity, frames: Tensor) -> Tensor:
        """Gravity as ``(*G, 1, 3)``, broadcastable against per-joint vectors."""
        g = torch.as_tensor(gravity, dtype=frames.dtype, device=frames.device)
        if g.shape[-1:] != (3,):
            raise ShapeError(f"gravity must have shape (*B, 3) [m/s^2], found {tuple(g.shape)}")
        return g[..., None, :]

    def gravity_torques(
        self,
        q: Tensor,
        payload: float | Tensor = 0.0,
        gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -STANDARD_GRAVITY),
        params: KinematicParams | None = None,
    ) -> Tensor:
        """Static joint torques that hold the arm against gravity.

        Same sign as the ``g(q)`` term of ``M(q) q'' + C q' + g(q) = tau``: the torque
        each motor must apply at rest.

        Args:
            q: ``(*B, dof)`` joint values [rad or m].
            payload: mass [kg] at the end-link origin; float or ``(*B,)`` tensor.
            gravity: gravity acceleration in the root frame [m/s^2], ``(3,)`` or per
                sample ``(*B, 3)`` (a robot on a ceiling, a wall or a tilted base).
            params: kinematic parameters to use instead of the robot's own.

        Returns:
            ``(*B, dof)`` torques [Nm] (forces [N] for prismatic joints).
        """
        frames = self.link_frames(q, params)
        g = self._gravity(gravity, frames)
        mass_out, arm = self._subtree_loads(frames, payload)
        z = self._axes_world(frames, params)
        tau_rev = (z * torch.linalg.cross(g.expand_as(arm), arm)).sum(-1)
        tau_pri = -mass_out * (z * g).sum(-1)
        return torch.where(self.revolute, tau_rev, tau_pri)

    def static_wrenches(
        self,
        q: Tensor,
        payload: float | Tensor = 0.0,
        gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -STANDARD_GRAVITY),
        params: KinematicParams | None = None,
        frame: str = "root",
    ) -> Tensor:
        """The full static wrench each joint transmits to hold what it carries.

        :meth:`gravity_torques` is its component along each joint's axis; the other
        five components load the bearings and bend the links (what
        ``tilt_compliance`` and ``column_bending`` read). Same sign as pinocchio's
        ``data.f`` after ``rnea`` at zero velocity and acceleration: the wrench the
        parent side exerts on the subtree of joint ``i`` (segments ``k >= i`` and the
        payload).

        Args:
            q: ``(*B, dof)`` joint values [rad or m].
            payload: mass [kg] at the end-link origin; float or ``(*B,)`` tensor.
            gravity: ``(3,)`` or ``(*B, 3)`` gravity in the root frame [m/s^2].
            params: kinematic parameters to use instead of the robot's own.
            frame: ``"root"``, or ``"joint"``: each wrench in its own joint's frame
                (pinocchio's ``data.f`` convention).

        Returns:
            ``(*B, dof, 6)``: force [N] then moment [Nm] about the origin of joint
            ``i``'s frame (on its axis, :meth:`link_frames` index ``i``), both in the
            root frame (or that joint frame).
        """
        if frame not in ("root", "joint"):
            raise ValueError(f"frame must be 'root' or 'joint', got {frame!r}")
        frames = self.link_frames(q, params)
        g = self._gravity(gravity, frames)
        mass_out, arm = self._subtree_loads(frames, payload)
        force = (-mass_out[..., None] * g).expand_as(arm)
        moment = torch.linalg.cross(g.expand_as(arm), arm)  # -(arm x m g) summed
        if frame == "joint":
            Rt = frames[..., : self.dof, :3, :3].transpose(-1, -2)
            force, moment = (Rt @ force[..., None])[..., 0], (Rt @ moment[..., None])[..., 0]
        return torch.cat([force, moment], -1)

    def extra_repr(self) -> str:
        return (
            f"name={self.name!r}, dof={self.dof}, joints={self.joint_names}, "
            f"end_link={self.end_link!r}, dtype={self.dtype}"
        )


def to_numpy(x: Tensor) -> np.ndarray:
    """Detached float64 numpy copy (for reports and JSON)."""
    return x.detach().cpu().to(torch.float64).numpy()

"""`HybridFK`: a base model (nominal or calibrated) corrected by two residual networks.

Composition (all differentiable w.r.t. ``q``)::

    E  = base.end_pose(q, cond)                       flange in the robot root frame
    R1 = axes of the frame joint 1 moves (nominal robot at the commanded q)
    E* = [exp(R1 w dw(u)) R_E | p_E + R1 w dp(u)]    corrected flange pose
    T  = T_meas_root · E* · T_end_point               measured point, measurement frame

``u`` are the joints normalised to [-1, 1] over the input range (the full joint limits,
paper 4.1, or the range of the training data, paper 4.2); ``dp`` [m] and ``dw`` [rad,
axis-angle] are the position and orientation networks' outputs times their output
scales, in the axes of joint 1's frame.

Why these choices:

- The *flange* pose is corrected in robot coordinates, so the networks do not depend
  on the base and tool frames: a re-fitted tracker or tool frame (``calibrate
  --refit``) leaves them valid, and the frame sets of several files share them.
- Joint 1's axes: every error that arises downstream of joint 1 (gravity deflection
  when joint 1 is vertical, link and joint errors of joints 2..n) turns rigidly with
  joint 1, so in these axes it does not depend on ``q1``; in root axes the networks
  would have to learn that rotation too (on the RX160 acceptance data: 1.4 x lower
  error after 30 epochs).
- ``w(q)`` in [0, 1] is the trust of the networks: 1 inside the joint box of the
  training data, 0 outside it by default (the base model, as the paper restricts its
  networks to the training range), or falling smoothly (C¹) to 0 within ``fade`` x
  the box size outside it. On the real UR10 a 10 % fade made the orientation worse
  on held-out rows just outside the box while helping on average further out, so the
  safe fall-back is the default and the fade is opt-in.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
from torch import Tensor, nn

from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import ModelFileError
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.hybrid.nets import build_net

__all__ = [
    "NETWORKS_FORMAT",
    "NETWORKS_VERSION",
    "HybridFK",
    "InputBox",
    "ResidualHead",
    "correction_axes",
    "frame_matrices",
]

NETWORKS_FORMAT = "hybrid_pk.residual_networks"
NETWORKS_VERSION = 1
DEFAULT_FADE = 0.0  # fade-out width outside the training box, fraction of its size


def _finite_limits(lower: Tensor, upper: Tensor) -> tuple[Tensor, Tensor]:
    """Limits with ``±inf`` (continuous joints) replaced by ``±pi``."""
    pi = torch.full_like(lower, torch.pi)
    return torch.where(torch.isfinite(lower), lower, -pi), torch.where(
        torch.isfinite(upper), upper, pi
    )


class InputBox(nn.Module):
    """Input normalisation and trust region of the networks.

    Buffers (each ``(dof,)``, joint units [rad or m]):
        lower, upper: range mapped to [-1, 1] (joint limits or the data's range).
        trust_lower, trust_upper: joint box of the training data.

    Args:
        lower, upper: normalisation range.
        trust_lower, trust_upper: training-data box (default: the normalisation range).
        fade: width of the fade-out outside the box, as a fraction of its size per joint.
    """

    def __init__(
        self,
        lower: Tensor,
        upper: Tensor,
        trust_lower: Tensor | None = None,
        trust_upper: Tensor | None = None,
        fade: float = DEFAULT_FADE,
    ) -> None:
        super().__init__()
        lower, upper = _finite_limits(lower.to(torch.float64), upper.to(torch.float64))
        if not bool((upper > lower).all()):
            raise ValueError(f"input range needs upper > lower per joint, got {lower}, {upper}")
        tl = lower if trust_lower is None else trust_lower.to(torch.float64)
        tu = upper if trust_upper is None else trust_upper.to(torch.float64)
        self.register_buffer("lower", lower.clone())
        self.register_buffer("upper", upper.clone())
        self.register_buffer("trust_lower", tl.clone())
        self.register_buffer("trust_upper", tu.clone())
        self.fade = float(fade)

    @classmethod
    def from_data(cls, q: Tensor, limits: tuple[Tensor, Tensor] | None, fade: float) -> InputBox:
        """Box of the training joints ``q (N, dof)``; normalised over ``limits`` if given
        (paper 4.1), else over the data's own range (paper 4.2)."""
        lo, hi = q.min(0).values, q.max(0).values
        hi = torch.where(hi > lo, hi, lo + 1e-6)  # a joint that never moved
        if limits is None:
            return cls(lo, hi, fade=fade)
        return cls(*limits, trust_lower=lo, trust_upper=hi, fade=fade)

    def normalise(self, q: Tensor) -> Tensor:
        """``(*B, dof)`` joints -> ``(*B, dof)`` in [-1, 1] over the range (beyond it outside)."""
        lo, hi = self.lower.to(q.dtype), self.upper.to(q.dtype)
        return 2 * (q - lo) / (hi - lo) - 1

    def trust(self, q: Tensor) -> Tensor:
        """``(*B,)`` weight of the network corrections: 1 inside the training box, 0 beyond
        ``fade`` x its size, ``(1 - r²)²`` in between (``r``: distance outside the box in
        units of the fade width), which is C¹ at both ends."""
        lo, hi = self.trust_lower.to(q.dtype), self.trust_upper.to(q.dtype)
        width = (self.fade * (hi - lo)).clamp_min(1e-9)
        outside = (torch.relu(lo - q) + torch.relu(q - hi)) / width
        r2 = (outside * outside).sum(-1)
        return (1 - r2).clamp_min(0) ** 2

    def extra_repr(self) -> str:
        return f"dof={self.lower.numel()}, fade={self.fade}"


class ResidualHead(nn.Module):
    """A network and the scale of its output: ``(N, dof) u -> (N, 3)`` in physical units.

    The network predicts in units of ``scale (3,)`` (the RMS of its training targets,
    e.g. tens of µm), so its outputs are O(1) whatever the size of the residual.

    Args:
        arch: architecture name (:func:`~hybrid_pk.hybrid.nets.build_net`).
        dof: number of inputs.
        scale: ``(3,)`` output unit [m or rad].
        zero_init: start with a zero output layer (the hybrid starts as the base model).
    """

    def __init__(self, arch: str, dof: int, scale: Tensor, zero_init: bool = False) -> None:
        super().__init__()
        self.arch = arch
        self.net = build_net(arch, dof, 3)
        self.register_buffer("scale", scale.detach().to(torch.float64).reshape(3).clone())
        if zero_init:
            last = [m for m in self.net.modules() if isinstance(m, nn.Linear)][-1]
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    @property
    def net_dtype(self) -> torch.dtype:
        return next(self.net.parameters()).dtype

    def forward(self, u: Tensor) -> Tensor:
        """``(*B, dof)`` normalised joints -> ``(*B, 3)`` correction [m or rad], dtype of ``u``."""
        batch = u.shape[:-1]
        out = self.net(u.reshape(-1, u.shape[-1]).to(self.net_dtype))
        return out.to(u.dtype).reshape(*batch, 3) * self.scale.to(u.dtype)

    def extra_repr(self) -> str:
        return f"arch={self.arch!r}"


def correction_axes(base: ExtendedModel, q: Tensor) -> Tensor:
    """``(*B, 3, 3)`` axes of the network corrections: joint 1's frame in the root frame
    (nominal robot at the commanded ``q (*B, dof)``)."""
    return base.robot.link_frames(q)[..., 0, :3, :3]


def frame_matrices(model: ExtendedModel, cond: Conditions | None) -> tuple[Tensor, Tensor]:
    """Base ``T_meas_root`` and tool ``T_end_point`` of each row: ``(4, 4)`` when shared,
    ``(*B, 4, 4)`` when rows pick their frame set with ``cond.group``."""
    group = None if cond is None else cond.group
    if group is None or model.base.sets == 1:
        return model.base.matrix()[0], model.tool.matrix()[0]
    return model.base.matrix(group), model.tool.matrix(group)


class HybridFK(nn.Module):
    """Base model + position and orientation residual networks.

    Args:
        base: the nominal or calibrated model (frames + effects); not trained here.
        box: input normalisation and trust region.
        position: head predicting the flange position correction ``dp`` [m], or None.
        orientation: head predicting the flange rotation correction ``dw`` [rad], or
            None (position-only data).
    """

    def __init__(
        self,
        base: ExtendedModel,
        box: InputBox,
        position: ResidualHead | None,
        orientation: ResidualHead | None,
    ) -> None:
        super().__init__()
        if box.lower.numel() != base.robot.dof:
            raise ValueError(f"input box has {box.lower.numel()} joints, robot {base.robot.dof}")
        self.base = base
        self.box = box
        self.position = position
        self.orientation = orientation

    @classmethod
    def build(
        cls,
        base: ExtendedModel,
        box: InputBox,
        position_net: str | None,
        orientation_net: str | None,
        position_scale: Tensor | None = None,
        orientation_scale: Tensor | None = None,
        zero_init: bool = False,
    ) -> HybridFK:
        """Fresh networks of the named architectures (None: no such network).

        Args:
            position_scale, orientation_scale: ``(3,)`` output units [m], [rad]
                (default 1 mm and 1 mrad).
        """
        default = torch.full((3,), 1e-3, dtype=torch.float64)

        def head(arch: str | None, scale: Tensor | None) -> ResidualHead | None:
            if arch is None:
                return None
            return ResidualHead(
                arch, base.robot.dof, default if scale is None else scale, zero_init
            )

        return cls(
            base, box, head(position_net, position_scale), head(orientation_net, orientation_scale)
        )

    # ------------------------------------------------------------------ prediction
    def networks(self) -> nn.ModuleDict:
        """The trainable heads by name (``position``, ``orientation``)."""
        heads = {"position": self.position, "orientation": self.orientation}
        return nn.ModuleDict({k: v for k, v in heads.items() if v is not None})

    def trust(self, q: Tensor) -> Tensor:
        """``(*B,)`` weight in [0, 1] of the corrections at ``q`` (1: inside the training box)."""
        return self.box.trust(q)

    def correction_axes(self, q: Tensor) -> Tensor:
        """``(*B, 3, 3)`` rotation of joint 1's frame in the root frame: the axes of the
        corrections (nominal robot, commanded ``q``)."""
        return correction_axes(self.base, q)

    def corrections(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Flange corrections at ``q (*B, dof)``, already weighted by :meth:`trust`.

        Returns:
            ``dp (*B, 3)`` [m] and ``dw (*B, 3)`` [rad] in the axes of
            :meth:`correction_axes`, dtype of ``q``.
        """
        u = self.box.normalise(q)
        w = self.box.trust(q)[..., None]
        zero = torch.zeros(*q.shape[:-1], 3, dtype=q.dtype, device=q.device)
        dp = zero if self.position is None else w * self.position(u)
        dw = zero if self.orientation is None else w * self.orientation(u)
        return dp, dw

    def end_pose(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` corrected flange pose in the robot root frame."""
        E = self.base.end_pose(q, cond)
        q = q.to(E.dtype)
        dp, dw = self.corrections(q)
        R1 = self.correction_axes(q)
        dp, dw = (R1 @ dp[..., None])[..., 0], (R1 @ dw[..., None])[..., 0]
        return transform(so3_exp(dw) @ E[..., :3, :3], E[..., :3, 3] + dp)

    def forward(self, q: Tensor, cond: Conditions | None = None) -> Tensor:
        """``(*B, 4, 4)`` pose of the measured point/frame in the measurement frame."""
        E = self.end_pose(q, cond)
        base, tool = frame_matrices(self.base, cond)
        return base.to(E.dtype) @ E @ tool.to(E.dtype)

    # ------------------------------------------------------------------ model file
    def state(self, metadata: dict | None = None) -> dict:
        """The ``networks`` entry of a model file (tensors and plain data only).

        Format::

            {"format": NETWORKS_FORMAT, "version": 1, "joint_names": [...],
             "frame": "flange origin, joint-1 axes",
             "input": {"lower", "upper", "trust_lower", "trust_upper" (dof,) tensors,
                       "fade": float},
             "position" / "orientation": {"arch": str, "scale": (3,) tensor,
                                          "dtype": str, "state_dict": {...}} or None,
             "training": {...}}
        """

        def head(h: ResidualHead | None) -> dict | None:
            if h is None:
                return None
            sd = OrderedDict((k, v.detach().cpu().clone()) for k, v in h.net.state_dict().items())
            return {
                "arch": h.arch,
                "scale": h.scale.detach().cpu().clone(),
                "dtype": str(h.net_dtype).removeprefix("torch."),
                "state_dict": sd,
            }

        box = self.box
        return {
            "format": NETWORKS_FORMAT,
            "version": NETWORKS_VERSION,
            "joint_names": list(self.base.robot.joint_names),
            "frame": "flange origin, joint-1 axes",
            "input": {
                "lower": box.lower.cpu().clone(),
                "upper": box.upper.cpu().clone(),
                "trust_lower": box.trust_lower.cpu().clone(),
                "trust_upper": box.trust_upper.cpu().clone(),
                "fade": box.fade,
            },
            "position": head(self.position),
            "orientation": head(self.orientation),
            "training": dict(metadata or {}),
        }

    @classmethod
    def from_state(cls, base: ExtendedModel, state: dict, source: str = "model file") -> HybridFK:
        """Rebuild from :meth:`state` on ``base`` (the model file's extended model).

        Raises:
            ModelFileError: not a networks entry, a newer version, or networks made for
                other joints than ``base``'s robot.
        """
        if not isinstance(state, dict) or state.get("format") != NETWORKS_FORMAT:
            raise ModelFileError(f"{source}: its networks are not hybrid_pk residual networks")
        if int(state.get("version", 0)) > NETWORKS_VERSION:
            raise ModelFileError(
                f"{source}: residual networks of format version {state['version']}; this "
                f"hybrid_pk reads up to {NETWORKS_VERSION}: upgrade hybrid_pk"
            )
        joints = list(state["joint_names"])
        if joints != list(base.robot.joint_names):
            raise ModelFileError(
                f"{source}: its residual networks were trained for joints {joints}, the "
                f"model's robot {base.robot.name!r} has {base.robot.joint_names}"
            )
        inp = state["input"]
        box = InputBox(
            inp["lower"], inp["upper"], inp["trust_lower"], inp["trust_upper"], inp["fade"]
        )
        heads = {}
        for name in ("position", "orientation"):
            entry = state.get(name)
            if entry is None:
                heads[name] = None
                continue
            h = ResidualHead(entry["arch"], base.robot.dof, entry["scale"])
            h.net.to(getattr(torch, entry.get("dtype", "float32")))
            try:
                h.net.load_state_dict(entry["state_dict"])
            except RuntimeError as exc:
                raise ModelFileError(
                    f"{source}: the {name} network does not match its architecture "
                    f"{entry['arch']!r}: {' '.join(str(exc).split())[:200]}"
                ) from exc
            heads[name] = h
        model = cls(base, box, heads["position"], heads["orientation"])
        return model.eval()

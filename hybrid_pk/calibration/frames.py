"""Known and guessed frames, and the prior that holds what the data leave free.

Every fit estimates ``T_meas = B · F(q) · X``: the base ``B = T_meas_root`` (where the
tracker stands) and the tool ``X = T_end_point`` (where the target sits on the flange).
When the flange orientation barely varies, ``B`` and ``X`` trade off: moving the target
by ``d`` on the flange and the tracker by ``-R_B R_F d`` leaves every point where it
was. A plain least-squares fit walks along that valley to wherever the unmodelled
errors push it (kilometre-scale tools on ISO-cube data). Here:

- :class:`FrameSpec` holds a frame the user knows (``--tool X,Y,Z[,RX,RY,RZ]``,
  ``--base ...``): fixed (not fitted), or a ``seed:`` that starts the fit and is the
  centre of the prior;
- :class:`FramePriors` is the prior of every fit of frames, written as extra residual
  rows that are linear in the fitted offsets (a Gaussian prior, i.e. Tikhonov). Each
  frame is held towards its known value or else towards where the fit started, the
  tool translation with a std of ``DEFAULT_TOOL_STD_M``, base and rotations with wider
  ones. Where the fit starts from the closed-form registration, the components the
  data do not determine are at the flange origin (the registration's ridge, see
  :mod:`hybrid_pk.geometry.registration`), so that is where they stay; the others
  start at the data's estimate, so the prior does not pull them. A well-determined
  frame does not notice the prior (its data carry ~1e6 times the prior's information);
  an undetermined one stays instead of walking. A frame equivalent to an effect (the
  tool translation along the last joint axis and that joint's link length) is not
  pulled away from its start either, so the effect is not pushed to absorb it.

Values are metres and radians; rotations of specs are URDF roll-pitch-yaw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import rpy_to_matrix, so3_log, transform

if TYPE_CHECKING:
    from hybrid_pk.calibration.problem import ParamBlock

__all__ = [
    "BASE_TRANSLATION_STD_M",
    "DEFAULT_TOOL_STD_M",
    "MAX_TOOL_TRANSLATION_M",
    "ROTATION_STD_RAD",
    "SEED_STD_M",
    "SEED_STD_RAD",
    "Centre",
    "FramePriors",
    "FrameSpec",
    "PriorRows",
    "parse_frame_spec",
    "prior_centres",
    "prior_residual",
]

# Prior std of the tool translation around its centre (the flange origin unless known):
# tracker targets and tool points sit within a few decimetres of the flange.
DEFAULT_TOOL_STD_M = 0.1
# Largest credible tool translation [m]: no tracker target on a flange sits farther.
MAX_TOOL_TRANSLATION_M = 0.5
# Wide priors that only hold directions no data constrain, around the fit's start.
BASE_TRANSLATION_STD_M = 1.0
ROTATION_STD_RAD = 1.0
# Prior std around a seed (a mount drawing is good to a few millimetres).
SEED_STD_M = 5e-3
SEED_STD_RAD = 0.02

_LABELS = {
    ("tool", "translation"): "tool_frame.translation",
    ("tool", "rotation"): "tool_frame.rotation",
    ("base", "translation"): "base_frame.translation",
    ("base", "rotation"): "base_frame.rotation",
}


@dataclass(frozen=True)
class FrameSpec:
    """Values of one frame known from outside the data (a drawing, a previous model).

    Attributes:
        translation: ``(3,)`` [m].
        rotation: ``(3, 3)``, or None when only the translation is known.
        fixed: True: the given components are not fitted; False: they start the fit and
            are the centre of its prior (``std_m``, ``std_rad``).
        std_m, std_rad: prior std around the values when not fixed.
        source: where the values come from, for messages (``--tool``).
    """

    translation: Tensor
    rotation: Tensor | None = None
    fixed: bool = True
    std_m: float = SEED_STD_M
    std_rad: float = SEED_STD_RAD
    source: str = "--tool"

    def matrix(self, current: Tensor) -> Tensor:
        """``(4, 4)``: these values, the rotation of ``current`` where none is given."""
        R = current[:3, :3] if self.rotation is None else self.rotation.to(current.dtype)
        return transform(R, self.translation.to(current.dtype))


@dataclass(frozen=True)
class FramePriors:
    """Known frames and the prior of every frame fit.

    Attributes:
        tool, base: frames known from outside the data, or None.
        tool_std_m: prior std of the tool translation around the fit's start when no
            tool is given [m].
        base_std_m: prior std of the base translation around the fit's start [m].
        rotation_std_rad: prior std of base and tool rotations around the fit's start.
        max_tool_m: a fitted tool translation beyond this is implausible [m].

    ``math.inf`` for a std removes that prior (a plain least-squares fit).
    """

    tool: FrameSpec | None = None
    base: FrameSpec | None = None
    tool_std_m: float = DEFAULT_TOOL_STD_M
    base_std_m: float = BASE_TRANSLATION_STD_M
    rotation_std_rad: float = ROTATION_STD_RAD
    max_tool_m: float = MAX_TOOL_TRANSLATION_M

    def fixed_labels(self) -> tuple[str, ...]:
        """Block labels (``tool_frame.translation``, ...) that fits must not touch."""
        out = []
        for name, spec in (("tool", self.tool), ("base", self.base)):
            if spec is not None and spec.fixed:
                out.append(_LABELS[(name, "translation")])
                if spec.rotation is not None:
                    out.append(_LABELS[(name, "rotation")])
        return tuple(out)


def parse_frame_spec(text: str, option: str = "--tool") -> FrameSpec:
    """``X,Y,Z[,RX,RY,RZ]`` [m, rad roll-pitch-yaw], optionally ``seed:`` first.

    Raises:
        HybridPKError: for anything else, naming ``option``.
    """
    raw = text.strip()
    fixed = not raw.lower().startswith("seed:")
    body = raw if fixed else raw[5:]
    usage = (
        f"{option}: expected X,Y,Z or X,Y,Z,RX,RY,RZ (metres, then roll-pitch-yaw in "
        f"radians), fixed as given or after 'seed:' to start the fit there, got {text!r}"
    )
    try:
        values = [float(v) for v in body.split(",")]
    except ValueError:
        raise HybridPKError(usage) from None
    if len(values) not in (3, 6) or not all(math.isfinite(v) for v in values):
        raise HybridPKError(usage)
    v = torch.tensor(values, dtype=torch.float64)
    rotation = rpy_to_matrix(v[3:]) if len(values) == 6 else None
    return FrameSpec(v[:3], rotation, fixed=fixed, source=option)


class Centre(NamedTuple):
    """Prior of one frame block: ``value (G, 3)`` (translations [m]) or ``(G, 3, 3)``
    (rotations), and its std [m or rad]."""

    value: Tensor
    std: float


def prior_centres(
    model: ExtendedModel, blocks: tuple[ParamBlock, ...], priors: FramePriors | None
) -> dict[str, Centre]:
    """Where the prior of each fitted frame block is centred, taken at the fit's start."""
    priors = priors or FramePriors()
    out = {}
    for b in blocks:
        if not b.name.startswith(("base.", "tool.")):
            continue
        which, kind = b.name.split(".")
        frame = getattr(model, which)
        spec = getattr(priors, which)
        current = frame.matrix().detach()  # (G, 4, 4)
        if kind == "dp":
            if spec is not None:
                value = spec.translation.to(current.dtype).expand(frame.sets, 3)
                out[b.name] = Centre(value.clone(), spec.std_m)
            elif which == "tool":
                out[b.name] = Centre(current[:, :3, 3].clone(), priors.tool_std_m)
            else:
                out[b.name] = Centre(current[:, :3, 3].clone(), priors.base_std_m)
        elif spec is not None and spec.rotation is not None:
            value = spec.rotation.to(current.dtype).expand(frame.sets, 3, 3)
            out[b.name] = Centre(value.clone(), spec.std_rad)
        else:
            out[b.name] = Centre(current[:, :3, :3].clone(), priors.rotation_std_rad)
    return out


class PriorRows:
    """The frame prior as extra residual rows of a fit (``Problem(extra=...)``):
    ``theta -> (A theta - b, A)`` in units of the prior std, linear in the scaled
    offsets ``theta`` from the model's *current* values (``b`` is read from the model
    at each call, so one instance serves every pass of a fit).

    Translation ``p = p0 + dp + theta s`` gives ``(p - c) / std``; rotation
    ``R0 exp(w + theta s)`` gives ``(w + theta s - log(R0^T C)) / std`` (first order).

    Attributes:
        A: ``(k, n)`` constant rows (``scale / std`` on the prior's parameters).
    """

    def __init__(
        self, model: ExtendedModel, blocks: tuple[ParamBlock, ...], centres: dict[str, Centre]
    ) -> None:
        self.model, self.centres = model, centres
        n = sum(b.size for b in blocks)
        dtype = model.robot.dtype
        rows, self._parts, start = [], [], 0
        for b in blocks:
            idx = slice(start, start + b.size)
            start += b.size
            if b.name not in centres:
                continue
            A = torch.zeros(b.size, n, dtype=dtype)
            A[:, idx] = torch.eye(b.size, dtype=dtype) * (b.scale / centres[b.name].std)
            rows.append(A)
            self._parts.append(b.name)
        self.A = torch.cat(rows) if rows else torch.zeros(0, n, dtype=dtype)

    def gap(self) -> Tensor:
        """``b``: (centre - current value) / std of every prior row."""
        out = []
        for name in self._parts:
            which, kind = name.split(".")
            frame = getattr(self.model, which)
            centre = self.centres[name]
            if kind == "dp":
                now = (frame.T0[:, :3, 3] + frame.dp).detach()
                gap = centre.value.to(now.dtype) - now  # (G, 3)
            else:
                now = frame.rotvec.detach()
                R0 = frame.T0[:, :3, :3]
                gap = so3_log(R0.transpose(-1, -2) @ centre.value.to(now.dtype)) - now
            out.append(gap.reshape(-1) / centre.std)
        return torch.cat(out) if out else torch.zeros(0, dtype=self.A.dtype)

    def __call__(self, theta: Tensor) -> tuple[Tensor, Tensor]:
        return self.A @ theta - self.gap(), self.A


def prior_residual(
    model: ExtendedModel, blocks: tuple[ParamBlock, ...], centres: dict[str, Centre]
) -> PriorRows | None:
    """The prior rows of the frame blocks among ``blocks`` (None without any)."""
    rows = PriorRows(model, blocks, centres)
    return rows if rows.A.shape[0] else None

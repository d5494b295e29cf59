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

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import nearest_rotation, quat_to_matrix, rpy_to_matrix, so3_log, transform
from hybrid_pk.geometry.registration import kabsch, register_frames

if TYPE_CHECKING:
    from hybrid_pk.calibration.fit import ParamBlock

__all__ = [
    "BASE_TRANSLATION_STD_M",
    "DEFAULT_TOOL_STD_M",
    "MAX_TOOL_TRANSLATION_M",
    "ROTATION_STD_RAD",
    "SEED_STD_M",
    "SEED_STD_RAD",
    "FramePriors",
    "FrameSpec",
    "PriorRows",
    "initialise_frames",
    "initialise_with_priors",
    "parse_frame_spec",
    "prior_centres",
    "prior_rows",
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


@torch.no_grad()
def initialise_frames(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    which: str = "frames",
) -> None:
    """Set base and/or tool frames to the closed-form registration of ``data``.

    Args:
        which: ``"frames"`` (both), ``"base"`` or ``"tool"``.
    """
    T_end = model.end_pose(data.q, cond)
    R_meas = None if data.quat is None else quat_to_matrix(data.quat)
    groups = [None] if model.base.sets == 1 or cond.group is None else range(model.base.sets)
    for g in groups:
        rows = slice(None) if g is None else cond.group == g
        if g is not None and not bool(rows.any()):
            continue
        base, tool = register_frames(
            T_end[rows], data.position[rows], None if R_meas is None else R_meas[rows]
        )
        if which in ("frames", "base"):
            model.base.reset_to(base, g)
        if which in ("frames", "tool"):
            model.tool.reset_to(tool, g)


def _register_base_to_tool(model: ExtendedModel, data: MeasuredData, cond: Conditions) -> None:
    """Closed-form base for the model's current tool: Kabsch of the predicted points."""
    with torch.no_grad():
        T_end = model.end_pose(data.q, cond)
        groups = [None] if model.base.sets == 1 or cond.group is None else range(model.base.sets)
        for g in groups:
            rows = slice(None) if g is None else cond.group == g
            if g is not None and not bool(rows.any()):
                continue
            X = model.tool.matrix()[0 if g is None else g].to(T_end.dtype)
            points = (T_end[rows] @ X)[:, :3, 3]
            R, p = kabsch(points, data.position[rows])
            model.base.reset_to(transform(R, p), g)


def _register_tool_to_base(model: ExtendedModel, data: MeasuredData, cond: Conditions) -> None:
    """Closed-form tool for the model's current base: linear in its translation."""
    with torch.no_grad():
        T_end = model.end_pose(data.q, cond)
        groups = [None] if model.tool.sets == 1 or cond.group is None else range(model.tool.sets)
        for g in groups:
            rows = slice(None) if g is None else cond.group == g
            if g is not None and not bool(rows.any()):
                continue
            B = model.base.matrix()[0 if g is None else g].to(T_end.dtype)
            R_F, p_F = T_end[rows, :3, :3], T_end[rows, :3, 3]
            A = B[:3, :3] @ R_F  # (n, 3, 3): p_meas = p_B + R_B p_F + (R_B R_F) p_X
            rhs = data.position[rows] - B[:3, 3] - p_F @ B[:3, :3].T
            p_X = torch.linalg.lstsq(A.reshape(-1, 3), rhs.reshape(-1, 1)).solution[:, 0]
            R_X = model.tool.matrix()[0 if g is None else g, :3, :3].to(T_end.dtype)
            if data.quat is not None:
                R_meas = quat_to_matrix(data.quat[rows])
                M = (R_F.transpose(-1, -2) @ B[:3, :3].T @ R_meas).sum(0)
                R_X = nearest_rotation(M)
            model.tool.reset_to(transform(R_X, p_X), g)


def initialise_with_priors(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    priors: FramePriors | None,
    which: str = "frames",
) -> None:
    """Registration of the ``which`` frames that respects known ones.

    The closed-form registration of both frames, then a given tool (fixed or seed)
    replaces the registered one and the base is registered again to it; a given base
    likewise, with the tool registered to it.

    Args:
        which: ``"frames"``, ``"base"`` or ``"tool"``: the frames to be fitted.
    """
    initialise_frames(model, data, cond, which)
    if priors is None:
        return
    with torch.no_grad():
        if priors.base is not None:
            for g in range(model.base.sets):
                model.base.reset_to(priors.base.matrix(model.base.matrix()[g].detach()), g)
        if priors.tool is not None:
            for g in range(model.tool.sets):
                model.tool.reset_to(priors.tool.matrix(model.tool.matrix()[g].detach()), g)
    if priors.tool is not None and priors.base is None and which in ("frames", "base"):
        _register_base_to_tool(model, data, cond)
    elif priors.base is not None and priors.tool is None and which in ("frames", "tool"):
        _register_tool_to_base(model, data, cond)


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


class PriorRows(NamedTuple):
    """Prior residual rows ``A theta - b`` (in units of the prior std), linear in the
    scaled parameter offsets ``theta`` of a problem.

    Attributes:
        A: ``(k, n)``.
        b: ``(k,)``.
    """

    A: Tensor
    b: Tensor

    def residual(self, theta: Tensor) -> Tensor:
        return self.A @ theta - self.b


def prior_rows(
    model: ExtendedModel, blocks: tuple[ParamBlock, ...], centres: dict[str, Centre]
) -> PriorRows | None:
    """The prior rows of the frame blocks among ``blocks``, at the model's current values.

    Translation ``p = p0 + dp + theta s`` gives ``(p - c) / std``; rotation
    ``R0 exp(w + theta s)`` gives ``(w + theta s - log(R0^T C)) / std`` (first order).
    """
    n = sum(b.size for b in blocks)
    rows_A, rows_b, start = [], [], 0
    for b in blocks:
        idx = slice(start, start + b.size)
        start += b.size
        if b.name not in centres:
            continue
        which, kind = b.name.split(".")
        frame = getattr(model, which)
        centre = centres[b.name]
        if kind == "dp":
            now = (frame.T0[:, :3, 3] + frame.dp).detach()
            gap = centre.value.to(now.dtype) - now  # (G, 3)
        else:
            now_w = frame.rotvec.detach()
            target = so3_log(frame.T0[:, :3, :3].transpose(-1, -2) @ centre.value.to(now_w.dtype))
            gap = target - now_w
        A = torch.zeros(b.size, n, dtype=gap.dtype)
        A[:, idx] = torch.eye(b.size, dtype=gap.dtype) * (b.scale / centre.std)
        rows_A.append(A)
        rows_b.append(gap.reshape(-1) / centre.std)
    if not rows_A:
        return None
    return PriorRows(torch.cat(rows_A), torch.cat(rows_b))

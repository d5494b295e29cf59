"""Which frame components the data determine, in words, and whether the frames are
plausible.

The frame columns of the identification Jacobian, with the noise weights undone, say
how far the measured points move (mm per mm, mm per mrad; orientations in mrad per
mrad) when a combination of frame parameters moves, once the other frame parameters
have compensated what they can. Its eigenvectors with a small rms motion per row
(``MIN_SENSITIVITY``) are the trade-off valleys: along them every unmodelled error of
1 mm becomes a frame error of more than 1 / MIN_SENSITIVITY mm. Such a direction is

- *not determined* when the data carry less information on it than the prior of
  :mod:`hybrid_pk.calibration.frames` (its value is the prior's, not a measurement);
- *weakly determined* otherwise (measured, but sensitive to any model error).

Each is named by the frame part that holds it (the one with the tightest prior: the
tool translation in the usual tool-base valley), e.g. "tool translation along the
flange z axis: not determined, the flange orientation spans only 4.0° about the axes
perpendicular to it".

Plausibility: a tool translation beyond ``FramePriors.max_tool_m`` (no tracker target
sits that far from a flange), or a base that moved far from where the fit started
without lowering the error, is a warning with the fix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from hybrid_pk.calibration.frames import FramePriors, PriorRows
from hybrid_pk.calibration.problem import subset_jacobian, subset_rows
from hybrid_pk.calibration.work import count as count_work
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import nearest_rotation, so3_log

if TYPE_CHECKING:
    from hybrid_pk.calibration.problem import ParamBlock

__all__ = [
    "BASE_MOVE_DEG",
    "BASE_MOVE_M",
    "MIN_GAIN_FRACTION",
    "MIN_SENSITIVITY",
    "FrameReport",
    "flange_span_deg",
    "frame_report",
    "skipped_frame_report",
]

# A frame direction whose rms point motion per row is below this fraction of its own
# size is a trade-off valley (errors are amplified more than 1 / MIN_SENSITIVITY times).
MIN_SENSITIVITY = 0.05
# Rows of the frame Jacobian evaluated for the report (an even subset of larger data).
MAX_ROWS = 2000
# A base that moves farther than this from where the fit started ...
BASE_MOVE_M = 0.1
BASE_MOVE_DEG = 5.0
# ... while the rms position error drops by less than this fraction is a valley walk.
MIN_GAIN_FRACTION = 0.1

_PARTS = {
    "tool.dp": ("tool", "translation", "flange"),
    "tool.rotvec": ("tool", "rotation", "tool frame"),
    "base.dp": ("base", "translation", "measurement frame"),
    "base.rotvec": ("base", "rotation", "robot root frame"),
}


@dataclass(frozen=True)
class FrameReport:
    """What the data say about the fitted frames.

    Attributes:
        directions: one entry per undetermined or weakly determined frame part:
            ``frame``, ``part``, ``set``, ``status``, ``axes`` (unit vectors spanning it,
            in the frame named by ``axes_frame``), ``sensitivity`` (rms point motion per
            unit), ``data_std`` and ``prior_std`` (mm or mrad along it), ``text``.
        warnings: plausibility warnings, each a sentence with the fix.
    """

    directions: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def undetermined(self) -> list[dict]:
        return [d for d in self.directions if d["status"] == "not determined"]

    def lines(self) -> list[str]:
        """Human lines: one per direction, then one per warning."""
        out = [d["text"] for d in self.directions]
        return out + [f"warning: {w}" for w in self.warnings]

    def to_json(self) -> dict:
        return {"directions": self.directions, "warnings": self.warnings}


def flange_span_deg(R_flange: Tensor, axis: Tensor | None = None) -> float:
    """Extent [deg] of the flange orientations ``(N, 3, 3)``, about axes perpendicular
    to ``axis`` (flange frame) when given.

    The rotation vectors of ``R_mean^T R_i`` (flange frame) are projected off ``axis``;
    the extent is the largest spread of that cloud over 12 directions.
    """
    if R_flange.shape[0] < 2:
        return 0.0
    R_mean = nearest_rotation(R_flange.sum(0))
    w = so3_log(R_mean.T @ R_flange)  # (N, 3)
    if axis is not None:
        a = axis / axis.norm()
        w = w - (w @ a)[:, None] * a
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(12, 3, generator=g, dtype=w.dtype)
    dirs = torch.cat([torch.eye(3, dtype=w.dtype), dirs / dirs.norm(dim=1, keepdim=True)])
    proj = w @ dirs.T  # (N, 15)
    return math.degrees(float((proj.max(0).values - proj.min(0).values).max()))


def _axis_words(u: Tensor, frame: str) -> str:
    k = int(u.abs().argmax())
    if float(u.abs()[k]) > 0.97:
        return f"the {frame} {'xyz'[k]} axis"
    return f"({', '.join(f'{float(x):+.2f}' for x in u)}) in the {frame}"


def _columns(blocks: tuple[ParamBlock, ...]) -> list[tuple[str, int, int, int]]:
    """``(block name, set, axis, column)`` of every frame parameter."""
    out, start = [], 0
    for b in blocks:
        if b.name in _PARTS:
            for k in range(b.size):
                out.append((b.name, k // 3, k % 3, start + k))
        start += b.size
    return out


_FIXES = {
    "tool": "measure more flange orientations or give it with --tool X,Y,Z",
    "base": "measure poses spread over the workspace or give it with --base X,Y,Z,RX,RY,RZ",
}


def _status_text(d: dict, value_words: str, reason: str) -> str:
    head = f"{d['label']}: {d['status']}"
    fix = _FIXES[d["frame"]]
    if d["status"] == "not determined":
        return f"{head}, {reason}; held at {value_words}. To determine it, {fix}"
    return (
        f"{head}, {reason}: an unmodelled error of 1 mm moves it by about "
        f"{1.0 / max(d['sensitivity'], 1e-9):.3g} mm. To determine it better, {fix}"
    )


def _held_at(which: str, part: str, T: Tensor, priors: FramePriors) -> str:
    """Where the prior holds an undetermined frame part, in words."""
    spec = getattr(priors, which)
    if part == "rotation":
        if spec is not None and spec.rotation is not None:
            return f"the {which} rotation of {spec.source}"
        return "its starting orientation (the registration guess)"
    xyz = "(" + ", ".join(f"{float(x) + 0.0:.4f}" for x in T[:3, 3]) + ") m"
    if spec is not None:
        centre = f"{spec.source} ± {1e3 * spec.std_m:.3g} mm"
    elif which == "tool":
        centre = (
            f"the end link's origin ± {priors.tool_std_m:g} m, where what the data do not "
            "determine is held"
        )
    else:
        return f"its registration guess: {which} translation {xyz}"
    return f"the prior ({centre}): {which} translation {xyz}"


def _describe(
    group: list[dict], R_flange: Tensor | None, model: ExtendedModel, priors: FramePriors
) -> dict:
    """Merge the directions of one frame part into one entry with words."""
    name, g, status = group[0]["block"], group[0]["set"], group[0]["status"]
    which, part, axes_frame = _PARTS[name]
    V = torch.stack([d["vector"] for d in group])  # (k, 3) block parts
    _, S, Vt = torch.linalg.svd(V, full_matrices=True)
    rank = max(1, int((S > 0.3 * S[0]).sum()))
    axes = Vt[:rank]
    tag = f" [set {g}]" if model.base.sets > 1 else ""
    if rank == 1:
        where = f"along {_axis_words(axes[0], axes_frame)}"
    elif rank == 2:
        where = f"perpendicular to {_axis_words(Vt[2], axes_frame)}"
    else:
        where = "(all three components)"
    label = f"{which} {part}{tag} {where}"
    sens = min(d["sensitivity"] for d in group)
    entry = {
        "frame": which,
        "part": part,
        "set": g,
        "status": status,
        "axes": [[float(x) for x in a] for a in axes],
        "axes_frame": axes_frame,
        "sensitivity": sens,
        "data_std": max(d["data_std"] for d in group),
        "prior_std": max(d["prior_std"] for d in group),
        "label": label,
    }
    T = getattr(model, which).matrix()[g].detach()
    if which == "tool" and part == "translation" and R_flange is not None:
        span = flange_span_deg(R_flange, axes[0] if rank == 1 else None)
        about = " about the axes perpendicular to it" if rank == 1 else ""
        reason = f"the flange orientation spans only {span:.1f}°{about}"
        entry["flange_span_deg"] = span
    else:
        reason = f"the data move the measured points by {sens:.2g} mm per mm (or mrad) of it"
    entry["summary"] = f"{label}: {status}, {reason}"
    entry["text"] = _status_text(entry, _held_at(which, part, T, priors), reason)
    return entry


def _frame_information(
    model: ExtendedModel, data: MeasuredData, cond: Conditions, blocks: tuple[ParamBlock, ...]
) -> tuple[Tensor, Tensor, Tensor, int]:
    """Information of the frame columns on at most ``MAX_ROWS`` rows (an even subset):
    ``(H_pos, H_rot, R_flange, n)`` with ``H`` in mm² (or mrad²) per scaled unit² summed
    over the ``n`` rows used, and their flange orientations ``(n, 3, 3)``."""
    frame_blocks = tuple(b for b in blocks if b.name in _PARTS)
    _, J, sub, cond_sub = subset_jacobian(model, data, cond, frame_blocks, MAX_ROWS)
    n_pos = 3 * sub.n
    Jp, Jr = J[:n_pos], J[n_pos:]
    with torch.no_grad():
        R_flange = model.end_pose(sub.q, cond_sub)[:, :3, :3]
    return Jp.T @ Jp, Jr.T @ Jr, R_flange, sub.n


def _directions(
    cols: list[tuple[str, int, int, int]],
    information: tuple[Tensor, Tensor, int],
    n_rows: int,
    sigma_pos_mm: float,
    sigma_rot_rad: float | None,
    prior: PriorRows | None,
) -> list[dict]:
    """The weak directions of the frame columns ``cols`` given their position and
    rotation information on ``n_sub`` of the ``n_rows`` rows (``information``)."""
    idx = [c[3] for c in cols]
    H_pos, H_rot, n_sub = information
    lam, V = torch.linalg.eigh((H_pos + H_rot) / max(n_sub, 1))  # physical, per row
    # noise-normalised information of all the rows (scaled units)
    H = (n_rows / n_sub) * (H_pos / sigma_pos_mm**2 + H_rot / (1e3 * (sigma_rot_rad or 1.0)) ** 2)
    P = torch.zeros_like(H) if prior is None else (prior.A[:, idx].T @ prior.A[:, idx])
    out = []
    for k in range(len(idx)):
        sens = float(lam[k].clamp_min(0).sqrt())
        if sens >= MIN_SENSITIVITY:
            break
        v = V[:, k]
        data_info, prior_info = float(v @ H @ v), float(v @ P @ v)
        data_std = 1.0 / math.sqrt(max(data_info, 1e-300))
        prior_std = 1.0 / math.sqrt(prior_info) if prior_info > 0 else math.inf
        # name it by the part whose prior holds it (or the largest part without priors)
        share = {}
        for (name, g, _, _), x, p in zip(cols, v, P.diagonal(), strict=True):
            key = (name, g)
            weight = float(p) if prior_info > 0 else 1.0
            share[key] = share.get(key, 0.0) + weight * float(x) ** 2
        name, g = max(share, key=share.get)
        part = torch.stack([v[i] for i, c in enumerate(cols) if c[0] == name and c[1] == g])
        out.append(
            {
                "block": name,
                "set": g,
                "vector": part / part.norm().clamp_min(1e-300),
                "status": "not determined" if data_std > prior_std else "weakly determined",
                "sensitivity": sens,
                "data_std": data_std,
                "prior_std": prior_std,
            }
        )
    return out


def frame_report(
    model: ExtendedModel,
    data: MeasuredData,
    cond: Conditions,
    blocks: tuple[ParamBlock, ...],
    *,
    sigma_pos_mm: float,
    sigma_rot_rad: float | None,
    prior: PriorRows | None,
    priors: FramePriors | None = None,
    start: dict | None = None,
    rms_mm: float | None = None,
) -> FrameReport:
    """Identifiability and plausibility of the fitted frames.

    The frame columns of the Jacobian are evaluated on at most ``MAX_ROWS`` rows (the
    directions are a property of the poses' spread; the information scales with the
    row count).

    Args:
        model: the fitted model (frames hold the fitted values).
        data, cond: the fitted rows and their conditions.
        blocks: the fitted parameter blocks (frames first, in the fit's order).
        sigma_pos_mm, sigma_rot_rad: the fit's noise levels.
        prior: the prior rows of the fit, or None.
        priors: the fit's priors (plausibility limit of the tool).
        start: ``{"base": (G, 4, 4), "rms_mm": float}`` where the fit started.
        rms_mm: rms position error [mm] after the fit.
    """
    cols, raw, R_flange = _columns(blocks), [], None
    if cols:
        H_pos, H_rot, R_flange, n_sub = _frame_information(model, data, cond, blocks)
        raw = _directions(cols, (H_pos, H_rot, n_sub), data.n, sigma_pos_mm, sigma_rot_rad, prior)
    groups: dict[tuple, list[dict]] = {}
    for d in raw:
        groups.setdefault((d["block"], d["set"], d["status"]), []).append(d)
    priors = priors or FramePriors()
    directions = [_describe(g, R_flange, model, priors) for g in groups.values()]
    fitted = {b.name for b in blocks}
    warnings = _plausibility(model, priors, fitted, start, rms_mm)
    return FrameReport(directions, warnings)


def skipped_frame_report(data: MeasuredData, blocks: tuple[ParamBlock, ...]) -> None:
    """No report, for a refit whose report nobody reads; the Jacobian rows
    :func:`frame_report` evaluates are counted as work done all the same, so that a
    diagnosis' work budget (:mod:`hybrid_pk.calibration.work`) cuts where it did."""
    if _columns(blocks):
        count_work(len(subset_rows(data.n, MAX_ROWS)), len(_columns(blocks)))


def _plausibility(
    model: ExtendedModel, priors: FramePriors, fitted: set, start: dict | None, rms_mm
) -> list[str]:
    out = []
    sets = model.base.sets
    if "tool.dp" in fitted:
        T = model.tool.matrix().detach()
        for g in range(sets):
            dist = float(T[g, :3, 3].norm())
            if dist > priors.max_tool_m:
                tag = f" [set {g}]" if sets > 1 else ""
                out.append(
                    f"tool frame{tag} translation {dist:.3g} m from the flange is beyond what "
                    f"a tracker target on a flange can be ({priors.max_tool_m:g} m): the data "
                    "cannot separate tool and base. Measure more flange orientations, fix the "
                    "tool with --tool X,Y,Z (from the target's mount drawing), or refit only "
                    "the base of a model whose tool is known (--model MODEL --refit base)"
                )
    if start is None or "base" not in start or not fitted & {"base.dp", "base.rotvec"}:
        return out
    B0, B1 = start["base"], model.base.matrix().detach()
    rms0 = start.get("rms_mm")
    for g in range(sets):
        moved = float((B1[g, :3, 3] - B0[g, :3, 3]).norm())
        turned = math.degrees(float(so3_log(B0[g, :3, :3].T @ B1[g, :3, :3]).norm()))
        if moved <= BASE_MOVE_M and turned <= BASE_MOVE_DEG:
            continue
        if rms0 is None or rms_mm is None or rms_mm < (1 - MIN_GAIN_FRACTION) * rms0:
            continue
        tag = f" [set {g}]" if sets > 1 else ""
        out.append(
            f"base frame{tag} moved {moved:.3g} m and {turned:.3g}° from its registration "
            f"guess while the rms position error only went from {rms0:.4g} to "
            f"{rms_mm:.4g} mm: the fit walked along a trade-off, not to a measurement. "
            "Fix the tool with --tool X,Y,Z, fix or seed the base with --base, or refit "
            "only the base (--model MODEL --refit base)"
        )
    return out

"""Components of an effect no data can see: the parts the fitted frames absorb.

A link length of the last joint along that joint's axis moves every measured point
exactly as a tool translation along the flange axis does; every fit estimates the
tool, so that part of the link length is absorbed and a diagnosis reports ~0 for it,
whatever was there. Tables that compare values (demo, simulate truth against a
diagnosis) compare the seeable part and mark the rest, e.g. "(along joint_6's axis:
absorbed by the tool frame)".

Linearised at the frames-only model: the effect's Jacobian columns projected off the
frame columns; directions of its parameters whose projection keeps less than
``RANK_TOLERANCE`` of their own motion are absorbed (named by the frame whose columns
alone absorb them).
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.selection import RANK_TOLERANCE
from hybrid_pk.calibration.diagnosis.variants import with_effects
from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import Conditions, Effect, ExtendedModel, entry_label, make_effect

__all__ = ["MAX_ROWS", "mark_unseen", "seeable_split", "seen_error"]

# Rows of the Jacobian used (an even subset): absorption is a property of the poses'
# spread, not of their count; 1000 rows estimate each singular value to ~2 %
# (1/sqrt(2000)), which moves a direction across RANK_TOLERANCE only within 2 % of it.
MAX_ROWS = 1000
_FRAMES = {"base.dp": "base", "base.rotvec": "base", "tool.dp": "tool", "tool.rotvec": "tool"}


def _absorbed(Jc: Tensor, J_frames: Tensor) -> tuple[Tensor, Tensor]:
    """``(V_seen, V_absorbed)``: orthonormal parameter directions (columns)."""
    Q, _ = torch.linalg.qr(J_frames)
    Jp = Jc - Q @ (Q.T @ Jc)
    # relative size of each direction's projection against its own motion
    _, S, Vt = torch.linalg.svd(Jp, full_matrices=True)
    own = (Jc @ Vt.T).norm(dim=0).clamp_min(1e-300)
    S = torch.cat([S, S.new_zeros(Vt.shape[0] - S.numel())])
    lost = S / own < RANK_TOLERANCE
    return Vt[~lost].T, Vt[lost].T


def _axis_words(robot, effect: Effect, u: Tensor) -> str:
    """Where ``u`` (the effect's 3-vector parameter direction) points, in words."""
    i = effect.joint_index
    spec = robot.spec
    R = torch.as_tensor(spec.origins[i, :3, :3], dtype=u.dtype)
    a = torch.as_tensor(spec.axes[i], dtype=u.dtype)
    if effect.stage == "geometry" and effect.unit == "m":
        a = R @ a  # a translation of the origin is in the parent frame
    if float((u @ a).abs()) > 0.99 * float(a.norm()):  # within 8 deg: "along" in words
        return f"along {effect.joint}'s axis"
    return "along (" + ", ".join(f"{float(x):+.2f}" for x in u) + ")"


def seeable_split(
    nominal: ExtendedModel, data: MeasuredData, cond: Conditions, effect: Effect
) -> dict | None:
    """The part of ``effect``'s value the data can see and the part the frames absorb.

    Args:
        nominal: the frames-only model fitted to ``data`` (a diagnosis'
            ``nominal_model``).
        effect: the effect with its (injected) value.

    Returns:
        None when every direction is seen; else ``{"seen": list, "absorbed": list}``
        (the value split in its parameters' units) and ``"words"``, e.g. "along
        joint_6's axis: absorbed by the tool frame".
    """
    step = max(1, -(-data.n // MAX_ROWS))
    rows = torch.arange(0, data.n, step)
    sub, cond_sub = data.subset(rows), cond.subset(rows)
    trial = with_effects(nominal, [make_effect(nominal.robot, effect.label)])
    blocks = param_blocks(trial, None, data.quat is None)
    _, J = Problem(trial, sub, cond_sub, blocks, 1.0, 1e-3).jacobian(
        torch.zeros(sum(b.size for b in blocks), dtype=torch.float64)
    )
    J = J.detach()
    cols, start = {}, 0
    for b in blocks:
        cols[b.name] = J[:, start : start + b.size]
        start += b.size
    frames = [cols[n] for n in cols if n in _FRAMES]
    Jc = cols[blocks[-1].name]
    _, V_lost = _absorbed(Jc, torch.cat(frames, 1))
    if V_lost.shape[1] == 0:
        return None
    value = effect.value.detach().to(torch.float64).reshape(-1)
    absorbed = V_lost @ (V_lost.T @ value)
    by = []
    for frame in ("tool", "base"):
        own = torch.cat([cols[n] for n in cols if _FRAMES.get(n) == frame], 1)
        _, lost_here = _absorbed(Jc @ V_lost, own)
        if lost_here.shape[1] == V_lost.shape[1]:
            by.append(f"the {frame} frame")
    who = " or ".join(by) if by else "the base and tool frames together"
    if V_lost.shape[1] == value.numel():
        where = "all of it"
    elif V_lost.shape[1] == 1 and value.numel() == 3:
        where = _axis_words(nominal.robot, effect, V_lost[:, 0])
    else:
        where = f"{V_lost.shape[1]} of its {value.numel()} components"
    return {
        "seen": [float(x) for x in value - absorbed],
        "absorbed": [float(x) for x in absorbed],
        "axes": [[float(x) for x in col] for col in V_lost.T],
        "words": f"{where}: absorbed by {who}",
    }


def mark_unseen(
    nominal: ExtendedModel, data: MeasuredData, cond: Conditions, entries: list[dict]
) -> list[dict]:
    """``entries`` (``{"effect", "joint", "value"}``, e.g. a truth JSON's effects) with
    ``"unseen"`` added where the frames absorb part of the value
    (:func:`seeable_split`)."""
    out = []
    for e in entries:
        effect = make_effect(nominal.robot, entry_label(e), e["value"])
        split = seeable_split(nominal, data, cond, effect)
        size = torch.as_tensor(e["value"], dtype=torch.float64).numel()
        if split is not None and len(split["seen"]) != size:  # stored on another basis
            split = {"words": split["words"]}
        out.append(e if split is None else {**e, "unseen": split})
    return out


def seen_error(entry: dict, found) -> float | None:
    """Relative difference of a found value from the injected ``entry`` on the part the
    data see (None when the entry has no seeable part or no comparable value)."""
    unseen = entry.get("unseen")
    if unseen is None or "axes" not in unseen:
        return None
    f = torch.as_tensor(found, dtype=torch.float64).reshape(-1)
    seen = torch.as_tensor(unseen["seen"], dtype=torch.float64)
    if f.numel() != seen.numel() or float(seen.norm()) == 0.0:
        return None
    V = torch.as_tensor(unseen["axes"], dtype=torch.float64).T  # (size, k)
    f_seen = f - V @ (V.T @ f)
    return float((f_seen - seen).norm() / seen.norm())

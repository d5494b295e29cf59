"""A set-up that moved by a little during a file: a change at one row, a drift, or both.

A tracker knocked by a few millimetres, a tool re-seated, a tripod settling over the
hours: the rows then need frames that are not one rigid set, but the move is far below
the gross line of :mod:`~hybrid_pk.calibration.setup_change` (20 mm), so the diagnosis
explains it with causes. Afterwards, the final model's errors still carry it: a rigid
move of the base (measurement) frame and of the tool shifts every row after the change,
or every row a little more than the one before.

:func:`setup_moves` asks the final model's errors on the fit rows of each frame group,
in their measured order, which of four corrections of the frames predicts them best
out of sample (12 parameters each, 9 position-only: base translation and rotation, tool
translation and, with orientations, rotation; linearised at the final model):

- ``one``: one correction for all rows (what the fit already made: the peer);
- ``change``: one before and one after a row, the row chosen on the rows fitted;
- ``drift``: a correction growing linearly with the row's place in the sequence (its
  time stamp where the rows have them, else its order);
- ``both``: a drift and, on top of it, a change at the change's row (a tripod settling
  through the rows and a knock).

Each is fitted on the rows outside one region of joint space (the blocked hold-out's
regions, :mod:`.regions`) and judged on the rows inside it, in turn; the mean position
error over every held-out row is compared. A ``change`` or ``drift`` carries over
where it gains at least the practical margin over ``one`` (the rule every cause meets)
and lowers the held-out error of every region: a move of the set-up is rigid, the same
for every region, while an error of the robot that a frame change stands in for
locally (rows measured region by region, an error no cause explains) helps some regions
and not others. One that carries over is named; where both do, the one better by the
margin, else "moved" (the data cannot tell a change from a drift). ``both`` is named
(``change_and_drift``) where it carries over, beats each of the two alone by the margin
as well (the simpler story wins unless the data show more), and the drift carries over
on each side of the change on its own: a settling goes on through a knock, while the
causes fitted to a knock leave a pattern in the row order that does not (the shared
UR10's Series B with its rows from row 501 on moved by 1 mm: both together beat the
change by 0.025 mm, but before the change a drift does not carry on its own, losing in
one region of four; named a change).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import Tensor

from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.poses import predicted_poses
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.geometry.rotations import skew, so3_log

__all__ = ["mention_moves", "move_columns", "setup_move_text", "setup_moves"]

# Directions of a part's 12 x 12 Gram below this fraction of its largest (columns
# scaled to unit length) are left out: round-off, or a frame direction the rows do not
# see (a tool translation along an orientation that never changes).
RCOND = 1e-10
# Candidate change rows per level of the coarse-to-fine scan (every row of the finest).
SCAN_STEPS = 256
# Rows whose 12 x 12 Grams are formed at once: bounds the temporaries (~10 MB).
CHUNK_ROWS = 8192
# The corrections compared: one for all rows, a change at one row, a drift, both.
_MODELS = ("one", "change", "drift", "both")


def move_columns(T: Tensor, sigmas: tuple[float, float | None]) -> Tensor:
    """``(n, m, p)`` derivatives of the noise-normalised errors (``m`` = 6, or 3 without
    orientations: ``sigmas[1]`` None) of poses ``T (n, 4, 4)`` [m] with respect to a
    small move of the base frame (translation [mm], rotation [rad], in the measurement
    frame) and of the tool (translation [mm] and rotation [rad] in the tool frame):
    ``p`` = 12, or 9 without orientations (the tool's rotation moves no point)."""
    n, sp, sr = T.shape[0], sigmas[0], sigmas[1]
    R, p = T[:, :3, :3], T[:, :3, 3] * 1e3
    eye = torch.eye(3, dtype=T.dtype).expand(n, 3, 3)
    position = torch.cat([eye, -skew(p), R], dim=2) / sp  # (n, 3, 9)
    if sr is None:
        return position
    zero = torch.zeros(n, 3, 3, dtype=T.dtype)
    position = torch.cat([position, zero], dim=2)
    rotation = torch.cat([zero, eye, zero, R], dim=2) / sr
    return torch.cat([position, rotation], dim=1)


def _errors(T: Tensor, data, sigmas) -> Tensor:
    """``(n, m)`` measured minus predicted, noise-normalised (position mm / sigma_pos,
    rotation vector rad / sigma_rot)."""
    position = (data.position - T[:, :3, 3]) * 1e3 / sigmas[0]
    if sigmas[1] is None or data.quat is None:
        return position
    R_meas = data.T_measured()[:, :3, :3]
    rotation = so3_log(R_meas @ T[:, :3, :3].transpose(1, 2)) / sigmas[1]
    return torch.cat([position, rotation], dim=1)


def _solve(G: Tensor, b: Tensor) -> Tensor:
    """Minimum-norm solutions ``x`` of ``G x = b`` (batched ``(..., p, p)``, ``(..., p)``),
    directions below :data:`RCOND` of the largest left out."""
    scale = G.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()
    Gs = G * scale[..., :, None] * scale[..., None, :]
    w, V = torch.linalg.eigh(Gs)
    keep = w > RCOND * w[..., -1:].clamp_min(1e-300)
    inv = torch.where(keep, 1.0 / w.where(keep, torch.ones_like(w)), torch.zeros_like(w))
    y = V @ ((V.transpose(-1, -2) @ (b * scale)[..., None]).squeeze(-1) * inv)[..., None]
    return y.squeeze(-1) * scale


def _sums(A: Tensor, e: Tensor, weight: Tensor, segment: Tensor, n_segments: int, *scales):
    """Per segment of the rows: the sums of ``weight * A^T A`` and ``weight * A^T e``,
    formed :data:`CHUNK_ROWS` rows at a time (no Gram per row is kept: 250,000 rows
    would take 1.2 GB). ``scales``: per-row factors ``(n,)`` of further column blocks
    ``A * s`` (each row's place in the sequence: a drifting correction's slope; 0
    before a row and 1 from it: a change's step)."""
    p = A.shape[2] * (1 + len(scales))
    G, b = A.new_zeros(n_segments, p, p), A.new_zeros(n_segments, p)
    for start in range(0, A.shape[0], CHUNK_ROWS):
        rows = slice(start, start + CHUNK_ROWS)
        a = torch.cat([A[rows], *(A[rows] * s[rows, None, None] for s in scales)], 2)
        aw = a * weight[rows, None, None]
        if n_segments == 1:  # one sum: a matrix product, no Gram per row
            G[0] += aw.reshape(-1, p).T @ a.reshape(-1, p)
            b[0] += aw.reshape(-1, p).T @ e[rows].reshape(-1)
            continue
        G.index_add_(0, segment[rows], torch.einsum("nij,nik->njk", aw, a))
        b.index_add_(0, segment[rows], torch.einsum("nij,ni->nj", aw, e[rows]))
    return G, b


def _change_row(A: Tensor, e: Tensor, rows: Tensor, min_rows: int, w=None) -> int | None:
    """The place ``k`` in the sequence after which a second correction fits ``rows``
    (a mask of the sequence; ``w``: the rows' robust weights, None: 1) best, with
    ``min_rows`` of them on each side; None when they are too few. Coarse to fine:
    :data:`SCAN_STEPS` candidates a level."""
    count, weight = rows.long().cumsum(0), rows.to(A.dtype) * (1.0 if w is None else w)
    total = int(count[-1])
    if total < 2 * min_rows:
        return None
    order = torch.arange(len(rows))

    def gain(k: Tensor) -> Tensor:  # the explained sum of squares of the two parts
        segment = torch.searchsorted(k, order, right=True)  # row i counts for k > i
        G, b = _sums(A, e, weight, segment, len(k) + 1)
        G1, b1 = G.cumsum(0)[:-1], b.cumsum(0)[:-1]  # the rows before each k
        G2, b2 = G.sum(0) - G1, b.sum(0) - b1
        return (b1 * _solve(G1, b1)).sum(-1) + (b2 * _solve(G2, b2)).sum(-1)

    valid = ((count >= min_rows) & (total - count >= min_rows)).nonzero().squeeze(1) + 1
    lo, hi = int(valid[0]), int(valid[-1])
    while True:
        k = torch.unique(torch.linspace(lo, hi, min(SCAN_STEPS, hi - lo + 1)).round().long())
        best = int(k[gain(k).argmax()])
        if len(k) == hi - lo + 1:
            return best
        step = (hi - lo) / (SCAN_STEPS - 1)
        lo, hi = max(int(valid[0]), int(best - step)), min(int(valid[-1]), int(best + step) + 1)


def _gram(A: Tensor, e: Tensor, mask: Tensor, w, *scales) -> tuple[Tensor, Tensor]:
    """One :func:`_sums` over the rows of ``mask`` (``w``: their robust weights, None:
    1): ``G (q, q)`` and ``b (q,)``, ``p`` columns per block; a leading block's sums are
    its top-left part."""
    weight = mask.to(A.dtype) * (1.0 if w is None else w)
    G, b = _sums(A, e, weight, torch.zeros(A.shape[0], dtype=torch.long), 1, *scales)
    return G[0], b[0]


def _fitted(A: Tensor, e: Tensor, mask: Tensor, w, *scales) -> Tensor:
    """The correction's parameters fitted on the rows of ``mask`` (see :func:`_gram`)."""
    return _solve(*_gram(A, e, mask, w, *scales))


def _fits(A: Tensor, e: Tensor, place: Tensor, rows: Tensor, min_rows: int, w=None):
    """The four corrections (``{"one", "change", "drift", "both"}`` -> ``(n, p)``
    correction of each row; ``both``: a drift and, on top of it, a change at the
    change's row) fitted on ``rows`` (a mask of the sequence; ``w``: the rows' robust
    weights, None: 1), and the change's place (``change`` and ``both`` left out where
    the rows are too few for a change)."""
    n, p = A.shape[0], A.shape[2]
    k = _change_row(A, e, rows, min_rows, w)
    step = (torch.arange(n) >= (n if k is None else k)).to(A.dtype)
    # One Gram of the blocks [A, A place, A step] holds every model's: the rows from the
    # change are the step block's, those before it the rest of the first block's.
    G, b = _gram(A, e, rows, w, *((place,) if k is None else (place, step)))
    one, two = slice(0, p), slice(0, 2 * p)
    x_drift = _solve(G[two, two], b[two])
    out = {
        "one": _solve(G[one, one], b[one]).expand(n, -1),
        "drift": x_drift[:p] + place[:, None] * x_drift[p:],
    }
    if k is not None:
        after = slice(2 * p, 3 * p)
        x2 = _solve(G[after, after], b[after])
        x1 = _solve(G[one, one] - G[after, after], b[one] - b[after])
        out["change"] = torch.where(step[:, None] > 0, x2, x1)
        x = _solve(G, b)
        out["both"] = x[:p] + place[:, None] * x[p : 2 * p] + step[:, None] * x[2 * p :]
    return out, k


def setup_moves(model, res, split: Split, carry, say=None) -> list[dict]:
    """The set-up moves the final ``model``'s errors on ``split``'s fit rows show, one
    entry per frame group with one (see the module); empty without regions to hold out.

    Args:
        model, res: the final model of a diagnosis and its fit (the noise levels).
        carry: the blocked hold-out's settings (:class:`.carryover.Carry`): its regions
            of the fit rows, and the practical margin.
        say: the progress callback.

    Returns:
        ``{"kind": "change" | "drift" | "moved" | "change_and_drift", "file", "row"
        (the change's first row, else None), "rows", "shift_mm": {"mean", "max"},
        "base_translation_mm", "base_rotation_deg", "tool_translation_mm", "drift",
        "blocked_mean_mm": {"one", "change", "drift", "both"}, "gain_mm", "min_gain_mm",
        "regions_gained": {"gained", "of"}}``: the move as the named correction fitted
        on every fit row of the group (a change: the rows from the change against those
        before it; a drift: the last row against the first; both: the change on top of
        the drift, and ``drift`` the drift's own ``shift_mm`` and base and tool parts,
        else None).
    """
    folds, margin = carry.folds, carry.margin(res)
    sigmas = (res.sigma_pos_mm, None if split.position_only else res.sigma_rot_rad)
    regions = 0 if folds is None else int(folds.description.get("regions", 0))
    if regions < 2:
        return []
    if say is not None:
        say("checking whether the set-up moved during the rows")
    data, cond = split.train, split.cond_fit
    T = predicted_poses(model, data.q, cond)
    weights = res.weights  # a robust fit's row weights: outliers count as little here
    w = torch.ones(data.n, dtype=T.dtype) if weights is None else weights.to(T.dtype)
    groups = [None] if cond.group is None else cond.group.unique().tolist()
    found = []
    for g in groups:
        idx = torch.arange(data.n) if g is None else (cond.group == g).nonzero().squeeze(1)
        rows = (data.subset(idx), T[idx], w[idx])
        entry = _group_move(rows, folds.cell[idx] % regions, sigmas, margin)
        if entry is not None:
            found.append(entry)
    return found


def _group_move(rows, region: Tensor, sigmas, margin: float) -> dict | None:
    """:func:`setup_moves`' entry of one frame group's rows (in the order measured;
    ``rows``: ``(data, predicted poses, robust weights)``)."""
    data, T, w = rows
    least = diagnosis_tuning().check_rows  # a check's worth of rows on each side
    n = data.n
    if n < 2 * least:
        return None
    A, e = move_columns(T, sigmas), _errors(T, data, sigmas)
    place = _places(data, A.dtype)
    held = {k: torch.full((n,), math.nan, dtype=A.dtype) for k in _MODELS}
    regions = region.unique().tolist()
    for r in regions:
        inside = region == r
        if inside.all():
            return None
        fitted, _ = _fits(A, e, place, ~inside, least, w)
        for name, x in fitted.items():
            left = e[inside] - (A[inside] @ x[inside][..., None]).squeeze(-1)
            held[name][inside] = left[:, :3].norm(dim=1) * sigmas[0]

    def mean(name: str, rows=None) -> float:  # weighted as the fit weighs the rows
        v, u = (held[name], w) if rows is None else (held[name][rows], w[rows])
        return float((v * u).sum() / u.sum())  # NaN where a region left no change

    # a region of fewer rows than a block needs says nothing on its own: it does not vote
    voters = [r for r in regions if int((region == r).sum()) >= diagnosis_tuning().min_block_rows]
    if len(voters) < 2:
        return None  # nothing to carry over to
    gain, gained = {}, {}
    for kind in _MODELS[1:]:
        gain[kind] = mean("one") - mean(kind)
        gained[kind] = sum(mean("one", region == r) > mean(kind, region == r) for r in voters)
    # a rigid move is the same in every region: it must lower each one's held-out error
    carried = [k for k in gain if gain[k] >= margin and gained[k] == len(voters)]
    # both together only where they beat each alone by the margin (a cause's rule), and
    # the drift carries on each side of the change on its own: a settling goes on through
    # a knock, while causes fitted to a knock leave a pattern that does not
    both = "both" in carried and gain["both"] - max(gain["change"], gain["drift"]) >= margin
    k = _change_row(A, e, torch.ones(n, dtype=torch.bool), least, w) if both else None
    if k is not None and all(
        _drift_carries(A, e, place, w, region, side, margin, sigmas[0])
        for side in (torch.arange(n) < k, torch.arange(n) >= k)
    ):
        kind = "change_and_drift"
    else:
        carried = [c for c in carried if c != "both"]
        if not carried:
            return None
        kind = carried[0] if len(carried) == 1 else "moved"
    if kind == "moved" and abs(gain["change"] - gain["drift"]) >= margin:
        kind = "change" if gain["change"] > gain["drift"] else "drift"
    means = {k: mean(k) for k in held}
    shown = {"drift": "drift", "change_and_drift": "both"}.get(kind, "change")
    blocks = {"gained": gained[shown], "of": len(voters)}
    return _entry(kind, data, (A, e, place, w), (means, blocks), sigmas[0], margin)


def _drift_carries(A, e, place, w, region, side, margin: float, sigma_pos: float) -> bool:
    """Whether a drift carries over against one correction within the rows of ``side``
    alone (fitted outside each region, judged inside it; every region of enough rows
    gains, the mean by ``margin``)."""
    p, vote = A.shape[2], diagnosis_tuning().min_block_rows
    err = {k: torch.full((A.shape[0],), math.nan, dtype=A.dtype) for k in ("one", "drift")}
    voters = []
    for r in region[side].unique().tolist():
        inside = side & (region == r)
        fit = side & (region != r)
        G, b = _gram(A, e, fit, w, place)  # one correction: the first block alone
        x1, xd = _solve(G[:p, :p], b[:p]), _solve(G, b)
        corr = {"one": x1.expand(int(inside.sum()), -1),
                "drift": xd[:p] + place[inside, None] * xd[p:]}  # fmt: skip
        for name, x in corr.items():
            left = e[inside] - (A[inside] @ x[..., None]).squeeze(-1)
            err[name][inside] = left[:, :3].norm(dim=1) * sigma_pos
        if int(inside.sum()) >= vote:
            voters.append(inside)

    def mean(name: str, rows: Tensor) -> float:
        return float((err[name][rows] * w[rows]).sum() / w[rows].sum())

    if len(voters) < 2:
        return False
    gains = [mean("one", rows) > mean("drift", rows) for rows in voters]
    return mean("one", side) - mean("drift", side) >= margin and all(gains)


def _places(data, dtype) -> Tensor:
    """Each row's place in the sequence, 0 at the first and 1 at the last: by its time
    stamp where the rows have increasing ones (a pause overnight is then a long way for
    a drift, not one row), else by its order."""
    t = data.t
    if t is not None and torch.isfinite(t).all() and bool((t.diff() >= 0).all()):
        span = float(t[-1] - t[0])
        if span > 0:
            return ((t - t[0]) / span).to(dtype)
    return torch.linspace(0.0, 1.0, data.n, dtype=dtype)


def _entry(kind, data, fitted_on, held, sigma_pos: float, margin: float) -> dict:
    """The JSON entry of a named move (``fitted_on``: ``(A, e, place, w)`` of the
    group; ``held``: the held-out means and the regions gained), its sizes from the
    correction fitted on every row of the group."""
    A, e, place, w = fitted_on
    mean, blocks = held
    everything = torch.ones(data.n, dtype=torch.bool)
    fitted, k = _fits(A, e, place, everything, diagnosis_tuning().check_rows, w)
    shown = "drift" if kind == "drift" or k is None else "change"
    x = fitted[shown]
    move = x[-1] - x[0]  # a change: after it against before; a drift: last row - first
    drift = None
    if kind == "change_and_drift" and k is not None:  # the change on top of the drift
        p, step = A.shape[2], (torch.arange(data.n) >= k).to(A.dtype)
        both = _fitted(A, e, everything, w, place, step)
        move, drift = both[2 * p :], _move(A, both[p : 2 * p], slice(0, data.n), sigma_pos)
    rows = slice(k, data.n) if shown == "change" else slice(0, data.n)
    file, row = data.sources[int(data.file_index[0])], None
    if shown == "change":
        file, row = data.sources[int(data.file_index[k])], int(data.rows[k])
    return {
        "kind": kind,
        "file": file,
        "row": row,
        "rows": data.n,
        **_move(A, move, rows, sigma_pos),
        "drift": drift,
        "blocked_mean_mm": {k: (None if math.isnan(v) else v) for k, v in mean.items()},
        "gain_mm": mean["one"] - mean["both" if drift is not None else shown],
        "min_gain_mm": margin,
        "regions_gained": blocks,
    }


def _move(A: Tensor, move: Tensor, rows: slice, sigma_pos: float) -> dict:
    """A move's JSON fields: how far it shifts the points of ``rows`` [mm] and its base
    and tool parts (``move``: the parameters of :func:`move_columns`)."""
    shift = (A[rows, :3] @ move[:, None]).squeeze(-1).norm(dim=1) * sigma_pos
    return {
        "shift_mm": {"mean": float(shift.mean()), "max": float(shift.max())},
        "base_translation_mm": move[0:3].tolist(),
        "base_rotation_deg": torch.rad2deg(move[3:6]).tolist(),
        "tool_translation_mm": move[6:9].tolist(),
    }


def setup_move_text(entry: dict) -> str:
    """One line for a :func:`setup_moves` entry: what moved, by how much, the evidence,
    and what to do."""
    shift, gain, margin = entry["shift_mm"], entry["gain_mm"], entry["min_gain_mm"]
    size = f"{shift['mean']:.3g} mm (mean; up to {shift['max']:.3g} mm)"
    evidence = f"{gain:.3g} mm better than one frame set (margin {margin:.3g} mm)"
    carried = "the causes above may carry part of it"
    if entry["kind"] == "change":
        return (
            f"the set-up moved near row {entry['row']} of {entry['file']}: the rows from it "
            f"are shifted by {size} against those before; two frame sets, one "
            f"before and one from that row, predict held-out regions {evidence}, and better "
            "than a drift by the margin: the tracker was moved or the tool re-seated; "
            f"{carried}: diagnose again with --frames-per-file --split-at "
            f"{Path(entry['file']).name}:{entry['row']} (frames of its own from that row)"
        )
    if entry["kind"] == "change_and_drift":
        drift = entry["drift"]["shift_mm"]
        return (
            f"the set-up drifted during {entry['file']} and moved near row {entry['row']}: "
            f"the rows from it are shifted by {size} against those before, on top of a "
            f"drift of {drift['mean']:.3g} mm (mean; up to {drift['max']:.3g} mm) from its "
            f"first row to its last; a drift and a change together predict held-out "
            f"regions {evidence}, and better than either alone by the margin: a tracker or "
            f"fixture settling, and a knock; {carried}: diagnose again with "
            f"--frames-per-file --split-at {Path(entry['file']).name}:{entry['row']} "
            "(the drift remains within each part)"
        )
    if entry["kind"] == "drift":
        return (
            f"the set-up drifted during {entry['file']}: its last rows are shifted by {size} "
            f"against its first, growing with the rows; frames drifting with the "
            f"rows predict held-out regions {evidence}, and a change at one row does no "
            f"better: a tracker or fixture settling, or the room warming; {carried}"
        )
    return (
        f"the set-up moved during {entry['file']}: a change near row {entry['row']} (the rows "
        f"from it shifted by {size}) and a drift both predict held-out regions better than "
        f"one frame set ({gain:.3g} mm, margin {margin:.3g} mm), within the margin of each "
        f"other: the data cannot tell a change from a drift; {carried}"
    )


def mention_moves(structural: dict | None, moves: list[dict]) -> dict | None:
    """The structural verdict (``None``: none) with the set-up moves named: a move of the
    set-up is a frame change that no cause explains, and the causes fitted to it are
    what the verdict may be speaking of (a nudged table's wrist eccentricity "not a
    small correction", "the URDF may be wrong in more than one place")."""
    if structural is None or not moves or structural.get("structurally_wrong"):
        return structural
    where = ", ".join(
        f"{Path(m['file']).name}" + (f" at row {m['row']}" if m["row"] is not None else "")
        for m in moves
    )
    message = (
        f"{structural['message']}; but the set-up moved during the rows ({where}: see the "
        "set-up warning), which the causes were fitted to as well: give it frames of its "
        "own first (--split-at) and diagnose again"
    )
    return {**structural, "message": message}

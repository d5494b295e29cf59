"""Blocked hold-out of a hybrid's training rows: probe fits that decide which stages
carry over beyond their training joints (:mod:`~hybrid_pk.hybrid.blocked_trust`).

Blocks (contiguous regions of the training rows, :func:`blocked_blocks`):

- the lowest and the highest quarter of joint 1 (tests the equivariance to joint 1);
- the same of the joint that moves the flange point most after it
  (:func:`~hybrid_pk.hybrid.posture.moving_joints`; tests that the posture and load
  inputs carry the error to postures not trained on);
- each file, when the rows come from several (another set-up).

The probe fits (:func:`probe_folds`) leave out one end of each joint at a time (joint
1's low quarter with the other joint's high one, then the reverse) and each file in
turn; each trains the same networks with the same schedule on the rest and is judged on
what it left out. A block's rows are the main fit's training and validation rows in it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.hybrid.blocked_trust import decide
from hybrid_pk.hybrid.hybrid_fk import HybridFK
from hybrid_pk.hybrid.losses import (
    ResidualTargets,
    corrected_orientation_errors_deg,
    corrected_position_errors_mm,
)
from hybrid_pk.hybrid.posture import moving_joints
from hybrid_pk.hybrid.stage import combine_stages
from hybrid_pk.hybrid.tuning import hybrid_tuning
from hybrid_pk.robot import Robot

__all__ = [
    "Block",
    "blocked_blocks",
    "blocked_check",
    "fold_rows",
    "probe_folds",
]


@dataclass(frozen=True)
class Block:
    """A contiguous region: ``joint`` (0-based) in ``[lower, upper]``, or file ``file``."""

    label: str
    joint: int | None = None
    lower: float = -float("inf")
    upper: float = float("inf")
    file: int | None = None

    def mask(self, q: Tensor, files: Tensor | None) -> Tensor:
        """``(N,)`` rows of joints ``q (N, dof)`` (from ``files (N,)``) in the block."""
        if self.file is not None:
            return files == self.file
        x = q[:, self.joint]
        return (x >= self.lower) & (x <= self.upper)


def blocked_blocks(robot: Robot, q: Tensor, files: Tensor | None = None) -> list[Block]:
    """The blocks of training rows ``q (N, dof)`` (``files``: their file indices)."""
    q = q.detach().to(torch.float64)
    n, out = q.shape[0], []
    tuning = hybrid_tuning()
    quarter = tuning.block_quarter
    for j in [0, *moving_joints(robot, q)[:1]]:
        lo, hi = torch.quantile(q[:, j], quarter), torch.quantile(q[:, j], 1 - quarter)
        name = robot.joint_names[j]
        for block in (
            Block(f"{name} low quarter", j, upper=float(lo)),
            Block(f"{name} high quarter", j, lower=float(hi)),
        ):
            rows = int(block.mask(q, files).sum())
            if tuning.min_block_rows <= rows <= n // 2:  # a joint that barely moves has no ends
                out.append(block)
    if files is not None and int(files.unique().numel()) > 1:
        out += [Block(f"file {int(f) + 1}", file=int(f)) for f in files.unique()]
    return out


def probe_folds(blocks: list[Block]) -> list[list[Block]]:
    """Blocks left out together: one end of each joint per fit (joint 1's low end with
    the next joint's high end, then the reverse), each file alone."""
    by_joint: dict[int, list[Block]] = {}
    for b in blocks:
        if b.file is None:
            by_joint.setdefault(b.joint, []).append(b)
    folds = []
    for flip in (0, 1):
        fold = [
            b
            for k, ends in enumerate(by_joint.values())
            for b in ends
            if (b.upper < float("inf")) == ((k + flip) % 2 == 0)
        ]
        if fold:
            folds.append(fold)
    return folds + [[b] for b in blocks if b.file is not None]


def fold_rows(
    train: ResidualTargets,
    val: ResidualTargets,
    fold: list[Block],
    files: tuple[Tensor | None, Tensor | None] = (None, None),
) -> tuple[ResidualTargets, ResidualTargets, list[tuple[str, ResidualTargets]]]:
    """A probe's training and validation rows (those outside the ``fold``'s blocks) and
    its left-out rows per block (the training and validation rows inside it; a row in
    two blocks counts for both)."""
    kept, held = [], []
    for t, f in ((train, files[0]), (val, files[1])):
        inside = torch.zeros(t.n, dtype=torch.bool)
        for b in fold:
            mask = b.mask(t.q, f)
            inside |= mask
            if bool(mask.any()):
                held.append((b.label, t.subset(torch.nonzero(mask)[:, 0])))
        kept.append(t.subset(torch.nonzero(~inside)[:, 0]))
    return kept[0], kept[1], held


def _errors(hybrid: HybridFK, t: ResidualTargets, modes: dict[int, str]) -> dict[str, Tensor]:
    """Per-row errors of ``hybrid`` on rows ``t`` with the probed stages in ``modes``."""
    stages = list(hybrid.stages)
    encoded = hybrid.encode_all(t.q)
    own = [
        stage.weight(t.q, u, gated=modes.get(i, "gated") == "gated")
        for i, (stage, (u, _)) in enumerate(zip(stages, encoded, strict=True))
    ]
    saved = [stage.spread for stage in stages]
    try:
        for i, stage in enumerate(stages):
            if i in modes and modes[i] != "shrunk":
                stage.spread = None
        dp, dw = hybrid.predict_all(encoded, combine_stages(stages, own))
    finally:
        for stage, spread in zip(stages, saved, strict=True):
            stage.spread = spread
    out = {"position": corrected_position_errors_mm(t.position, t.lever, dp, dw)}
    if t.rotation is not None and hybrid.orientation is not None:
        out["orientation"] = corrected_orientation_errors_deg(t.rotation, dw)
    return out


def _family(label: str) -> str:
    """The invariance a block tests: its joint (``<joint> low quarter``) or ``file``."""
    return label.split(" ")[0]


def _scorer(probes: list[tuple[HybridFK, list[tuple[str, ResidualTargets]]]]) -> Callable:
    """Blocked score of a choice of modes, per family of blocks, over every probe's
    left-out rows (each block's rows are judged by the probe that left it out)."""
    rows = [(_family(label), t) for _, held in probes for label, t in held]
    zero = {id(t): torch.zeros_like(t.position) for _, t in rows}
    physics = _pooled([(f, _physics_errors(t, zero[id(t)])) for f, t in rows])

    @torch.no_grad()
    def score(modes: dict[int, str]) -> tuple[dict[str, Tensor], dict[str, float]]:
        errors = [(_family(label), _errors(h, t, modes)) for h, held in probes for label, t in held]
        families = {}
        for family in sorted({f for f, _ in errors}):
            parts = [e for f, e in errors if f == family]
            base = physics[family]
            families[family] = sum(
                torch.cat([p[k] for p in parts]) / max(base[k], 1e-12) for k in parts[0]
            )
        return families, _named(_pooled(errors)["all"])

    score.physics = _named(physics["all"])
    return score


def _physics_errors(t: ResidualTargets, zero: Tensor) -> dict[str, Tensor]:
    out = {"position": corrected_position_errors_mm(t.position, t.lever, zero, zero)}
    if t.rotation is not None:
        out["orientation"] = corrected_orientation_errors_deg(t.rotation, zero)
    return out


def _pooled(errors: list[tuple[str, dict[str, Tensor]]]) -> dict[str, dict[str, float]]:
    """Mean errors of each family and of all (``"all"``), with their row counts."""
    out: dict[str, dict[str, float]] = {}
    for family in [*sorted({f for f, _ in errors}), "all"]:
        parts = [e for f, e in errors if family in (f, "all")]
        out[family] = {k: float(torch.cat([p[k] for p in parts]).mean()) for k in parts[0]}
        out[family]["rows"] = sum(p["position"].numel() for p in parts)
    return out


def _named(means: dict[str, float]) -> dict[str, float]:
    units = {"position": "position_mm", "orientation": "orientation_deg", "rows": "rows"}
    return {units[k]: int(v) if k == "rows" else round(v, 6) for k, v in means.items()}


def blocked_check(
    hybrid: HybridFK,
    probes: list[tuple[HybridFK, list[tuple[str, ResidualTargets]]]],
    labels: list[str],
) -> dict[int, dict]:
    """Decide the mode of each stage of ``hybrid`` with a gate from the ``probes``
    (probe model, its left-out rows) and apply it: ``free`` frees the gate (joint 1's
    trained range stays), anything but ``shrunk`` drops the spread. Returns ``{stage:
    record}`` (also kept as each stage's
    :attr:`~hybrid_pk.hybrid.stage.ResidualStage.blocked`)."""
    probed = [i for i, stage in enumerate(hybrid.stages) if stage.gate is not None]
    spread = {i for i in probed if hybrid.stages[i].spread is not None}
    score = _scorer(probes)
    out = {}
    for i, record in decide(probed, spread, score).items():
        stage = hybrid.stages[i]
        stage.blocked = {**record, "physics": score.physics, "blocks": list(labels)}
        out[i] = stage.blocked
        stage.gate.free = record["mode"] != "gated"
        if record["mode"] != "shrunk":
            stage.spread = None
    return out

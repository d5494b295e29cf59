"""Selection by what carries over: blocked hold-out gains of causes and candidates.

A cause enters, stays and keeps its place only if it improves the blocked hold-out
(:mod:`.blocked`) by the practical margin (:func:`.blocked.practical_margin`); the
significance tests of the search stay as a necessary condition.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from torch import Tensor

from hybrid_pk.calibration.diagnosis.blocked import (
    Blocked,
    Folds,
    cell_factors,
    margin_sigma,
    position_channel,
    practical_margin,
)
from hybrid_pk.calibration.diagnosis.noise import NoiseEstimate
from hybrid_pk.calibration.diagnosis.split import Split
from hybrid_pk.calibration.fit import FitResult
from hybrid_pk.calibration.problem import ParamBlock, Problem, param_blocks
from hybrid_pk.calibration.shared_jacobian import shared_chunks
from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.effects import ExtendedModel

__all__ = ["Carry", "linearise", "margin_text", "removal_gains", "weakest"]


@dataclass(frozen=True)
class Carry:
    """The blocked hold-out settings of one diagnosis.

    Attributes:
        folds: the blocks (None: too few rows in one file; no blocked decision).
        min_gain_mm: ``--min-gain-mm``, or None for the default rule.
        noise: the model-free measurement noise (:mod:`.noise`; None: the fit's sigma).
    """

    folds: Folds | None
    min_gain_mm: float | None = None
    noise: NoiseEstimate | None = None

    @property
    def noise_mm(self) -> float | None:
        return None if self.noise is None else self.noise.sigma_mm

    def margin(self, res: FitResult) -> float:
        """The practical margin [mm] under ``res``'s noise estimate."""
        return practical_margin(res.sigma_pos_mm, self.min_gain_mm, self.noise_mm)

    def rule(self, res: FitResult) -> dict:
        """The margin and how it was set (the diagnosis JSON's ``carry_over``)."""
        rows = diagnosis_tuning().check_rows
        return {
            "min_gain_mm": self.margin(res),
            "rule": "--min-gain-mm"
            if self.min_gain_mm is not None
            else f"noise sigma_pos / sqrt(2 x {rows}): the standard error of an RMS "
            f"error measured on a check of {rows} poses; sigma_pos the model-free noise "
            "estimate (noise) capped by the fit's sigma (fit_sigma_mm)",
            "noise_position_mm": margin_sigma(res.sigma_pos_mm, self.noise_mm),
            "check_rows": rows,
            "fit_sigma_mm": res.sigma_pos_mm,
            "noise": None if self.noise is None else self.noise.to_json(),
            "gain": "drop of the RMS "
            + (
                "position error [mm]"
                if position_channel()
                else "error [mm] (rotation counted at the noise ratio sigma_pos / sigma_rot)"
            )
            + " on rows held out in blocks (regions of joint space, whole files); each "
            "block predicted by a linearised refit on the others (every measured component)",
            "entry": "a candidate enters when its blocked gain reaches the margin and its "
            "own standard error over the blocks (delete-one-block jackknife: the "
            "one-standard-error rule); a cause stays while it gains the margin",
            "channel": "position" if position_channel() else "pose",
            "blocks": None if self.folds is None else self.folds.description,
        }


def margin_text(carry_over: dict | None) -> str | None:
    """``practical margin M mm = noise S mm / sqrt(2 x N); noise: how it was found``
    from the diagnosis JSON's ``carry_over``; None without blocks (no margin used)."""
    if not carry_over or carry_over.get("blocks") is None:
        return None
    noise, fit_sigma = carry_over.get("noise") or {}, carry_over["fit_sigma_mm"]
    files = "; ".join(
        f"{Path(f['file']).name} {f['sigma_mm']:.2g} mm ({f['pairs']} pairs)"
        for f in noise.get("files", ())
    )
    how = (
        f"model-free {noise['sigma_mm']:.2g} mm from the closest pairs of poses per file "
        f"({files}), capped by the fit's sigma {fit_sigma:.2g} mm"
        if noise.get("sigma_mm") is not None
        else f"the fit's sigma {fit_sigma:.2g} mm (no pair of poses to compare)"
    )
    head = f"practical margin {carry_over['min_gain_mm']:.3g} mm"
    # a JSON written before the entry rule has no "entry": its search had none
    entry = "; to enter, a gain also above its standard error over the blocks" * (
        "entry" in carry_over
    )
    if carry_over["rule"] == "--min-gain-mm":
        return f"{head} (--min-gain-mm); noise: {how}{entry}"
    sigma, rows = carry_over["noise_position_mm"], carry_over["check_rows"]
    return f"{head} = noise {sigma:.2g} mm / sqrt(2 x {rows}); noise: {how}{entry}"


def linearise(
    trial: ExtendedModel,
    res: FitResult,
    split: Split,
    folds: Folds | None,
    progress: Callable[[str], None] | None = None,
    factor: bool = True,
    candidates: int = 0,
    keep: bool = False,
    share: bool = True,
) -> tuple[Problem, tuple[ParamBlock, ...], Tensor | None, Blocked | None]:
    """One Jacobian of every free parameter of ``trial`` on the fit rows: the problem,
    its blocks, a factor ``R`` of ``[J r]`` (None unless ``factor``: the blocked score
    alone needs only the cell Grams) and the cell Grams of the blocked score.

    ``candidates``: the last blocks are that many candidates; the factor's QR covers
    only the columns before them, the rest is completed from the Gram
    (:func:`.blocked.cell_factors`). With candidates or ``keep`` the chunks of
    ``[J r]`` are kept (``problem.kept``) for a refit to step with. ``share``: the
    columns come from, and go into, the point kept by
    :func:`~hybrid_pk.calibration.shared_jacobian.shared_chunks` (False: a one-off
    point, e.g. a variant fitted on part of the range, that would replace it)."""
    fixed = set() if res.priors is None else set(res.priors.fixed_labels())
    blocks = param_blocks(trial, None, split.position_only)
    blocks = tuple(b for b in blocks if b.label not in fixed)
    sig_r = res.sigma_rot_rad or 1.0
    # robust fits: the rows weigh as in the fit (a gross row does not score a candidate)
    weights = None if res.weights is None else res.weights.sqrt()
    problem = Problem(
        trial, split.train, split.cond_fit, blocks, res.sigma_pos_mm, sig_r,
        row_weights=weights, progress=progress,
    )  # fmt: skip
    lead = sum(b.size for b in blocks[: len(blocks) - candidates]) if candidates else None
    if share:  # the kept point's chunks: every column asked for there, its noise levels
        chunks, kept = shared_chunks(problem)
        R, pos, rot = cell_factors(problem, folds, factor, lead, chunks)
        problem.kept, problem.kept_blocks = kept.chunks, tuple(kept.blocks)
        problem.kept_sigmas = kept.sigmas
    else:
        problem.kept = [] if candidates or keep else None
        R, pos, rot = cell_factors(problem, folds, factor, lead)
        if problem.kept is not None:  # one pass's chunks (a fallback QR makes a second)
            problem.kept = problem.kept[: len(range(0, split.train.n, problem.chunk_rows))]
    blocked = None
    if folds is not None:
        values = problem.x0 / problem.scale
        sigmas = (res.sigma_pos_mm, None if split.position_only else res.sigma_rot_rad)
        blocked = Blocked(pos, rot, folds, blocks, values, sigmas)
    return problem, blocks, R, blocked


def removal_gains(blocked: Blocked, effects: list[str], gone=()) -> dict[str, dict]:
    """Per effect of ``effects``: the blocked gain [mm] of keeping it (the model without
    it, re-fitted per block, against the model with all), its standard error over the
    blocks [mm], with its position [mm] and orientation [deg] parts. ``gone``: effects
    of the linearisation that the model no longer has (set to zero)."""
    full = blocked.of(effects, gone)
    out = {}
    for label in effects:
        rest = [e for e in effects if e != label]
        without = blocked.of(rest, [label, *gone])
        out[label] = {
            "gain_mm": blocked.gain_mm(without, full),
            "se_mm": blocked.gain_se_mm(without, full),
            **blocked.parts(without, full),
        }
    return out


def weakest(blocked: Blocked, effects: list[str], margin: float, keep=None, gone=(), only=None):
    """``(label, gain)`` of the effect (not ``keep``; among ``only`` when given) with
    the smallest blocked gain of keeping it, when that is below ``margin``; None when
    every one carries over."""
    gains = removal_gains(blocked, effects, gone)
    gains = {k: v["gain_mm"] for k, v in gains.items() if k != keep and (only is None or k in only)}
    if not gains:
        return None
    label = min(gains, key=gains.get)
    return (label, gains[label]) if gains[label] < margin else None

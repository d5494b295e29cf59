"""Leave one file out: does a calibration carry over to another set-up?

Each measured file of a campaign is a set-up of its own (the tracker stationed anew, a
tool re-mounted, another workspace). For every file ``k``: the nominal model and the
extended model (the given causes) are fitted, frames included, to the other files only;
then, as a user moving the robot would, only the base and tool frames are re-fitted on
``refit_rows`` random rows of file ``k``; both models are judged on the rest of file
``k``. The extended model carries over when its error there stays well below that of
nominal + frames.

:func:`leave_one_file_out` returns a :class:`TransferResult`; ``diagnose`` and
``calibrate`` with several files print and store it (``--refit-rows``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hybrid_pk.calibration.fit import fit
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.calibration.settings import DiagnosisSettings
from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel, Gravity, conditions_from_data, make_effect
from hybrid_pk.evaluation.metrics import error_stats, row_errors
from hybrid_pk.robot import Robot

__all__ = ["DEFAULT_REFIT_ROWS", "FileTransfer", "TransferResult", "leave_one_file_out"]

# Rows the frames are re-fitted on (the reason is written at the settings' field).
DEFAULT_REFIT_ROWS = DiagnosisSettings.refit_rows
# The frame parameters of a re-fit (labels of calibration.fit).
_FRAMES = (
    "base_frame.translation",
    "base_frame.rotation",
    "tool_frame.translation",
    "tool_frame.rotation",
)
_STATS = ("mean", "rms", "p95", "max")


@dataclass(frozen=True)
class FileTransfer:
    """One left-out file: position errors [mm] on its judged rows (``mean``, ``rms``,
    ``p95``, ``max``) of nominal + frames and of the extended model, both fitted without
    the file, frames re-fitted on ``refit_rows`` of its rows; or why it was skipped."""

    file: str
    fit_rows: int
    refit_rows: int
    judged_rows: int
    nominal_mm: dict | None = None
    extended_mm: dict | None = None
    skipped: str | None = None

    @property
    def ratio(self) -> float | None:
        """Mean error of the extended model over that of nominal + frames."""
        if self.nominal_mm is None or self.extended_mm is None:
            return None
        return self.extended_mm["mean"] / max(self.nominal_mm["mean"], 1e-12)

    def to_json(self) -> dict:
        out = dataclasses.asdict(self)
        out["extended_over_nominal"] = self.ratio
        return out


@dataclass(frozen=True)
class TransferResult:
    """Leave-one-file-out errors of a campaign (one :class:`FileTransfer` per file)."""

    refit_rows: int
    effects: tuple[str, ...]
    files: tuple[FileTransfer, ...]
    seed: int

    def to_json(self) -> dict:
        return {
            "method": "leave one file out: nominal and extended models fitted on the other "
            "files, base and tool frames re-fitted on refit_rows random rows of the file, "
            "judged on its other rows (position error, mm)",
            "refit_rows": self.refit_rows,
            "effects": list(self.effects),
            "seed": self.seed,
            "files": [f.to_json() for f in self.files],
        }

    def lines(self) -> list[str]:
        """The table ``diagnose`` and ``calibrate`` print."""
        names = [Path(f.file).name for f in self.files]
        w = max([len("left-out file"), *map(len, names)])  # whole names: they tell files apart
        out = [
            f"transfer (leave one file out; frames re-fitted on {self.refit_rows} rows of "
            "the left-out file, judged on its other rows), position [mm]:",
            f"  {'left-out file':<{w}}{'judged':>8}  {'nominal+frames mean/max':>24}"
            f"  {'extended mean/max':>18}  {'ratio':>6}",
        ]
        for name, f in zip(names, self.files, strict=True):
            if f.skipped is not None:
                out.append(f"  {name:<{w}}  skipped: {f.skipped}")
                continue
            nom = f"{f.nominal_mm['mean']:.4g} / {f.nominal_mm['max']:.4g}"
            ext = f"{f.extended_mm['mean']:.4g} / {f.extended_mm['max']:.4g}"
            out.append(f"  {name:<{w}}{f.judged_rows:>8}  {nom:>24}  {ext:>18}  {f.ratio:>6.3f}")
        return out


def leave_one_file_out(
    robot: Robot,
    data: MeasuredData,
    effects: Sequence[str],
    *,
    refit_rows: int = DEFAULT_REFIT_ROWS,
    frames_per_file: bool = True,
    gravity: Gravity | None = None,
    priors: FramePriors | None = None,
    robust: str | None = None,
    seed: int = 0,
    start: ExtendedModel | None = None,
    progress: Callable[[str], None] | None = None,
) -> TransferResult:
    """Leave-one-file-out errors of nominal + frames and of the model with ``effects``.

    Args:
        robot: nominal robot (its parameters are not fitted).
        data: rows of several files (``data.sources``).
        effects: ``kind:joint`` labels of the extended model.
        refit_rows: rows of the left-out file its frames are re-fitted on.
        frames_per_file: the other files keep one frame set each (else one shared).
        gravity, priors, robust: as for the calibration (mounting, known frames, loss).
        seed: seed of the choice of re-fit rows.
        start: a model holding ``effects`` (the calibration's): their values start each
            fit (else they start at zero).
        progress: called with a short text before each file.
    """
    if refit_rows < 1:
        raise ValueError(f"refit_rows must be at least 1, got {refit_rows}")
    cond_all = conditions_from_data(data, frames_per_file)
    rng = np.random.default_rng(seed)
    made = [_effect(robot, label, start) for label in effects]
    files = []
    for k, source in enumerate(data.sources):
        if progress is not None:
            progress(f"transfer: leaving out {source}")
        files.append(
            _one_file(robot, data, cond_all, k, made, refit_rows, rng, gravity, priors, robust)
        )
    return TransferResult(refit_rows, tuple(effects), tuple(files), seed)


def _one_file(robot, data, cond_all, k, effects, refit_rows, rng, gravity, priors, robust):
    inside = data.file_index == k
    rest, held = _relabelled(data, cond_all, ~inside), _relabelled(data, cond_all, inside)
    source = data.sources[k]
    n_k = int(inside.sum())
    if n_k <= refit_rows:
        why = f"{n_k} rows, not more than the {refit_rows} re-fit rows"
        return FileTransfer(source, rest[0].n, refit_rows, 0, skipped=why)
    pick = torch.zeros(n_k, dtype=torch.bool)
    pick[torch.as_tensor(rng.choice(n_k, size=refit_rows, replace=False))] = True
    refit_part, judged = _part(held, pick), _part(held, ~pick)
    sets = int(rest[1].group.max()) + 1 if rest[1].group is not None else 1
    nominal, weights = _fit_model(robot, [], rest, sets, gravity, priors, robust)
    extended, _ = _fit_model(robot, effects, rest, sets, gravity, priors, robust, weights)
    errors = []
    for model in (nominal, extended):
        moved = ExtendedModel(robot, list(model.effects), frame_sets=1, gravity=model.gravity)
        _fit_frames(moved, refit_part, priors, robust)
        with torch.no_grad():
            pos = row_errors(moved(judged[0].q, judged[1]), judged[0])[0]
        stats = error_stats(pos)
        errors.append({s: float(getattr(stats, s)) for s in _STATS})
    return FileTransfer(source, rest[0].n, refit_rows, judged[0].n, errors[0], errors[1])


def _effect(robot: Robot, label: str, start: ExtendedModel | None):
    """A factory of fresh ``label`` effects, valued as in ``start`` if given."""
    value = None if start is None else start.effect(label).value.detach().clone()
    return lambda: make_effect(robot, label, None if value is None else value.clone())


def _relabelled(data: MeasuredData, cond: Conditions, mask) -> tuple[MeasuredData, Conditions]:
    """Rows ``mask`` with their files numbered anew (0..) and conditions to match; the
    approach directions are those of the full files (the acquisition order)."""
    sub, sub_cond = data.subset(mask), cond.subset(mask)
    kept = sorted(set(sub.file_index.tolist()))
    index = torch.tensor([kept.index(i) for i in sub.file_index.tolist()], dtype=torch.long)
    sub = dataclasses.replace(sub, file_index=index, sources=tuple(data.sources[i] for i in kept))
    group = None if sub_cond.group is None else index
    return sub, dataclasses.replace(sub_cond, group=group)


def _part(pair: tuple[MeasuredData, Conditions], mask) -> tuple[MeasuredData, Conditions]:
    data, cond = pair
    return data.subset(mask), cond.subset(mask)


def _fit_model(robot, effects, pair, sets, gravity, priors, robust, weights=None):
    """A model with ``effects`` (factories; frames included) fitted to ``pair``; its row
    weights."""
    data, cond = pair
    model = ExtendedModel(robot, [e() for e in effects], frame_sets=sets, gravity=gravity)
    initialise_with_priors(model, data, cond, priors)
    res = fit(
        model, data, cond=cond, frames=priors, robust=robust, weights=weights, covariance=False
    )
    return model, res.weights


def _fit_frames(model, pair, priors, robust) -> None:
    data, cond = pair
    cond = dataclasses.replace(cond, group=None)
    initialise_with_priors(model, data, cond, priors)
    fit(model, data, free=list(_FRAMES), cond=cond, frames=priors, robust=robust, covariance=False)

"""The ik workflow: every distinct joint solution of target poses on a model file,
with the kinematics plus frames alone, or refined on the full model (effects or
residual networks) by a two-stage solve in chunks of targets.

    res = solve_targets(load_model("model.pt"), data)
    res.frame.to_csv("solutions.csv")
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import pandas as pd
import torch

from hybrid_pk.data import MeasuredData
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.errors import HybridPKError
from hybrid_pk.ik import (
    IKAssumption,
    IKOptions,
    IKResult,
    resolve_conditions,
    solve_ik,
    solve_ik_two_stage,
)
from hybrid_pk.ik.compensation import chain_reach
from hybrid_pk.ik.conditions import Approach
from hybrid_pk.ik.two_stage import DEFAULT_BOX
from hybrid_pk.io.hybrid_file import load_hybrid, networks_used
from hybrid_pk.io.model_file import LoadedModel

__all__ = ["CHUNK", "IKJob", "solutions_frame", "solve_targets", "target_reach"]

CHUNK = 128  # targets per two-stage solve (the progress moves after each)


@dataclass(frozen=True)
class IKJob:
    """What :func:`solve_targets` returns: one solutions table (``target`` indexes the
    rows of the targets), whether the full model refined them, and the notes on the
    conditions assumed."""

    frame: pd.DataFrame
    two_stage: bool
    notes: list[str] = field(default_factory=list)
    closest_mm: torch.Tensor | None = None  # (N,) IKResult.closest_mm of every target
    closest_deg: torch.Tensor | None = None
    near_singular: torch.Tensor | None = None  # (N,) IKResult.near_singular
    smallest_singular_value: torch.Tensor | None = None  # (N,) [m/rad]


def _expensive(loaded: LoadedModel, model: ExtendedModel):
    """The accurate model when it is more than the kinematics plus frames, else None."""
    if networks_used(loaded):
        return load_hybrid(loaded)
    return model if len(model.effects) else None


def _conditions(data, models, k: int, sets: int, approach, fixes) -> tuple[Conditions, list]:
    """Conditions of the targets: payload and temperature from the data, the frame set,
    and the backlash ``approach`` (else mid-play), with the notes that say so."""
    group = torch.full((data.n,), k, dtype=torch.long) if sets > 1 else None
    cond = Conditions(payload=data.payload, temperature=data.temperature, group=group)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IKAssumption)  # returned as notes
        return resolve_conditions(models, cond, data.n, approach, fixes=fixes)


def solve_targets(
    loaded: LoadedModel, data: MeasuredData, frame_set: int = 0, *, seeds: int = 8,
    options: IKOptions | None = None, box: float = DEFAULT_BOX, approach: Approach = None,
    fixes: Mapping[str, str] | None = None, progress: Callable[[int], None] | None = None,
    started: Callable[[int, bool], None] | None = None,
) -> IKJob:  # fmt: skip
    """All solutions of the targets in ``data`` (poses, or positions) on MODEL
    (``loaded``, frame set ``frame_set``); joint columns in ``data`` are extra seeds.

    Args:
        seeds, options: as in :func:`~hybrid_pk.ik.solve_ik`; ``box`` the two-stage
            refinement's joint box.
        approach: the backlash approach (only for a model with effects or networks).
        fixes: how a user states each assumed condition, for the notes.
        progress: told the number of targets done after each chunk; ``started`` told
            the number of targets and whether the solve is two-stage, first.

    Raises:
        HybridPKError: an ``approach`` for a model without effects.
    """
    model = loaded.model
    robot = model.robot
    targets = data.T_measured() if data.has_orientation else data.position
    extra = data.q[:, None, :] if data.q.shape[1] == robot.dof else None
    with torch.no_grad():
        base, tool = model.base.matrix()[frame_set], model.tool.matrix()[frame_set]
    cheap = ExtendedModel(robot, [], base=base, tool=tool)
    expensive = _expensive(loaded, model)
    cond, notes = None, []
    if expensive is not None:
        sets = model.base.sets
        cond, notes = _conditions(data, [expensive], frame_set, sets, approach, fixes)
    elif approach is not None:
        raise HybridPKError(f"--approach: {loaded.source} has no backlash effect")
    common = {"seeds": seeds, "options": options or IKOptions()}
    progress = progress or (lambda _n: None)
    n = targets.shape[0]
    if started is not None:
        started(n, expensive is not None)
    if expensive is None:
        result = solve_ik(cheap, targets, extra_seeds=extra, progress=progress, **common)
        return IKJob(solutions_frame(result), False, list(notes), *_per_target([result]))
    parts = []
    for lo in range(0, n, CHUNK):
        rows = torch.arange(lo, min(n, lo + CHUNK))
        parts.append(
            solve_ik_two_stage(
                cheap, expensive, targets[rows], box=box, cond=cond.subset(rows), robot=robot,
                extra_seeds=None if extra is None else extra[rows], **common,
            )
        )  # fmt: skip
        progress(rows.numel())
    return IKJob(solutions_frame(parts), True, list(notes), *_per_target(parts))


def _per_target(results: list[IKResult]) -> tuple[torch.Tensor, ...]:
    """``(N,)`` each of the chunks' :data:`_PER_TARGET` fields, in IKJob's order."""
    return tuple(torch.cat([getattr(r, a).reshape(-1) for r in results]) for a in _PER_TARGET)


_PER_TARGET = ("closest_mm", "closest_deg", "near_singular", "smallest_singular_value")


def solutions_frame(results: IKResult | list[IKResult]) -> pd.DataFrame:
    """One solutions table; chunks' target indices offset to rows of the targets."""
    if isinstance(results, IKResult):
        return results.to_frame()
    frames, offset = [], 0
    for part in results:
        frame = part.to_frame()
        frame["target"] += offset
        offset += part.counts.numel()
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def target_reach(
    loaded: LoadedModel, data: MeasuredData, frame_set: int = 0
) -> tuple[torch.Tensor, float]:
    """``(distance (N,) [m] of each target point from the robot's root origin, in MODEL's
    base frame; the reach [m] no configuration exceeds)``.

    The reach is the sum of the lengths of the joint origins' translations (the model's
    geometry, at the targets' temperatures or 20 °C), the prismatic joints' largest
    travel and the tool offset: by the triangle inequality no joint values put the
    measured point farther from the root origin, so a target beyond it is unreachable
    whatever the solver does (typically a target in another frame than the model's
    measurement frame).
    """
    model = loaded.model
    robot = model.robot
    temp = data.temperature
    if temp is None:
        temp = torch.full((data.n,), REFERENCE_TEMPERATURE, dtype=torch.float64)
    with torch.no_grad():
        base, tool = model.base.matrix()[frame_set], model.tool.matrix()[frame_set]
        params = model.kinematic_params(Conditions(temperature=temp))
        reach = chain_reach(robot, params.origin_xyz) + float(tool[:3, 3].norm())
        distance = (data.position.to(torch.float64) - base[:3, 3]).norm(dim=-1)
    return distance, reach

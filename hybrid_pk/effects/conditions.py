"""Operating conditions of each measured row besides its joint values.

Payload, temperature, the approach direction of each joint (backlash reads it) and the
frame set a row uses. :func:`conditions_from_data` derives them from a measured table.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.errors import DataError, ShapeError
from hybrid_pk.geometry.shapes import broadcast_shapes

__all__ = ["Conditions", "approach_direction", "conditions_from_data"]


@dataclass(frozen=True)
class Conditions:
    """Operating conditions of each sample besides ``q`` (all optional).

    Attributes:
        payload: ``(*B,)`` [kg] mass at the flange.
        temperature: ``(*B,)`` [°C].
        direction: ``(*B, dof)`` approach direction of each joint: +1, -1, or 0 (unknown).
        group: ``(*B,)`` long, which base/tool frame set a row uses (its file, when each
            file has its own frames); None = set 0.
    """

    payload: Tensor | None = None
    temperature: Tensor | None = None
    direction: Tensor | None = None
    group: Tensor | None = None

    def subset(self, index: Tensor) -> Conditions:
        return Conditions(*(None if x is None else x[index] for x in self._fields()))

    def check_batch(self, batch: torch.Size) -> None:
        """One-line error when a condition's batch does not broadcast with ``q``'s."""
        tails = {"payload": 0, "temperature": 0, "direction": 1, "group": 0}
        for (name, tail), x in zip(tails.items(), self._fields(), strict=True):
            if not isinstance(x, Tensor):
                continue
            try:
                broadcast_shapes(x.shape[: max(x.dim() - tail, 0)], batch)
            except RuntimeError:
                raise ShapeError(
                    f"Conditions.{name} has batch {tuple(x.shape[: x.dim() - tail])}, q has "
                    f"{tuple(batch)}: one value per sample (or one for all)"
                ) from None

    def _fields(self) -> tuple[Tensor | None, ...]:
        return (self.payload, self.temperature, self.direction, self.group)


def approach_direction(q: Tensor, file_index: Tensor | None = None) -> Tensor:
    """Direction each joint moved to reach each row, in acquisition order.

    ``sign(q[i] - q[i-1])``; a joint that did not move keeps its previous direction
    (it stays on the same side of its play); the first row of a file is 0 (unknown).

    Args:
        q: ``(N, dof)`` joint values in acquisition order.
        file_index: ``(N,)`` file of each row; rows of different files are not chained.
    """
    n = q.shape[0]
    first = torch.zeros(n, dtype=torch.bool, device=q.device)
    first[0] = True
    if file_index is not None:
        first[1:] = file_index[1:] != file_index[:-1]
    step = torch.zeros_like(q)
    step[1:] = torch.sign(q[1:] - q[:-1])
    step[first] = 0
    # Forward fill: each row takes the step of the last row (same file) where it moved.
    keep = (step != 0) | first[:, None]
    rows = torch.arange(n, device=q.device)[:, None].expand_as(q)
    last = torch.where(keep, rows, 0).cummax(dim=0).values
    return step.gather(0, last)


def conditions_from_data(
    data: MeasuredData, frames_per_file: bool = False, robot=None
) -> Conditions:
    """Operating conditions of every row: payload, temperature, approach direction, and
    (with ``frames_per_file``) the file's own base/tool frame set. With ``robot``, the
    data's joints must be the robot's (a table of another robot is refused)."""
    if not isinstance(data, MeasuredData):  # diagnose / fit / train given a path or array
        raise DataError(
            "data must be a MeasuredData (hpk.read_table_for(path, robot) reads a table), "
            f"got {type(data).__name__}"
        )
    if robot is not None and tuple(robot.joint_names) != tuple(data.joint_names):
        raise DataError(
            f"data has joints {', '.join(data.joint_names)}; robot {robot.name} has "
            f"{', '.join(robot.joint_names)}: a table of another robot?"
        )
    return Conditions(
        payload=data.payload,
        temperature=data.temperature,
        direction=approach_direction(data.q, data.file_index),
        group=data.file_index if frames_per_file else None,
    )

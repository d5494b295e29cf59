"""The compensate workflow: a robot program (joint targets or flange poses) read for
the model's robot, the joints that put the calibrated (or hybrid) model at the nominal
poses (:func:`~hybrid_pk.ik.compensation.compensate`), written as a joint table with
each row's residual and status.

    comp = compensate_program(load_model("model.pt"), read_program("prog.csv", robot))
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from hybrid_pk.data import joint_table, read_table_for
from hybrid_pk.data.cells import check_conditions, numeric_column, to_float
from hybrid_pk.data.files import PARQUET_SUFFIXES
from hybrid_pk.effects import Conditions
from hybrid_pk.errors import HybridPKError
from hybrid_pk.ik import IKOptions
from hybrid_pk.ik.compensation import COMPENSATION_BOX, Compensation, compensate
from hybrid_pk.ik.conditions import Approach, IKAssumption
from hybrid_pk.io.hybrid_file import forward_model
from hybrid_pk.io.model_file import LoadedModel
from hybrid_pk.robot import Robot

__all__ = ["Program", "compensate_program", "compensation_frame", "read_program"]

F64 = torch.float64


@dataclass(frozen=True)
class Program:
    """A robot program: nominal joint targets or flange poses (one of them), the
    rows' payload [kg] and temperature [degC] where given, ``kind`` for the messages,
    ``notes`` (columns left unused), ``columns``: a joint program's other columns as
    read (text), copied to the corrected program beside its joints, and ``angle_unit``:
    that of its revolute joints, the corrected program's too (``q_nominal`` is in rad)."""

    q_nominal: Tensor | None
    targets: Tensor | None
    payload: Tensor | None = None
    temperature: Tensor | None = None
    kind: str = "joint targets"
    notes: list[str] = field(default_factory=list)
    columns: pd.DataFrame | None = None
    angle_unit: str = "rad"

    @property
    def n(self) -> int:
        return (self.q_nominal if self.q_nominal is not None else self.targets).shape[0]


def read_program(path: str, robot: Robot, angle_unit: str = "rad") -> Program:
    """The program ``path``: joint targets (one column per joint, revolute ones in
    ``angle_unit``) or flange poses."""
    # Joint targets when a joint column is there, or when no x, y, z are (a program of
    # another robot's joints: the missing joint columns are the error to name).
    has = joint_table.has_joint_columns
    if has(path, robot.joint_names) or not has(path, ("x", "y", "z")):
        q, rest = joint_table.read_joint_table(path, robot, angle_unit)
        unused = [c for c in rest.columns if c not in ("payload", "temperature")]
        notes = [
            f"{path}: joint targets used; columns {', '.join(unused)} are not (copied to the "
            "output as they are)"
        ] * bool(unused)
        values = {
            c: numeric_column(str(path), rest[c], c)
            for c in ("payload", "temperature")
            if c in rest.columns
        }
        check_conditions(str(path), values, np.arange(1, len(rest) + 1))
        extra = {c: torch.tensor(v, dtype=F64) for c, v in values.items()}
        if {"status", "nominal_mm"} <= set(rest.columns):  # what compensate writes
            notes.append(
                f"warning: {path} is a compensate output (columns status, nominal_mm): its "
                "joints are corrected already, and corrected again they miss the targets by "
                "the correction once more; give the nominal program"
            )
        notes += _radians_read_as_degrees(path, q, robot, angle_unit)
        columns = rest if len(rest.columns) else None
        return Program(
            q, None, extra.get("payload"), extra.get("temperature"), notes=notes,
            columns=columns, angle_unit=angle_unit,
        )  # fmt: skip
    data = read_table_for([path], robot, n_params=1, require_joints=False)
    if not data.has_orientation:
        raise HybridPKError(
            f"{path}: a pose program needs the flange orientation qw qx qy qz besides x y z "
            "(or give the joint targets, one column per joint)"
        )
    return Program(None, data.T_measured(), data.payload, data.temperature, "flange poses")


def _radians_read_as_degrees(path, q: Tensor, robot: Robot, angle_unit: str) -> list[str]:
    """A warning when a program read in degrees looks like radians: every revolute
    value within one turn's worth of radians (2 pi), the largest above 1 (a program
    near the zero pose reads alike in both units). Read as degrees it would move each
    joint by less than 6.3 deg, less than a wrist's width at the tool; a warning, not
    an error, as such a small program is possible."""
    revolute = [j for j, kind in enumerate(robot.joint_types) if kind != "prismatic"]
    if angle_unit != "deg" or not revolute or not q.numel():
        return []
    stated = q[:, revolute].abs() * (180.0 / np.pi)  # the values as written [deg]
    top = float(stated.max())
    if not 1.0 < top <= 2 * np.pi:
        return []
    j = revolute[int(stated.max(0).values.argmax())]
    return [
        f"warning: {path}: every revolute joint value lies within +-6.28 (largest "
        f"{top:.4g}, column {robot.joint_names[j]}): these look like radians, which "
        "--angle-unit deg reads as degrees; if they are radians, leave --angle-unit out"
    ]


def compensate_program(
    loaded: LoadedModel,
    program: Program,
    *,
    frame_set: int = 0,
    box: float = COMPENSATION_BOX,
    options: IKOptions | None = None,
    approach: Approach = None,
    out: str | os.PathLike | None = None,
    fixes: Mapping[str, str] | None = None,
    controller: Robot | None = None,
) -> Compensation:
    """The joints that put MODEL (``loaded``, base/tool frame set ``frame_set``) at the
    program's nominal poses; written to ``out`` (joints, a joint program's other columns,
    residuals, status) if given.
    The IK's assumptions are in the result's ``assumed``, not warned, each with how to
    state it instead (``fixes``: the caller's words, e.g. a column of the program).
    ``controller``: the kinematics the program was computed with and the intended poses
    come from (default: MODEL's robot, the nominal URDF)."""
    model = loaded.model
    robot = model.robot
    group = torch.full((program.n,), frame_set, dtype=torch.long) if model.base.sets > 1 else None
    cond = Conditions(payload=program.payload, temperature=program.temperature, group=group)
    real = forward_model(loaded)
    real.requires_grad_(False)
    with torch.no_grad():
        base, tool = model.base.matrix()[frame_set], model.tool.matrix()[frame_set]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IKAssumption)  # the caller reports comp.assumed
        comp = compensate(
            real, controller or robot, base=base, tool=tool, q_nominal=program.q_nominal,
            targets=program.targets, cond=cond, box=box, options=options, approach=approach,
            fixes=fixes,
        )  # fmt: skip
    if out is not None:
        computed = compensation_frame(comp)
        if program.columns is not None:  # the program's own columns; this run's replace
            kept = program.columns.drop(columns=[c for c in computed if c in program.columns])
            if Path(out).suffix.lower() in PARQUET_SUFFIXES:  # typed: numbers as numbers
                kept = kept.apply(_typed)
            computed = pd.concat([kept.reset_index(drop=True), computed], axis=1)
        q = comp.q / torch.as_tensor(joint_table.angle_factors(robot, program.angle_unit))
        joint_table.write_joint_table(out, q, robot.joint_names, computed)
    return comp


def compensation_frame(comp: Compensation) -> pd.DataFrame:
    """The per-row columns written beside the corrected joints."""
    return pd.DataFrame(
        {
            "residual_mm": comp.residual_mm.numpy(),
            "residual_deg": comp.residual_deg.numpy(),
            "status": list(comp.status),
            "nominal_mm": comp.nominal_mm.numpy(),
            "nominal_deg": comp.nominal_deg.numpy(),
            "note": list(comp.note),
        }
    )


def _typed(column: pd.Series) -> pd.Series:
    """A CSV column read as text, as float64 where every cell is a finite number."""
    values, unparsable = to_float(column)
    if unparsable.any() or not np.isfinite(values).all():
        return column
    return pd.Series(values, index=column.index, name=column.name)

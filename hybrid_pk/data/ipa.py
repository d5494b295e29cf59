"""Import of the published UR10 laser-tracker measurements (IPA; Landgraf et al., CASE 2021).

Source format: ``;`` separator, ``,`` decimal; the six UR joint angles [rad], the
commanded pose ``Goal x,y,z`` [m] and ``Goal roll,pitch,yaw`` [rad],
``measurement_temperature`` [°C], the T-Mac pose measured by the laser tracker,
``measurement_x,y,z`` [mm] and ``measurement_rx,ry,rz`` [deg], and (Series B)
``measurement_std_*`` [mm, deg]. The ``Timestamp`` column was mangled by a
spreadsheet, so no ``t`` is written; row order is kept.

Euler conventions, verified on the data (:func:`detect_euler_convention`). The
reference is the flange orientation computed from the joint angles (UR DH twists
only, no lengths involved). The pairwise angle ``angle(R_i^T R_j)`` is invariant to
the unknown base and tool frames, but also to transposing every rotation: it cannot
tell intrinsic ``XYZ`` from extrinsic ``zyx`` fed the same three numbers (its "twin"
below). So the ranking fits the constant frames, ``R_i ≈ A R_ref_i B``, and compares
the rotation residual [deg RMS]:

=========================  ===========  =================  =====================
data                       winner       runner-up          pairwise: winner/twin
=========================  ===========  =================  =====================
measurement, Series A      XYZ 0.114    zyx 0.144          0.098 / 0.098
measurement, Series B      XYZ 0.0850   zyx 0.0856         0.078 / 0.078
measurement, hand-eye (B)  XYZ 0.0548   xyz 5.64           0.048 / 0.048
                                        (twin zyx 15.2)
Goal rpy, Series A         xyz 0.0656   zyz 13.7           0.057 / 0.057 (ZYX 21.3)
Goal rpy, Series B         xyz 0.0112   zyz 6.39           0.012 / 0.012 (ZYX 17.4)
=========================  ===========  =================  =====================

- ``measurement_rx,ry,rz`` are intrinsic ``XYZ`` angles, ``R = Rx(rx) Ry(ry) Rz(rz)``.
  The hand-eye file (``calibration_handeye.csv``, diverse orientations, flange
  quaternions as reference) separates it clearly; the two grids, whose commands sit
  near pitch = 90°, only weakly. Cyclic relabellings (``YZX``, ``ZXY``) fit exactly
  as well, as constant frames absorb them; the sequence that keeps rx, ry, rz on x, y,
  z is chosen. Corroboration: with ``XYZ`` the fitted tracker frame is level (its z
  axis within 0.6° of the robot's) and the fitted flange-to-T-Mac rotation is
  Rz(-90°) within 0.2°, the rotation of the published ``Trafo_TM_F_init.txt``.
- ``Goal roll,pitch,yaw`` is UR's extrinsic ``xyz``, ``R = Rz(yaw) Ry(pitch) Rx(roll)``,
  checked with the base rotation held at Rz(180°) (ROS ``base_link``; the Goal
  positions confirm it to 0.1 mm). The Goal pose is not the flange but a TCP 109 mm
  along the flange z axis, turned 90° about it (the T-Mac).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from decimal import Decimal
from functools import cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from hybrid_pk.data.cells import (
    RowProblems,
    check_header_names,
    check_joint_unit,
    missing_columns_error,
    note_joint_limits,
    to_float,
)
from hybrid_pk.data.euler import (
    EULER_SEQUENCES,
    ConventionScore,
    EulerDetection,
    describe_sequence,
    detect_euler_convention,
)
from hybrid_pk.data.files import read_text_cells, write_frame
from hybrid_pk.errors import DataError

__all__ = [
    "EULER_SEQUENCES",
    "GOAL_CONVENTION",
    "MEASUREMENT_CONVENTION",
    "UR_JOINT_NAMES",
    "ConventionScore",
    "EulerDetection",
    "IpaConventions",
    "IpaImport",
    "check_ipa_joints",
    "convert_ipa",
    "describe_sequence",
    "detect_euler_convention",
    "detect_ipa_conventions",
    "ipa_to_frame",
    "read_ipa_csv",
    "ur_flange_rotations",
]

MEASUREMENT_CONVENTION = "XYZ"
GOAL_CONVENTION = "xyz"
_UR_WRISTS = tuple(f"wrist_{k}_joint" for k in (1, 2, 3))
UR_JOINT_NAMES = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", *_UR_WRISTS)
MEASUREMENT_ANGLES = ("measurement_rx", "measurement_ry", "measurement_rz")
MEASUREMENT_POSITION = ("measurement_x", "measurement_y", "measurement_z")
GOAL_ANGLES = ("Goal roll", "Goal pitch", "Goal yaw")
_STD_COLUMNS = {
    "measurement_std_x": "std_x_mm",
    "measurement_std_y": "std_y_mm",
    "measurement_std_z": "std_z_mm",
    "measurement_std_rx": "std_rx_deg",
    "measurement_std_ry": "std_ry_deg",
    "measurement_std_rz": "std_rz_deg",
}
# Twist angles alpha_i [rad] of UR's DH table: all that flange orientation depends on.
_UR_DH_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)
# Goal poses are given in ROS base_link, turned by pi about z from the DH base frame.
_GOAL_FROM_DH = np.diag([-1.0, -1.0, 1.0])


# ----------------------------------------------------------------------------- reading


def read_ipa_csv(
    path: str | os.PathLike, columns: Sequence[str], optional: Sequence[str] = ()
) -> pd.DataFrame:
    """Numbers of an IPA file (``;`` separator, ``,`` decimal) as float64 columns.

    Args:
        path: the source file.
        columns: columns that must be there.
        optional: columns read when present.

    Returns:
        One float64 column per name found, rows in file order.

    Raises:
        DataError: missing column, duplicated header, or a cell that is no finite number.
    """
    path = Path(path)
    file = str(path)
    if path.stat().st_size == 0:
        raise DataError("empty file", file=file)
    raw = read_text_cells(path, sep=";")
    header = [str(c).strip() for c in raw.columns]
    check_header_names(file, header)
    raw.columns = header
    missing = [c for c in columns if c not in header]
    if missing:
        raise missing_columns_error(file, missing, header, note=" of the IPA UR10 format")
    if len(raw) == 0:
        raise DataError("no data rows below the header", file=file)
    out = {}
    for col in [*columns, *(c for c in optional if c in header)]:
        cells = raw[col].str.strip()
        values, bad = to_float(cells.str.replace(",", ".", regex=False))
        bad |= ~np.isfinite(values)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise DataError(
                f"cannot read {cells.iloc[k]!r} as a finite number (',' decimal)",
                file=file,
                row=k + 1,
                column=col,
            )
        out[col] = values
    return pd.DataFrame(out)


@cache
def _ur10_limits() -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """``(lower, upper, types)`` of :data:`UR_JOINT_NAMES`, from the shipped UR10's URDF."""
    from hybrid_pk.robot.chain_spec import load_chain_spec

    spec = load_chain_spec("ur10")
    order = [spec.joint_names.index(name) for name in UR_JOINT_NAMES]
    return spec.lower[order], spec.upper[order], tuple(spec.joint_types[k] for k in order)


def check_ipa_joints(file: str, raw: pd.DataFrame) -> None:
    """Raise at the first joint value of ``raw`` (rows of ``file``) that the table reader
    would refuse for the UR10, the one arm of the IPA data set: a column that holds
    degrees, or a value outside the joint limits. The error names the source file, its
    1-based data row and column, so no table is written that every command refuses."""
    lower, upper, types = _ur10_limits()
    columns = {name: raw[name].to_numpy() for name in UR_JOINT_NAMES}
    every = np.ones(len(raw), bool)
    for j, name in enumerate(UR_JOINT_NAMES):
        check_joint_unit(file, name, types[j], lower[j], upper[j], columns[name], every)
    problems = RowProblems(file, len(raw))
    note_joint_limits(problems, columns, UR_JOINT_NAMES, lower, upper, types, every)
    problems.raise_first()


def ipa_to_frame(raw: pd.DataFrame, convention: str = MEASUREMENT_CONVENTION) -> pd.DataFrame:
    """Parsed IPA columns -> table of contract section 1 (plus ``std_*`` extras).

    Joints are copied [rad]; ``measurement_x,y,z`` [mm] -> ``x, y, z`` [m];
    ``measurement_rx,ry,rz`` [deg] -> ``qw, qx, qy, qz`` (``w >= 0``) using the Euler
    ``convention`` (a scipy sequence); ``measurement_temperature`` -> ``temperature``
    [°C]; ``measurement_std_*`` -> ``std_*_mm`` / ``std_*_deg`` unchanged.
    """
    out = {name: raw[name].to_numpy() for name in UR_JOINT_NAMES}
    for src, dst in zip(MEASUREMENT_POSITION, ("x", "y", "z"), strict=True):
        out[dst] = _mm_to_m(raw[src].to_numpy())
    xyzw = Rotation.from_euler(convention, raw[list(MEASUREMENT_ANGLES)].to_numpy(), degrees=True)
    quat = xyzw.as_quat()[:, [3, 0, 1, 2]]
    quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    out.update(qw=quat[:, 0], qx=quat[:, 1], qy=quat[:, 2], qz=quat[:, 3])
    out["temperature"] = raw["measurement_temperature"].to_numpy()
    for src, dst in _STD_COLUMNS.items():
        if src in raw:
            out[dst] = raw[src].to_numpy()
    return pd.DataFrame(out)


def _mm_to_m(mm: np.ndarray) -> np.ndarray:
    """[mm] -> [m] by a decimal shift, so ``2361.9831`` becomes exactly ``2.3619831``."""
    # repr gives the shortest decimal of each value, i.e. the digits of the source file.
    return np.array([float(Decimal(repr(float(v))).scaleb(-3)) for v in mm])


@dataclass(frozen=True)
class IpaImport:
    """What :func:`convert_ipa` did."""

    source: str
    destination: str
    n_rows: int
    temperature: tuple[float, float]  # min, max [°C]
    convention: str
    extra_columns: tuple[str, ...]
    detected: bool = False  # convention found on the file (--convention auto)

    def summary(self) -> str:
        """A short human summary, one fact per line."""
        lo, hi = self.temperature
        lines = [
            f"{self.source} -> {self.destination}: {self.n_rows} rows (row order kept, no t)",
            f"  temperature {lo:.2f} .. {hi:.2f} °C",
            f"  measurement_x,y,z [mm] -> x, y, z [m]; measurement_rx,ry,rz [deg] -> "
            f"qw..qz as {describe_sequence(self.convention)}"
            + (", detected on the file's joint angles" if self.detected else ""),
        ]
        if self.extra_columns:
            lines.append(f"  kept as extra columns: {', '.join(self.extra_columns)}")
        return "\n".join(lines)


def convert_ipa(
    src: str | os.PathLike, dst: str | os.PathLike, *, convention: str = MEASUREMENT_CONVENTION
) -> IpaImport:
    """Convert one IPA measurement file to a section-1 table (CSV or Parquet by extension).

    Args:
        src: ``measurements_*.csv`` of the IPA UR10 data set; its joints must be radians
            within the UR10's limits (:func:`check_ipa_joints`).
        dst: output table; ``.csv``, ``.parquet`` or ``.pq``.
        convention: scipy Euler sequence of ``measurement_rx,ry,rz``, or ``"auto"`` to
            detect it on this file (:func:`detect_ipa_conventions`).
    """
    if convention != "auto" and convention not in EULER_SEQUENCES:
        raise ValueError(f"unknown Euler sequence {convention!r}; one of {EULER_SEQUENCES}")
    required = [*UR_JOINT_NAMES, *MEASUREMENT_POSITION, *MEASUREMENT_ANGLES]
    required.append("measurement_temperature")
    if convention == "auto":
        required += GOAL_ANGLES
    raw = read_ipa_csv(src, required, optional=list(_STD_COLUMNS))
    check_ipa_joints(str(src), raw)
    detected = convention == "auto"
    if detected:
        convention = _detect_on(raw).measurement.convention
    frame = ipa_to_frame(raw, convention)
    write_frame(dst, frame)
    extras = tuple(c for c in frame.columns if c.startswith("std_"))
    temp = frame["temperature"]
    return IpaImport(
        str(src), str(dst), len(frame), (float(temp.min()), float(temp.max())), convention, extras,
        detected,
    )  # fmt: skip


# ----------------------------------------------------------------------------- conventions


def ur_flange_rotations(q: np.ndarray) -> np.ndarray:
    """Orientation of the UR flange (DH frame 6) in the DH base, ``(N, 6)`` [rad] -> ``(N, 3, 3)``.

    Depends only on the DH twists, so it is exact for every UR arm whatever its lengths.
    """
    q = np.asarray(q, dtype=np.float64)
    R = np.broadcast_to(np.eye(3), (q.shape[0], 3, 3))
    for k, alpha in enumerate(_UR_DH_ALPHA):
        Rz = Rotation.from_euler("z", q[:, k : k + 1]).as_matrix()
        R = R @ Rz @ Rotation.from_euler("x", alpha).as_matrix()
    return R


class IpaConventions(NamedTuple):
    """Detected Euler conventions of an IPA file."""

    goal: EulerDetection  # Goal roll, pitch, yaw [rad]
    measurement: EulerDetection  # measurement_rx, ry, rz [deg]


def _detect_on(raw: pd.DataFrame, n_pairs: int = 4000, seed: int = 0) -> IpaConventions:
    G = ur_flange_rotations(raw[list(UR_JOINT_NAMES)].to_numpy())
    goal = detect_euler_convention(
        raw[list(GOAL_ANGLES)].to_numpy(),
        G,
        degrees=False,
        left=_GOAL_FROM_DH,
        n_pairs=n_pairs,
        seed=seed,
    )
    meas = detect_euler_convention(
        raw[list(MEASUREMENT_ANGLES)].to_numpy(), G, degrees=True, n_pairs=n_pairs, seed=seed
    )
    return IpaConventions(goal, meas)


def detect_ipa_conventions(
    path: str | os.PathLike, *, n_pairs: int = 4000, seed: int = 0
) -> IpaConventions:
    """Detect the Euler conventions of ``Goal roll,pitch,yaw`` and ``measurement_rx,ry,rz``.

    Both are checked against the flange orientation computed from the joint angles
    (:func:`ur_flange_rotations`); the Goal with the base rotation of ROS ``base_link``
    held fixed, the measurement with tracker and T-Mac frames fitted.
    """
    columns = [*UR_JOINT_NAMES, *GOAL_ANGLES, *MEASUREMENT_ANGLES]
    return _detect_on(read_ipa_csv(path, columns), n_pairs=n_pairs, seed=seed)

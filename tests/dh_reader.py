"""An independent reader of DH / modified-DH tables and of UR's kinematics YAML, written
from the formats' definitions (numpy only, nothing from hybrid_pk), for the tests.

- DH (standard):  A_i = Rz(theta_i + q_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)
- MDH (Craig):    A_i = Rx(alpha_i) Tx(a_i) Ry(beta_i) Rz(theta_i + q_i) Tz(d_i)
  (a prismatic joint adds q_i to d_i instead), T = base A_1 ... A_n flange.
- UR kinematics:  T = Π_i Trans(x, y, z) Rz(yaw) Ry(pitch) Rx(roll) Rz(q_i), the joints
  in the order shoulder, upper_arm, forearm, wrist_1, wrist_2, wrist_3.
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

UR_ORDER = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")


def _rot(axis: int, angle) -> np.ndarray:
    angle = np.asarray(angle, dtype=np.float64)
    T = np.zeros((*angle.shape, 4, 4))
    T[..., 3, 3] = 1
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    T[..., axis, axis] = 1
    c, s = np.cos(angle), np.sin(angle)
    T[..., i, i], T[..., i, j], T[..., j, i], T[..., j, j] = c, -s, s, c
    return T


def _trans(vec) -> np.ndarray:
    vec = np.asarray(vec, dtype=np.float64)
    T = np.zeros((*vec.shape[:-1], 4, 4))
    T[..., [0, 1, 2, 3], [0, 1, 2, 3]] = 1
    T[..., :3, 3] = vec
    return T


def _along(axis: int, length) -> np.ndarray:
    length = np.asarray(length, dtype=np.float64)
    v = np.zeros((*length.shape, 3))
    v[..., axis] = length
    return _trans(v)


def pose(xyz, rpy) -> np.ndarray:
    """URDF origin: Trans(xyz) Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    return _trans(xyz) @ _rot(2, y) @ _rot(1, p) @ _rot(0, r)


def rows_of(table: list[dict]) -> list[dict]:
    """Rows with beta (0 when absent) and type."""
    return [{"beta": 0.0, "type": "revolute"} | dict(r) for r in table]


def chain_pose(rows, convention: str, q: np.ndarray, base=None, flange=None) -> np.ndarray:
    """``(N, 4, 4)`` pose of the table's flange at joint values ``q (N, n)``."""
    T = np.broadcast_to(np.eye(4) if base is None else base, (q.shape[0], 4, 4)).copy()
    for i, r in enumerate(rows):
        prismatic = r["type"] == "prismatic"
        theta = r["theta"] + (0 if prismatic else q[:, i])
        d = r["d"] + (q[:, i] if prismatic else 0)
        if convention == "dh":
            A = _rot(2, theta) @ _along(2, d) @ _along(0, r["a"]) @ _rot(0, r["alpha"])
            A = A @ _rot(1, r["beta"])
        else:
            A = _rot(0, r["alpha"]) @ _along(0, r["a"]) @ _rot(1, r["beta"])
            A = A @ _rot(2, theta) @ _along(2, d)
        T = T @ A
    return T if flange is None else T @ flange


def read_table_yaml(path: Path) -> dict:
    """``{convention, rows, frames: (base, flange)}`` of an exported table."""
    doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    frames = tuple(pose(doc[k]["xyz"], doc[k]["rpy"]) for k in ("base", "flange"))
    return {"convention": doc["convention"], "rows": rows_of(doc["joints"]), "frames": frames}


def ur_pose(path: Path, q: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` tool0 in base_link_inertia from a UR kinematics YAML; the extra
    ``hybrid_pk_tool0`` transform after wrist_3 when the file has one."""
    doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    kin = doc["kinematics"]
    assert str(kin["hash"]).startswith("calib_")
    T = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4)).copy()
    for i, name in enumerate(UR_ORDER):
        e = kin[name]
        T = T @ pose((e["x"], e["y"], e["z"]), (e["roll"], e["pitch"], e["yaw"])) @ _rot(2, q[:, i])
    extra = doc.get("hybrid_pk_tool0")
    return T if extra is None else T @ pose(extra["xyz"], extra["rpy"])


def _matrix(p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(p[:3]).as_matrix()
    T[:3, 3] = p[3:]
    return T


def fit_base_flange(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Constant ``X, Y`` with ``B ≈ X A Y`` (least squares from ``X = B_0 A_0^-1``)."""
    X0 = B[0] @ np.linalg.inv(A[0])

    def residual(p: np.ndarray) -> np.ndarray:
        X, Y = X0 @ _matrix(p[:6]), _matrix(p[6:])
        return (X @ A @ Y - B)[:, :3, :].ravel()

    sol = least_squares(residual, np.zeros(12), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return X0 @ _matrix(sol.x[:6]), _matrix(sol.x[6:])


def erd_root() -> Path:
    """The ``robots`` folder the PyPI package ``example-robot-data`` installs (dev extra);
    the calling test skips where it is not installed."""
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("dev extra example-robot-data not installed")
    return Path(dist.locate_file("cmeel.prefix/share/example-robot-data/robots"))

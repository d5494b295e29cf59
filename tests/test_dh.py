"""DH / modified-DH tables in (``Robot.from_dh``, ``hybrid-pk import dh``) and out
(``model_dh_table``): published tables against the shipped and reference URDFs, round
trips, the written URDF in pinocchio and yourdfpy, and bad tables.

The chain of a table is rebuilt here from the conventions' definitions
(``tests/dh_reader.py``), never with the package's own DH code.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.io.dh_export import model_dh_table, write_dh_yaml
from tests.dh_reader import chain_pose, erd_root, fit_base_flange, read_table_yaml, rows_of

pytestmark = pytest.mark.usefixtures("one_thread")

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "reference-urdf"
ERD = "ur_description/urdf"
PI = math.pi
TURN = 6.28318530718  # the UR limits as their URDFs write them

# Published DH tables (lengths [m], angles [rad]): a, alpha, d, theta per joint.
# UR5 and UR10: Universal Robots' "DH parameters for calculations of kinematics".
UR5_DH = [
    (0, PI / 2, 0.089159, 0),
    (-0.425, 0, 0, 0),
    (-0.39225, 0, 0, 0),
    (0, PI / 2, 0.10915, 0),
    (0, -PI / 2, 0.09465, 0),
    (0, 0, 0.0823, 0),
]
UR10_DH = [
    (0, PI / 2, 0.1273, 0),
    (-0.612, 0, 0, 0),
    (-0.5723, 0, 0, 0),
    (0, PI / 2, 0.163941, 0),
    (0, -PI / 2, 0.1157, 0),
    (0, 0, 0.0922, 0),
]
# Staubli RX160 (arm manual): shoulder offset 0.15, arm 0.825, forearm 0.625, flange 0.11.
RX160_DH = [
    (0.15, -PI / 2, 0.55, 0),
    (0.825, 0, 0, -PI / 2),
    (0, PI / 2, 0, PI / 2),
    (0, -PI / 2, 0.625, 0),
    (0, PI / 2, 0, 0),
    (0, 0, 0.11, 0),
]
# The same robots in Craig's modified DH (alpha_{i-1}, a_{i-1}, theta_i, d_i per row),
# as published beside them: rows (alpha, a, d, theta).
UR5_MDH = [
    (0, 0, 0.089159, 0),
    (PI / 2, 0, 0, 0),
    (0, -0.425, 0, 0),
    (0, -0.39225, 0.10915, 0),
    (PI / 2, 0, 0.09465, 0),
    (-PI / 2, 0, 0.0823, 0),
]
UR10_MDH = [
    (0, 0, 0.1273, 0),
    (PI / 2, 0, 0, 0),
    (0, -0.612, 0, 0),
    (0, -0.5723, 0.163941, 0),
    (PI / 2, 0, 0.1157, 0),
    (-PI / 2, 0, 0.0922, 0),
]
RX160_MDH = [
    (0, 0, 0.55, 0),
    (-PI / 2, 0.15, 0, -PI / 2),
    (0, 0.825, 0, PI / 2),
    (PI / 2, 0, 0.625, 0),
    (-PI / 2, 0, 0, 0),
    (PI / 2, 0, 0.11, 0),
]


def _table(values, convention: str, limits=(-TURN, TURN)) -> list[dict]:
    rows = []
    for i, v in enumerate(values, start=1):
        a, alpha, d, theta = v if convention == "dh" else (v[1], v[0], v[2], v[3])
        rows.append(
            {"name": f"joint_{i}", "a": a, "alpha": alpha, "d": d, "theta": theta}
            | {"type": "revolute", "lower": limits[0], "upper": limits[1]}
        )
    return rows


def _erd(name: str) -> Path:
    return erd_root() / ERD / name


def _urdf_with_exact_half_pi(path: Path, tmp_path: Path) -> tuple[Path, float]:
    """The URDF with its 12-digit pi/2 and pi written exactly, and the angle [rad] the
    rounding had moved a joint's zero by (the UR URDFs write 1.57079632679)."""
    text = path.read_text(encoding="utf-8")
    rounded = [("1.57079632679", PI / 2), ("3.14159265359", PI)]
    moved = max((abs(float(s) - v) for s, v in rounded if s in text), default=0.0)
    for s, v in rounded:
        text = text.replace(s, repr(v))
    out = tmp_path / path.name
    out.write_text(text, encoding="utf-8")
    return out, moved


CASES = [
    ("ur5", UR5_DH, UR5_MDH, lambda: _erd("ur5_robot.urdf"), "tool0"),
    ("ur10", UR10_DH, UR10_MDH, lambda: REPO / "urdf" / "ur10.urdf", None),
    ("ur10", UR10_DH, UR10_MDH, lambda: SHARED / "ur10.urdf", "tool0"),
    ("rx160", RX160_DH, RX160_MDH, lambda: REPO / "urdf" / "rx160.urdf", None),
    ("rx160", RX160_DH, RX160_MDH, lambda: SHARED / "staubli_rx160.urdf", "tool0"),
]


@pytest.mark.parametrize("convention", ["dh", "mdh"])
@pytest.mark.parametrize(("name", "dh", "mdh", "urdf", "end"), CASES)
def test_published_table_matches_urdf(tmp_path, name, dh, mdh, urdf, end, convention):
    """A published table and the URDF agree to 1e-12 m after one constant base and
    flange transform, at 1000 configurations (URDF rounding of pi/2 restored; the URDF
    as written agrees to the size of that rounding)."""
    path = urdf()
    if not path.is_file():
        pytest.skip(f"{path} not found")
    exact, moved = _urdf_with_exact_half_pi(path, tmp_path)
    table = _table(dh if convention == "dh" else mdh, convention)
    robot = Robot.from_dh(table, convention, name=name)
    q = robot.sample_q(1000, torch.Generator().manual_seed(len(name)))
    with torch.no_grad():
        A = robot.fk(q).numpy()
        B = Robot.from_urdf(exact, end_link=end).fk(q).numpy()
        B_written = Robot.from_urdf(path, end_link=end).fk(q).numpy()
    ours = chain_pose(rows_of(table), convention, q.numpy())  # the table by its definition
    assert np.abs(ours - A).max() < 1e-12
    X, Y = fit_base_flange(A[:20], B[:20])
    P = X @ A @ Y
    assert np.abs(P[:, :3, 3] - B[:, :3, 3]).max() < 1e-12
    assert np.abs(P[:, :3, :3] - B[:, :3, :3]).max() < 1e-12
    reach = sum(abs(r["a"]) + abs(r["d"]) for r in table)
    bound = 6 * moved * reach + 1e-12  # each joint's zero moved by the rounding at most
    assert np.abs(P[:, :3, 3] - B_written[:, :3, 3]).max() < bound


@pytest.mark.parametrize("convention", ["dh", "mdh"])
@pytest.mark.parametrize(("values_dh", "values_mdh"), [(UR10_DH, UR10_MDH), (RX160_DH, RX160_MDH)])
def test_round_trip_exact(tmp_path, convention, values_dh, values_mdh):
    """table -> robot -> export -> table gives the same numbers to 1e-12 (angles modulo
    a turn), and the file written reads back to the same chain."""
    table = _table(values_dh if convention == "dh" else values_mdh, convention)
    robot = Robot.from_dh(table, convention)
    out = model_dh_table(ExtendedModel(robot), convention)
    want = np.array([[r[k] for k in ("a", "alpha", "d", "theta")] for r in table])
    got = out.rows[:, :4]
    wrap = np.array([0, 1, 0, 1], dtype=bool)
    diff = got - want
    diff[:, wrap] = (diff[:, wrap] + PI) % (2 * PI) - PI
    assert np.abs(diff).max() < 1e-12
    assert np.abs(out.rows[:, 4]).max() < 1e-12  # no parallel-axis tilt in these robots
    assert np.abs(out.base - np.eye(4)).max() < 1e-12
    assert np.abs(out.flange - np.eye(4)).max() < 1e-12
    path = write_dh_yaml(out, tmp_path / "t.yaml")
    back = read_table_yaml(path)
    assert back["convention"] == convention
    q = robot.sample_q(200, torch.Generator().manual_seed(1)).numpy()
    assert (
        np.abs(
            chain_pose(back["rows"], convention, q, *back["frames"])
            - chain_pose(rows_of(table), convention, q)
        ).max()
        < 1e-12
    )


@pytest.mark.parametrize(
    ("values_dh", "values_mdh"), [(UR5_DH, UR5_MDH), (UR10_DH, UR10_MDH), (RX160_DH, RX160_MDH)]
)
def test_dh_robot_exports_the_published_mdh_table(values_dh, values_mdh):
    """A robot built from its DH table exports the same maker's MDH table: the two
    conventions hold the same numbers, regrouped. (The other way, MDH -> DH, the offset
    along a pair of parallel axes may land one row earlier: where between two parallel
    axes the normal sits is a free choice, and an MDH-built robot's frames put it
    elsewhere than the DH table did.)"""
    robot = Robot.from_dh(_table(values_dh, "dh"), "dh")
    out = model_dh_table(ExtendedModel(robot), "mdh")
    rows = _table(values_mdh, "mdh")
    want = np.array([[r[k] for k in ("a", "alpha", "d", "theta")] for r in rows])
    diff = out.rows[:, :4] - want
    diff[:, [1, 3]] = (diff[:, [1, 3]] + PI) % (2 * PI) - PI
    assert np.abs(diff).max() < 1e-12
    assert np.abs(out.base - np.eye(4)).max() < 1e-12
    assert np.abs(out.flange - np.eye(4)).max() < 1e-12

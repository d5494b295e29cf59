"""ISO 9283 pose accuracy AP and repeatability RP on repeated poses."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from hybrid_pk.data import read_table_for
from hybrid_pk.data.ipa import convert_ipa
from hybrid_pk.effects import ExtendedModel
from hybrid_pk.errors import DataError
from hybrid_pk.evaluation.iso9283 import expected_rp_mm, group_repeated_poses, iso9283
from hybrid_pk.geometry import so3_exp
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign

NOISE_MM, NOISE_DEG, CYCLES = 0.02, 0.01, 30
SERIES_B = (
    Path(__file__).resolve().parents[1].parent
    / "shared/data/ipa-ur10/Series_B/measurements_joint_configurations.csv"
)


@pytest.fixture(scope="module")
def campaign():
    """ISO cube P1..P5, 30 cycles, no robot error: only measurement noise spreads."""
    robot = Robot.from_urdf("ur10")
    data, truth = simulate_campaign(
        robot,
        5 * CYCLES,
        "none",
        noise_mm=NOISE_MM,
        noise_deg=NOISE_DEG,
        trajectory="iso-cube",
        seed=3,
    )
    base = torch.tensor(truth["base_frame"], dtype=torch.float64)
    tool = torch.tensor(truth["tool_frame"], dtype=torch.float64)
    with torch.no_grad():
        T_true = ExtendedModel(robot, base=base, tool=tool)(data.q)
    return data, T_true


def test_repeated_iso_poses_are_grouped_in_visit_order(campaign):
    data, _ = campaign
    ids = group_repeated_poses(data.q)
    assert ids.max() == 4
    np.testing.assert_array_equal(ids[:5], [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(np.bincount(ids), [CYCLES] * 5)


def test_grouping_tolerance_joins_near_copies_only():
    q = torch.tensor([[0.0, 1.0], [1e-9, 1.0], [0.0, 1.0 + 1e-3], [0.0, 1.0 - 5e-7]])
    np.testing.assert_array_equal(group_repeated_poses(q, tol=1e-6), [0, 0, 1, 0])


def test_rp_matches_the_noise_and_ap_is_zero_for_the_true_model(campaign):
    data, T_true = campaign
    result = iso9283(data, T_true)
    poses = result.poses
    assert len(poses) == 5
    assert (poses["n"] == CYCLES).all()
    expected = expected_rp_mm(NOISE_MM, CYCLES)  # 3.56 sigma
    assert math.isclose(poses["RP_l_mm"].mean(), expected, rel_tol=0.15)
    assert ((poses["RP_l_mm"] > 0.6 * expected) & (poses["RP_l_mm"] < 1.4 * expected)).all()
    # barycentre of 30 noisy visits: AP ~ sigma * 1.6 / sqrt(30) ~ 0.006 mm
    assert poses["AP_p_mm"].max() < 4 * NOISE_MM / math.sqrt(CYCLES)
    for axis in "abc":
        rp = poses[f"RP_{axis}_deg"]
        assert math.isclose(rp.mean(), 3 * NOISE_DEG, rel_tol=0.2)
        assert poses[f"AP_{axis}_deg"].abs().max() < 4 * NOISE_DEG / math.sqrt(CYCLES)


def test_ap_reports_a_known_offset_of_the_commanded_pose(campaign):
    data, T_true = campaign
    shift_mm = torch.tensor([0.3, -0.4, 0.0], dtype=torch.float64)
    turn_deg = 0.05
    T_cmd = T_true.clone()
    T_cmd[:, :3, 3] += 1e-3 * shift_mm
    rot = so3_exp(torch.tensor([0.0, 0.0, math.radians(turn_deg)], dtype=torch.float64))
    T_cmd[:, :3, :3] = rot @ T_cmd[:, :3, :3]
    poses = iso9283(data, T_cmd).poses
    bound = 4 * NOISE_MM / math.sqrt(CYCLES)
    # attained - commanded = -shift: AP_p = 0.5 mm
    assert np.allclose(poses["AP_p_mm"], 0.5, atol=bound)
    assert np.allclose(poses["AP_x_mm"], -0.3, atol=bound)
    assert np.allclose(poses["AP_y_mm"], 0.4, atol=bound)
    assert np.allclose(poses["AP_c_deg"], -turn_deg, atol=4 * NOISE_DEG / math.sqrt(CYCLES))
    # repeatability does not depend on the commanded pose
    np.testing.assert_allclose(poses["RP_l_mm"], iso9283(data).poses["RP_l_mm"])


def test_summary_is_json_ready_and_flags_few_cycles(campaign):
    data, T_true = campaign
    short = data.subset(slice(0, 15))  # 3 cycles
    result = iso9283(short, T_true[:15])
    summary = result.summary()
    assert summary["n_poses"] == 5
    assert summary["cycles"] == {"min": 3, "max": 3}
    assert set(summary["AP_p_mm"]) == {"mean", "max"}
    assert math.isclose(summary["sigma_pooled_mm"], NOISE_MM, rel_tol=0.3)
    assert math.isclose(summary["sigma_robust_mm"], NOISE_MM, rel_tol=0.3)
    assert any("fewer than the 30 cycles" in line for line in result.lines())
    from hybrid_pk.report.evaluation_report import _iso_section

    lines, _ = _iso_section(short, T_true[:15], "m.pt")
    assert "5 repeated poses, 3 visits each" in "\n".join(lines)  # not "3-3 visits"
    figures = [
        ln.split(" | ")[0].lstrip("| ")
        for ln in "\n".join(lines).splitlines()
        if ln.startswith(("| AP", "| RP"))
    ]
    assert figures[0] == "AP_p [mm]"  # was "AP_p_mm", after RP_l_mm and the RP angles
    assert [f[:2] for f in figures] == sorted(f[:2] for f in figures)  # accuracy, then RP
    assert (
        f"the median, which a bad visit does not inflate: {summary['sigma_robust_mm']:.4f} mm"
        in ("\n".join(lines))
    )


def test_position_only_data_gives_position_figures_only(campaign):
    data, T_true = campaign
    pos_only = type(data)(
        q=data.q,
        position=data.position,
        quat=None,
        joint_names=data.joint_names,
        file_index=data.file_index,
        rows=data.rows,
        sources=data.sources,
    )
    result = iso9283(pos_only, T_true)
    assert not result.has_orientation
    assert "RP_a_deg" not in result.poses
    assert "RP_a_deg" not in result.summary()


def test_data_without_repeats_is_an_error():
    robot = Robot.from_urdf("ur10")
    data, _ = simulate_campaign(robot, 20, "none", noise_mm=0.01, seed=1)
    with pytest.raises(DataError, match="repeated"):
        iso9283(data)


@pytest.mark.skipif(not SERIES_B.is_file(), reason="shared data not found")
def test_real_series_b_repeats_give_the_noise_floor(tmp_path):
    """Series B visits 293 configurations twice (encoder values logged to ~1e-5 rad)."""
    dst = tmp_path / "B.parquet"
    convert_ipa(SERIES_B, dst)
    robot = Robot.from_urdf("ur10")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # std_* columns are listed as ignored
        data = read_table_for(dst, robot)
    summary = iso9283(data, tol=3e-4).summary()
    assert summary["n_poses"] == 293
    assert summary["cycles"] == {"min": 2, "max": 2}
    # UR10 repeatability is +-0.1 mm; tracker + robot noise per axis well below it
    assert 0.002 < summary["sigma_robust_mm"] < 0.05
    # a few poses whose two visits differ by ~2 mm inflate the plain pooled level
    assert summary["sigma_pooled_mm"] > 2 * summary["sigma_robust_mm"]

"""Hold-out splits (random, by workspace region, joint box), initial frames (closed-form
registration of real data, referencing by circles of single-joint sweeps)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from hybrid_pk.calibration.fit import fit
from hybrid_pk.data import MeasuredData, read_table_for
from hybrid_pk.data.ipa import convert_ipa
from hybrid_pk.effects import ExtendedModel, conditions_from_data
from hybrid_pk.errors import DataError
from hybrid_pk.evaluation.splits import joint_box_split, random_split, region_split
from hybrid_pk.geometry import matrix_to_quat, so3_exp
from hybrid_pk.geometry.registration import register_frames
from hybrid_pk.simulate import random_frames, simulate_campaign
from tests.helpers import rotation_distance
from tests.oracles.circle_referencing import (
    JointSweep,
    find_single_joint_sweeps,
    fit_circle,
    reference_from_sweeps,
    registration_guess,
)

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
IPA = SHARED / "data" / "ipa-ur10"
SERIES = {
    "A": (IPA / "Series_A" / "measurements_grid.csv", 48),  # (file, keep every k-th row)
    "B": (IPA / "Series_B" / "measurements_joint_configurations.csv", 6),
}
needs_shared = pytest.mark.skipif(not IPA.is_dir(), reason=f"shared data not found at {IPA}")


@pytest.fixture(scope="module")
def campaign(ur10) -> MeasuredData:
    data, _ = simulate_campaign(ur10, 400, "none", noise_mm=0.01, noise_deg=0.005, seed=2)
    return data


# ----------------------------------------------------------------------------- splits


def test_random_split_is_a_seeded_partition(campaign):
    a, b = random_split(campaign, 0.25, seed=1), random_split(campaign, 0.25, seed=1)
    assert torch.equal(a.holdout, b.holdout)
    assert len(a.holdout) == 100
    assert sorted(torch.cat([a.fit, a.holdout]).tolist()) == list(range(campaign.n))
    assert not torch.equal(a.holdout, random_split(campaign, 0.25, seed=2).holdout)


@pytest.mark.parametrize(("axis", "side"), [("x", "high"), ("z", "low"), ("auto", "high")])
def test_region_split_holds_out_the_rows_beyond_a_plane(campaign, ur10, axis, side):
    split = region_split(campaign, ur10, holdout=0.2, axis=axis, side=side)
    with torch.no_grad():
        p = ur10.fk(campaign.q)[:, :3, 3]
    if axis == "auto":
        centred = p - p.mean(0)
        u = torch.linalg.svd(centred, full_matrices=False)[2][0]
    else:
        u = torch.eye(3, dtype=p.dtype)["xyz".index(axis)]
    s = p @ u
    held, kept = s[split.holdout], s[split.fit]
    if axis == "auto" and held.mean() < kept.mean():
        held, kept = -held, -kept  # the sign of a principal direction is a convention
    if side == "high":
        assert held.min() > kept.max()
    else:
        assert held.max() < kept.min()
    assert len(split.holdout) == 80
    assert "region" in split.rule


def test_radial_split_holds_out_the_far_reach(campaign, ur10):
    split = region_split(campaign, ur10, holdout=0.3, axis="radial")
    with torch.no_grad():
        r = ur10.fk(campaign.q)[:, :3, 3][:, :2].norm(dim=-1)
    assert r[split.holdout].min() > r[split.fit].max()


def test_region_split_of_several_tracker_frames_needs_the_robot(campaign):
    two = MeasuredData.concat([campaign.subset(slice(0, 200)), campaign.subset(slice(200, 400))])
    two = MeasuredData(
        **{f: getattr(two, f) for f in ("q", "position", "quat", "joint_names", "rows")},
        file_index=torch.cat([torch.zeros(200), torch.ones(200)]),
        sources=("a.csv", "b.csv"),
    )
    with pytest.raises(DataError, match="different tracker frames"):
        region_split(two)


def test_joint_box_split_holds_out_a_corner_of_joint_space(campaign):
    split = joint_box_split(campaign, holdout=0.15, corner="high")
    q = campaign.q[:, :3]
    inside = split.holdout
    assert 0.13 <= len(inside) / campaign.n <= 0.2
    lo = q[inside].min(0).values  # every fit row is outside the box of the hold-out
    outside_box = (q[split.fit] < lo).any(-1)
    assert bool(outside_box.all())


def test_explicit_joint_box(campaign):
    box = {"shoulder_pan_joint": (0.0, 10.0), "elbow_joint": (-10.0, 0.0)}
    split = joint_box_split(campaign, box=box)
    q = campaign.q
    expected = (q[:, 0] >= 0) & (q[:, 2] <= 0)
    assert torch.equal(split.holdout, torch.nonzero(expected)[:, 0])


# ----------------------------------------------------------------------------- referencing
# The paper's referencing by circles (``tests/oracles/circle_referencing.py``, test code)
# is an independent way to the base frame: the product's closed-form registration
# (``geometry.registration.register_frames``, where every fit starts) must agree with it
# on the same sweeps. The circle fit's own tests check the oracle itself.

HOME = (0.3, -1.2, 1.3, -1.7, -1.5, 0.4)  # [rad] a UR10 pose away from singularities


SWEEPS = ((0, -0.5, 1.0), (1, -1.6, -0.8), (4, -2.0, -0.5), (5, -1.0, 1.0))  # joint, range


def _sweeps(robot, base, tool, noise_mm, seed=0, k=25, ranges=SWEEPS):
    g = torch.Generator().manual_seed(seed)
    home = torch.tensor(HOME, dtype=torch.float64)
    out = []
    for j, lo, hi in ranges:
        q = home.repeat(k, 1)
        q[:, j] = torch.linspace(lo, hi, k, dtype=torch.float64)
        with torch.no_grad():
            T = base @ robot.fk(q) @ tool
        p = T[:, :3, 3] + 1e-3 * noise_mm * torch.randn(k, 3, generator=g, dtype=torch.float64)
        out.append(JointSweep(robot.joint_names[j], q, p, matrix_to_quat(T[:, :3, :3])))
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_referencing_by_circles_recovers_the_base_frame(ur10, seed):
    base, tool = random_frames(torch.Generator().manual_seed(seed))
    sweeps = _sweeps(ur10, base, tool, noise_mm=0.005, seed=seed)
    ref = reference_from_sweeps(ur10, sweeps)
    assert 1e3 * float((ref.base[:3, 3] - base[:3, 3]).norm()) < 0.1  # mm
    assert math.degrees(float(rotation_distance(ref.base[:3, :3], base[:3, :3]))) < 0.01
    assert 1e3 * float((ref.tool[:3, 3] - tool[:3, 3]).norm()) < 0.1
    assert math.degrees(float(rotation_distance(ref.tool[:3, :3], tool[:3, :3]))) < 0.01
    assert all(c.rms_mm < 0.02 for c in ref.circles)
    # the product's registration of the same rows, positions only, agrees with it
    base_product = _registered_base(ur10, sweeps)
    assert 1e3 * float((base_product[:3, 3] - ref.base[:3, 3]).norm()) < 0.1  # mm
    assert math.degrees(float(rotation_distance(base_product[:3, :3], ref.base[:3, :3]))) < 0.01


def _registered_base(robot, sweeps) -> torch.Tensor:
    """``T_meas_root`` of the product's closed-form registration of the sweeps' rows
    (positions only: the orientations would give the rotation directly)."""
    q = torch.cat([s.q for s in sweeps])
    with torch.no_grad():
        T_end = robot.fk(q).double()
    base, _ = register_frames(T_end, torch.cat([s.position for s in sweeps]), None)
    return base


def test_circle_fit_is_exact_on_a_short_arc():
    centre, radius = np.array([0.4, -1.0, 2.0]), 0.3
    axis = np.array([1.0, 2.0, 2.0]) / 3
    e1 = np.cross(axis, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    t = np.linspace(0.0, 0.5, 9)  # 29 deg of arc
    points = centre + radius * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
    circle = fit_circle(points)
    np.testing.assert_allclose(circle.centre, centre, atol=1e-9)
    np.testing.assert_allclose(circle.normal, axis, atol=1e-12)  # turning positively
    assert abs(circle.radius - radius) < 1e-9
    assert abs(circle.arc_deg - math.degrees(0.5)) < 1e-6


def test_sweeps_are_found_in_a_table_and_reference_it(ur10):
    base, tool = random_frames(torch.Generator().manual_seed(3))
    sweeps = _sweeps(ur10, base, tool, noise_mm=0.0, k=12)
    table = MeasuredData(
        q=torch.cat([s.q for s in sweeps]),
        position=torch.cat([s.position for s in sweeps]),
        quat=None,
        joint_names=ur10.joint_names,
        file_index=torch.zeros(48),
        rows=torch.arange(1, 49),
        sources=("sweeps.csv",),
    )
    found = find_single_joint_sweeps(table)
    assert [(s.joint, len(s.q)) for s in found] == [(s.joint, 12) for s in sweeps]
    ref = reference_from_sweeps(ur10, found)  # position only: tool point, no rotation
    assert 1e3 * float((ref.base[:3, 3] - base[:3, 3]).norm()) < 1e-6
    assert 1e3 * float((ref.tool[:3, 3] - tool[:3, 3]).norm()) < 1e-6
    base_product = _registered_base(ur10, found)  # the product, on the sweeps found
    assert 1e3 * float((base_product[:3, 3] - ref.base[:3, 3]).norm()) < 1e-3


def test_parallel_axes_cannot_fix_the_base(ur10):
    base, tool = random_frames(torch.Generator().manual_seed(0))
    sweeps = _sweeps(ur10, base, tool, noise_mm=0.0, ranges=((1, -1.6, -0.8), (2, 0.8, 1.6)))
    with pytest.raises(DataError, match="parallel"):
        reference_from_sweeps(ur10, sweeps)


# ----------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def series(tmp_path_factory, ur10) -> dict[str, MeasuredData]:
    """Both shared series, imported as the CLI does, thinned to ~250 rows each (the fit
    cost is per iteration more than per row; the full series give the same optimum)."""
    out = {}
    for name, (src, every) in SERIES.items():
        dst = tmp_path_factory.mktemp("ipa") / f"{name}.parquet"
        convert_ipa(src, dst)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # std_* columns are listed as ignored
            data = read_table_for(dst, ur10)
        out[name] = data.subset(slice(0, None, every))
    return out


def _fit_from(robot, data, base, tool, max_iter=50):
    model = ExtendedModel(robot, base=base, tool=tool)
    # fixed noise levels: one LM pass, comparable costs between starts
    result = fit(
        model,
        data,
        cond=conditions_from_data(data),
        sigma_pos_mm=0.5,
        sigma_rot_rad=2e-3,
        max_iter=max_iter,
        covariance=False,
    )
    return model, result


@needs_shared
@pytest.mark.parametrize(("name", "yaw"), [("A", 30.0), ("B", -30.0)])
def test_registration_converges_on_both_real_series(series, ur10, name, yaw):
    data = series[name]
    guess = registration_guess(data, ur10)
    model, result = _fit_from(ur10, data, guess.base[0], guess.tool[0])
    assert result.converged
    assert float(result.position_mm.mean()) < 3.0  # nominal UR10 + frames: ~1 mm
    assert float(result.orientation_deg.mean()) < 0.3
    base = model.base.matrix()[0].detach()
    # the closed-form guess is already near the optimum
    assert 1e3 * float((guess.base[0, :3, 3] - base[:3, 3]).norm()) < 20.0
    assert math.degrees(float(rotation_distance(guess.base[0, :3, :3], base[:3, :3]))) < 1.0

    # a tracker yaw 30 deg off reaches the same optimum
    turned = guess.base[0].clone()
    turned[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, math.radians(yaw)])).double() @ turned[:3, :3]
    other, res = _fit_from(ur10, data, turned, guess.tool[0])
    assert res.converged
    b2 = other.base.matrix()[0].detach()
    assert 1e3 * float((b2[:3, 3] - base[:3, 3]).norm()) < 1e-3
    assert float(rotation_distance(b2[:3, :3], base[:3, :3])) < 1e-6
    assert abs(float(res.position_mm.mean() - result.position_mm.mean())) < 1e-5

    # a naive identity start does not: the tool ends up turned (or LM stalls)
    _, naive = _fit_from(ur10, data, None, None, max_iter=8)
    worse = float(naive.orientation_deg.mean()) > 10 * float(result.orientation_deg.mean())
    assert worse or not naive.converged
    assert naive.ssr_weighted > 1.5 * result.ssr_weighted

"""What the extended model leaves, binned along each joint (the diagnosis'
``unexplained.along_joints``): the joint an error varies along carries it, the others
stay near the noise's share, and an error that turns with the arm is the same at every
joint-1 angle once in the first link's axes. Errors drawn at random per run
(``tests.helpers.run_rng``)."""

from __future__ import annotations

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.statistics import along_joints, along_joints_text, in_link_1
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.geometry import so3_exp, transform
from tests.helpers import run_rng


def _q(robot: hpk.Robot, n: int, seed: int) -> torch.Tensor:
    return robot.sample_q(n, torch.Generator().manual_seed(seed))


def test_the_joint_an_error_varies_along_carries_it():
    rng = run_rng("along_joints")
    robot = hpk.Robot.from_urdf("ur10")
    q = _q(robot, 3000, int(rng.integers(1 << 30)))
    joint, amp = int(rng.integers(6)), float(rng.uniform(0.05, 0.3))  # mm
    g = torch.Generator().manual_seed(int(rng.integers(1 << 30)))
    r = 0.01 * torch.randn(3000, 3, generator=g, dtype=torch.float64)
    r[:, int(rng.integers(3))] += amp * torch.cos(q[:, joint])
    shares = along_joints(r, q, robot.joint_names)
    assert shares[0]["joint"] == robot.joint_names[joint], (joint, shares)
    signal, noise = amp**2 / 2, 3 * 1e-4
    assert shares[0]["share"] > 0.9 * signal / (signal + noise), (amp, shares[0])
    for e in shares[1:]:  # the others: noise's share, within a few times its spread
        assert e["share"] < 4 * e["chance"], (joint, e)
    assert "noise alone" in along_joints_text(shares)


def test_an_error_that_turns_with_the_arm_is_flat_along_joint_1_in_link_1():
    rng = run_rng("in_link_1")
    robot = hpk.Robot.from_urdf("ur10")
    model = ExtendedModel(robot)
    with torch.no_grad():
        R = so3_exp(torch.as_tensor(rng.normal(0, 1, 3), dtype=torch.float64))
        model.base.reset_to(transform(R, torch.as_tensor(rng.normal(0, 1, 3))))
    q = _q(robot, 2000, int(rng.integers(1 << 30)))
    data = hpk.MeasuredData(
        q=q,
        position=torch.zeros(2000, 3, dtype=torch.float64),
        quat=None,
        joint_names=robot.joint_names,
        file_index=torch.zeros(2000, dtype=torch.long),
        rows=torch.arange(1, 2001),
        sources=("sim",),
    )
    # a fixed error across joint 1's axis in the first link's axes (e.g. a link too
    # long): seen from the tracker it turns with joint 1
    R_1 = robot.link_frames(q)[:, 0, :3, :3]
    rel = R_1[0].T @ R_1[1]  # a turn about joint 1's axis, in link-1 axes
    axis = torch.stack([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    axis = axis / axis.norm()
    e = torch.as_tensor(rng.normal(0, 0.1, 3), dtype=torch.float64)
    e = e - (e @ axis) * axis
    seen = (model.base.matrix()[0, :3, :3] @ R_1 @ e[:, None])[..., 0]
    in_tracker = along_joints(seen, q, robot.joint_names)
    assert in_tracker[0]["joint"] == robot.joint_names[0], in_tracker
    assert in_tracker[0]["share"] > 0.5, in_tracker[0]
    turned = in_link_1(model, data, Conditions(), seen)
    torch.testing.assert_close(turned, e.expand(2000, 3), atol=1e-12, rtol=0)
    assert all(x["share"] < 1e-12 for x in along_joints(turned, q, robot.joint_names))


def _noise(sigma: float, pairs: int):
    from hybrid_pk.calibration.diagnosis.noise import NoiseEstimate

    one = {"file": "a.csv", "sigma_mm": sigma, "pairs": pairs, "max_distance_mm": 0.0}
    return NoiseEstimate(sigma, (one,))


def test_noise_alone_is_not_beyond_the_noise_and_a_larger_error_is():
    from hybrid_pk.calibration.diagnosis.noise import beyond_noise

    rng = run_rng("beyond_noise")
    g = torch.Generator().manual_seed(int(rng.integers(1 << 30)))
    sigma, n = float(rng.uniform(0.01, 1.0)), int(rng.integers(80, 3000))
    for _ in range(20):  # noise at the estimate's own sigma, give or take its error
        estimate = sigma * float(rng.uniform(0.92, 1.08))  # 1 sd of a 50-pair median
        r = sigma * torch.randn(n, 3, generator=g, dtype=torch.float64)
        out = beyond_noise(r, _noise(estimate, 50))
        assert not out["beyond"], (sigma, n, out)
        assert 1.0 < out["limit"] < 1.6, out
    r = 2.0 * sigma * torch.randn(n, 3, generator=g, dtype=torch.float64)
    assert beyond_noise(r, _noise(sigma, 50))["beyond"], (sigma, n)
    # fewer rows and pairs: a wider band; no estimate: no verdict
    few = beyond_noise(r[:20], _noise(sigma, 10))["limit"]
    assert few > beyond_noise(r, _noise(sigma, 200))["limit"]
    assert beyond_noise(r, None) is None


def test_an_error_left_well_above_the_noise_is_called_structured():
    """An offset the candidates offered cannot explain (only other joints' offsets) is
    left; the campaign repeats a sixth of its poses, so the model-free noise is the
    simulated one. Left at 1-3 mrad it is far above the noise: structured, whatever
    the neighbours of the few hold-out rows show; with nothing left, not."""
    from hybrid_pk.calibration import diagnose
    from hybrid_pk.calibration.diagnosis.leftovers import structured_text
    from hybrid_pk.simulate import simulate_campaign

    rng = run_rng("beyond_noise_campaign")
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    seed = int(rng.integers(1 << 20))
    q = robot.sample_q(250, torch.Generator().manual_seed(seed))
    q = torch.cat([q, q[:50]])
    joint = str(rng.choice(["joint_2", "joint_3"]))
    others = [f"joint_offset:{j}" for j in ("joint_5", "joint_6")]
    clean, _ = simulate_campaign(
        robot, None, [], poses=q, noise_mm=0.05, position_only=True, seed=seed
    )
    un = diagnose(robot, clean, seed=seed, candidates=others).unexplained
    assert not un["beyond_noise"]["beyond"], un
    assert not un["structured"], un
    assert structured_text(un).startswith("no"), un
    # 50 repeated poses are the estimate's 50 pairs: said so, not a distance
    assert "from repeated poses" in structured_text(un), un
    far = {**un["beyond_noise"], "pair_distance_mm": 559.0}
    assert "up to 559 mm apart" in structured_text({**un, "beyond_noise": far})
    # nothing to compare with (one hold-out row, no noise estimate): not "noise"
    unknown = structured_text({**un, "beyond_noise": None})
    assert unknown.startswith("no sign of it"), unknown
    assert "not compared with the noise" in unknown
    offset = hpk.make_effect(robot, f"joint_offset:{joint}", float(rng.uniform(1e-3, 3e-3)))
    data, _ = simulate_campaign(
        robot, None, [offset], poses=q, noise_mm=0.05, position_only=True, seed=seed
    )
    un = diagnose(robot, data, seed=seed, candidates=others).unexplained
    assert un["beyond_noise"]["beyond"], (joint, un)
    assert un["structured"], (joint, un)
    assert un["beyond_noise"]["ratio"] > 3, un
    assert structured_text(un).startswith("yes"), un

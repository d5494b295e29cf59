"""Near-duplicate causes must not split one effect between them.

The RX160's elbow compliance (joint 3) and a bending of the forearm about an axis
parallel to joint 3 (``tilt_compliance:joint_4``) have nearly the same signature: the
loads differ only by the short segment between the two joints. With an unmodelled
hardening spring in the wrist, the greedy search can pick the tilt first and add the
compliance later, both significant, the truth shared between them (demo seed 8: the
compliance came out 9.6 % low). The diagnosis must name the compliance at its value and
drop the stand-in. Values, spring and campaign are drawn per run (``HYBRID_PK_TEST_SEED``
replays one).
"""

from __future__ import annotations

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.effects import make_effect
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.unmodelled import HardeningCompliance, rms_gravity_torques
from tests.helpers import RUN_SEED, run_rng

pytestmark = pytest.mark.slow


def test_elbow_compliance_is_not_split_with_a_forearm_tilt():
    rng = run_rng("split-duplicates")
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    payload = 20.0
    c2, c3 = float(rng.uniform(0.5e-6, 1.5e-6)), float(rng.uniform(2e-6, 4e-6))
    tau0 = 0.4 * float(rms_gravity_torques(robot, payload, torch.Generator())[4])
    spring = HardeningCompliance(robot, "joint_5", float(rng.uniform(1.5e-4, 3e-4)) / tau0, tau0)
    effects = [
        make_effect(robot, "joint_compliance:joint_2", c2),
        make_effect(robot, "joint_compliance:joint_3", c3),
        spring,
    ]
    seed = int(rng.integers(1_000_000))
    data, _ = simulate_campaign(
        robot, 2250, effects, noise_mm=0.02, noise_deg=0.002, payload=payload, seed=seed
    )
    diag = diagnose(robot, data, seed=RUN_SEED % 1000)
    where = (
        f"run seed {RUN_SEED}: c2 {c2:.3g}, c3 {c3:.3g}, spring {float(spring.value):.3g} rad/Nm"
    )
    named = {(c.effect, c.joint): c for c in diag.causes}
    for joint, truth in (("joint_2", c2), ("joint_3", c3)):
        cause = named.get(("joint_compliance", joint))
        assert cause is not None, f"{where}: joint_compliance:{joint} not named: {list(named)}"
        assert abs(cause.value / truth - 1) < 0.05, f"{where}: {joint} {cause.value:.4g}"
    assert ("tilt_compliance", "joint_4") not in named, f"{where}: {list(named)}"


def test_search_stopped_at_its_limit_says_so():
    """Three hidden effects, at most one cause: the diagnosis warns that a significant
    candidate was left; with room for all three it does not."""
    rng = run_rng("max-causes")
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    seed = int(rng.integers(1_000_000))
    data, truth = simulate_campaign(
        robot, 1500, "random:3", noise_mm=0.02, noise_deg=0.002, seed=seed
    )
    where = f"run seed {RUN_SEED}: {[e['effect'] for e in truth['effects']]}"
    capped = diagnose(robot, data, max_causes=1, seed=1)
    assert len(capped.causes) == 1, where
    warned = [w for w in capped.warnings if "stopped at its limit of 1 cause:" in w["why"]]
    assert len(warned) == 1, f"{where}: {capped.warnings}"
    assert capped.to_json()["warnings"] == capped.warnings
    roomy = diagnose(robot, data, max_causes=8, seed=1)
    assert not [w for w in roomy.warnings if "stopped at its limit" in w["why"]], where


def test_a_tilt_that_only_carries_an_offset_gives_way_to_the_offset():
    """On the RX160 the joint_5 origin lies on the joint_4 axis, so a joint_4 offset is
    exactly the z component of a joint_5 axis tilt. When the search has chosen the tilt
    (two parameters), the swap pass must trade it for the offset (one parameter, the
    same fit): the same cause count, fewer parameters."""
    from hybrid_pk.calibration.diagnosis.carryover import Carry
    from hybrid_pk.calibration.diagnosis.regions import make_folds
    from hybrid_pk.calibration.diagnosis.split import split_campaign
    from hybrid_pk.calibration.diagnosis.swaps import prefer_fewer_causes
    from hybrid_pk.calibration.fit import fit
    from hybrid_pk.calibration.known_frames import initialise_with_priors
    from hybrid_pk.effects import ExtendedModel, conditions_from_data

    rng = run_rng("offset-not-tilt")
    robot = hpk.Robot.from_urdf("rx160")
    robot.requires_grad_(False)
    truth = float(rng.choice([-1, 1]) * rng.uniform(0.5e-3, 2e-3))
    effects = [
        make_effect(robot, "joint_offset:joint_4", truth),
        make_effect(robot, "joint_offset:joint_2", float(rng.uniform(-2e-3, 2e-3))),
    ]
    data, _ = simulate_campaign(robot, 300, effects, noise_mm=0.05, noise_deg=0.005,
                                seed=int(rng.integers(1_000_000)))  # fmt: skip
    split = split_campaign(data, conditions_from_data(data), 0.2, 0)
    chosen = ["joint_offset:joint_2", "axis_misalignment:joint_5"]
    model = ExtendedModel(robot, effects=[make_effect(robot, c) for c in chosen])
    initialise_with_priors(model, split.train, split.cond_fit, None)  # as diagnose does
    res = fit(model, split.train, cond=split.cond_fit)
    steps = [{"candidate": c, "accepted": True, "threshold": 1e-3} for c in chosen]
    pair = [("axis_misalignment:joint_5", "joint_offset:joint_4")]
    carry = Carry(make_folds(model, split, 0))  # the blocks, the default margin
    model, _ = prefer_fewer_causes(model, res, pair, split, (1e-3, carry), steps, lambda _m: None)
    where = f"run seed {RUN_SEED}: offset {truth:.4g} rad"
    labels = [e.label for e in model.effects]
    assert sorted(labels) == ["joint_offset:joint_2", "joint_offset:joint_4"], where
    assert abs(float(model.effect("joint_offset:joint_4").value) / truth - 1) < 0.05, where
    assert steps[-1]["replaces"] == "axis_misalignment:joint_5", where
    assert "fewer parameters" in steps[-1]["why"], where

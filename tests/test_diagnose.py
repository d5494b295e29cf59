"""Diagnosis must find hidden effects: kind, joint and value drawn at random from a seed.

The seed is pinned (``HYBRID_PK_TEST_SEED`` runs another; ``-m sweep`` runs fresh ones);
every failure message names it. Campaigns: 2,000–4,000 rows, noise 0.01–0.03 mm, effect
sized to 0.15–0.9 mm mean error on the campaign itself, unknown base and tool frames.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.plausibility import implausibility
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.effects import EFFECTS, ExtendedModel, make_effect
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import RUN_SEED, is_periodic, run_rng

pytestmark = pytest.mark.slow

ROBOTS = ("rx160", "ur10")
# column_bending needs a column: the shipped lifting column (two mimic segments under a
# sideways arm), where 0.15-0.9 mm takes 3e-6 to 2e-5 rad/Nm/m, as steel and aluminium
# tubes bend. (The generic 7-axis arm's short slide would need 1e-3, which no metal has.)
COLUMN_ROBOT = "column_arm"
# Smallest mean |moment| [Nm] about either axis perpendicular to a joint for its tilt to
# be drawn: a 0.15-0.9 mm tilt then needs a compliance metal joints have (<= 1e-5 rad/Nm).
MIN_TILT_MOMENT_NM = 20.0


def _robot(name: str) -> hpk.Robot:
    robot = hpk.Robot.from_urdf(name, end_link="tool0")
    robot.requires_grad_(False)
    return robot


def _joints_for(robot: hpk.Robot, kind: str, payload: float, gravity=None) -> list[str]:
    """Joints where the effect has a signature no frame or other joint can mimic
    (loads under ``gravity``, a root-frame vector; default upright)."""
    names = robot.joint_names
    g = (0.0, 0.0, -9.80665) if gravity is None else gravity
    if kind == "joint_offset":  # first joint = base yaw, last joint = tool roll
        return names[1:-1]
    if kind in ("gear_ratio", "joint_eccentricity", "backlash"):
        return names[:-1]
    if kind == "joint_compliance":
        q = robot.sample_q(256, torch.Generator().manual_seed(0))
        tau = robot.gravity_torques(q, payload=payload, gravity=g).abs().mean(0)
        return [n for n, t in zip(names, tau, strict=True) if t > 10.0]
    if kind == "column_bending":  # the column's segments (chain joints, mimic or not)
        types = robot.chain_joint_types
        return [n for n, t in zip(robot.chain_joint_names, types, strict=True) if t == "prismatic"]
    if kind == "tilt_compliance":
        q = robot.sample_q(256, torch.Generator().manual_seed(0))
        W = robot.static_wrenches(q, payload=payload, gravity=g, frame="joint")
        out = []
        for i, name in enumerate(names):
            basis = make_effect(robot, f"tilt_compliance:{name}").basis
            moment = (W[:, i, 3:] @ basis.T).abs().mean(0)
            if bool((moment > MIN_TILT_MOMENT_NM).all()):
                out.append(name)
        return out
    if kind == "link_length":  # a length error along the link itself
        return [n for i, n in enumerate(names[1:], 1) if _link_direction(robot, i) is not None]
    if kind == "axis_misalignment":  # that moves the flange (the campaigns' size measure)
        return [n for n in names[1:] if _moves_flange(robot, f"{kind}:{n}")]
    raise AssertionError(kind)


def _moves_flange(robot: hpk.Robot, label: str) -> bool:
    """Whether a small effect moves the flange's origin at all. A misalignment of the
    RX160's last origin only turns the flange about its own centre: its size, measured
    as a position error at the flange, would be zero."""
    q = robot.sample_q(16, torch.Generator().manual_seed(0))
    values = (1e-3 * torch.ones(make_effect(robot, label).value.shape)).tolist()
    with torch.no_grad():
        moved = ExtendedModel(robot, [make_effect(robot, label, values)])(q)[:, :3, 3]
        return bool((moved - robot.fk(q)[:, :3, 3]).norm(dim=-1).max() > 1e-9)


def _link_direction(robot: hpk.Robot, index: int) -> torch.Tensor | None:
    """Unit direction of origin ``index``'s translation with the components along the two
    joint axes it connects removed: a shift along either axis commutes with that joint's
    rotation and equals shifting the neighbouring origin (structurally ambiguous)."""
    t = torch.tensor(robot.spec.origins[index, :3, 3])
    own = torch.tensor(robot.spec.origins[index, :3, :3] @ robot.spec.axes[index])
    previous = torch.tensor(robot.spec.axes[index - 1])  # in the same (segment) frame
    for axis in (previous, own):
        axis = axis / axis.norm()
        t = t - (t @ axis) * axis
    return None if t.norm() < 0.05 else t / t.norm()


def _draw(robot: hpk.Robot, kind: str, rng: np.random.Generator, payload: float):
    """Label and unit-size value of a random effect of ``kind``."""
    if kind == "thermal_expansion":
        return kind, float(rng.uniform(0.5, 1.0))
    joint = str(rng.choice(_joints_for(robot, kind, payload)))
    label = f"{kind}:{joint}"
    if kind == "link_length":
        d = _link_direction(robot, robot.joint_names.index(joint))
        return label, (d * rng.choice([-1.0, 1.0])).tolist()
    if kind == "axis_misalignment":
        e = make_effect(robot, label)
        uv = rng.normal(size=2)
        return label, (torch.tensor(uv / np.linalg.norm(uv)) @ e.basis).tolist()
    if kind == "joint_eccentricity":
        ab = rng.normal(size=2)
        return label, (ab / np.linalg.norm(ab)).tolist()
    if kind in ("tilt_compliance", "column_bending"):  # compliances are positive
        c = np.abs(rng.normal(size=2)) + 0.2
        return label, (c / np.linalg.norm(c)).tolist()
    sign = 1.0 if kind in ("backlash", "joint_compliance") else rng.choice([-1.0, 1.0])
    return label, float(sign)


def _scaled(robot, label, unit_value, scale, factor):
    v = np.asarray(unit_value, dtype=float) * scale * factor
    return make_effect(robot, label, v.tolist() if v.ndim else float(v))


def _campaign(
    robot, specs, rng, *, position_only=False, payload=10.0, payload_range=None, mount=None
):
    """Simulated campaign with each effect sized to 0.15–0.9 mm mean error (``mount``:
    a mounting of ``simulate_campaign``; the tracker is then level)."""
    n = int(rng.integers(2000, 4001))
    noise = float(rng.uniform(0.01, 0.03))
    seed = int(rng.integers(1 << 30))
    kw = {
        "trajectory": "random",
        "payload": payload,
        "payload_range": payload_range,
        "temperature_range": (20.0, 28.0),
        "seed": seed,
        "mount": mount,
    }
    effects, truth_values = [], {}
    for label, unit_value in specs:
        cls = EFFECTS[label.split(":")[0]]
        probe = _scaled(robot, label, unit_value, cls.scale, 1.0)
        _, truth = simulate_campaign(robot, n, [probe], noise_mm=0.0, known_frames=True, **kw)
        error = truth["dataset_error"]["position_mm"]["mean"]
        factor = float(rng.uniform(0.15, 0.9)) / error
        # Physics first: a hidden effect is a plausible one. Where 0.15-0.9 mm needs more
        # (a backlash of 1.2 deg on the RX160's wrist), draw it smaller, with margin for
        # the 20 % that the found value may differ by.
        while implausibility(_scaled(robot, label, unit_value, cls.scale, 1.5 * factor), robot):
            factor *= 0.8
        effect = _scaled(robot, label, unit_value, cls.scale, factor)
        effects.append(effect)
        truth_values[label] = effect.report_value()
    data, _ = simulate_campaign(
        robot,
        n,
        effects,
        noise_mm=noise,
        noise_deg=0.0 if position_only else noise / 10,
        position_only=position_only,
        **kw,
    )
    return data, truth_values, f"seed {RUN_SEED}, n={n}, noise={noise:.3f} mm"


def _value_error(found, truth, kind: str) -> float:
    if is_periodic(kind):
        truth = math.hypot(*truth)
    f, t = np.asarray(found, dtype=float), np.asarray(truth, dtype=float)
    return float(np.linalg.norm(f - t) / np.linalg.norm(t))


# Each search step tests at a family-wise false-positive rate alpha (1e-3), so about one
# diagnosis in a thousand or two names a chance cause fitted to the noise (a 3 µrad axis
# tilt, 0.003 µm of hold-out gain, beside a 0.13 mm thermal expansion). One such cause is
# tolerated when its hold-out gain is below this fraction of the nominal error; a
# stand-in for the truth or a real wrong cause gains far more and fails.
CHANCE_GAIN = 1e-3


def _check(diag, truth_values, where):
    named = {(c.effect if c.joint is None else f"{c.effect}:{c.joint}"): c for c in diag.causes}
    bound = CHANCE_GAIN * diag.nominal["position_mm"]["mean"]
    chance = [k for k in set(named) - set(truth_values) if named[k].position_gain_mm < bound]
    if len(chance) == 1:
        named.pop(chance[0])
    assert set(named) == set(truth_values), (
        f"{where}: expected causes {sorted(truth_values)}, diagnosis named {sorted(named)}; "
        f"steps {diag.steps}"
    )
    for label, truth in truth_values.items():
        cause = named[label]
        err = _value_error(cause.value, truth, cause.effect)
        assert err < 0.2, f"{where}: {label} value {cause.value}, truth {truth} ({err:.0%} off)"
        assert cause.position_gain_mm > 0, f"{where}: {label} has no hold-out gain"
        # a cause of the whole robot lowers the error of most regions held out in turn
        blocks = cause.blocked_blocks
        if blocks is not None:
            assert 2 * blocks["gained"] > blocks["of"], f"{where}: {label} {blocks}"


@pytest.mark.parametrize("kind", sorted(EFFECTS))
def test_hidden_effect_is_named_with_its_value(kind):
    rng = run_rng(kind)
    robot = _robot(str(rng.choice(ROBOTS)) if kind != "column_bending" else COLUMN_ROBOT)
    spec = _draw(robot, kind, rng, payload=10.0)
    data, truth, where = _campaign(robot, [spec], rng)
    diag = diagnose(robot, data, seed=RUN_SEED % 1000)
    _check(diag, truth, f"{robot.name} {where}")
    # halved, or at what the noise alone leaves: an effect sized with known frames can be
    # mostly a frame change once they are fitted (sweep seed 919191: a shoulder axis
    # tilted about the vertical left 0.058 mm nominal, the noise alone 0.040 mm)
    noise = float(re.search(r"noise=([0-9.]+) mm", where).group(1))
    floor = math.sqrt(8 / math.pi) * noise  # mean 3-D norm of the noise; ~2 % sd here
    extended, nominal = (d["position_mm"]["mean"] for d in (diag.extended, diag.nominal))
    assert extended < max(nominal / 2, 1.1 * floor), (where, extended, nominal, floor)


def test_hidden_effect_position_only_data():
    rng = run_rng("position-only")
    robot = _robot(str(rng.choice(ROBOTS)))
    kind = str(rng.choice(["joint_offset", "joint_compliance", "gear_ratio", "link_length"]))
    data, truth, where = _campaign(robot, [_draw(robot, kind, rng, 10.0)], rng, position_only=True)
    assert data.quat is None
    diag = diagnose(robot, data, seed=1)
    _check(diag, truth, f"{robot.name} position-only {where}")
    assert diag.extended["orientation_deg"] is None


def test_two_hidden_effects_at_once():
    rng = run_rng("two")
    robot = _robot(str(rng.choice(ROBOTS)))
    kinds = rng.choice(["joint_offset", "joint_compliance", "gear_ratio", "backlash"], 2, False)
    specs = [_draw(robot, str(k), rng, 10.0) for k in kinds]
    while specs[0][0] == specs[1][0]:
        specs[1] = _draw(robot, str(kinds[1]), rng, 10.0)
    data, truth, where = _campaign(robot, specs, rng)
    _check(diagnose(robot, data, seed=2), truth, f"{robot.name} two effects {where}")


def test_hidden_compliance_with_varying_payload():
    rng = run_rng("payload")
    robot = _robot(str(rng.choice(ROBOTS)))
    spec = _draw(robot, "joint_compliance", rng, 10.0)
    data, truth, where = _campaign(robot, [spec], rng, payload=0.0, payload_range=(0.0, 20.0))
    assert float(data.payload.max() - data.payload.min()) > 10.0
    _check(diagnose(robot, data, seed=3), truth, f"{robot.name} payload {where}")


def test_noise_only_data_has_no_causes():
    rng = run_rng("noise")
    robot = _robot(str(rng.choice(ROBOTS)))
    data, _, where = _campaign(robot, [], rng)
    diag = diagnose(robot, data, seed=4)
    assert diag.causes == [], f"{where}: named {[c.effect for c in diag.causes]} in pure noise"
    assert not diag.unexplained["structured"], f"{where}: noise flagged as structured"


def test_diagnosis_on_data_generated_with_pinocchio(pin):
    """An independent generator: pinocchio FK and gravity, our code only diagnoses."""
    robot, data, truth = pinocchio_campaign(pin, run_rng("pinocchio"))
    diag = diagnose(robot, data, seed=5)
    _check(diag, truth, f"pinocchio-generated, seed {RUN_SEED}")


def pinocchio_campaign(pin, rng):
    """``(robot, data, truth)``: an RX160 campaign of 2,500 rows made by pinocchio (FK
    and gravity) with a joint-3 offset and a joint-2 compliance under a 15 kg payload,
    their sizes drawn from ``rng``."""
    robot = _robot("rx160")
    model = pin.buildModelFromUrdf(robot.spec.urdf_path)
    data_pin = model.createData()
    fid = model.getFrameId("tool0")
    n = 2500
    q = robot.sample_q(n, torch.Generator().manual_seed(int(rng.integers(1 << 30)))).numpy()
    offset = float(rng.uniform(3e-4, 8e-4)) * rng.choice([-1, 1])  # joint_3 offset [rad]
    compliance = float(rng.uniform(1.0e-6, 2.5e-6))  # joint_2 [rad/Nm]
    payload = 15.0
    frame = model.frames[fid]
    jid = frame.parentJoint
    model.inertias[jid] = model.inertias[jid] + pin.Inertia(
        payload, frame.placement.translation, np.zeros((3, 3))
    )
    data_pin = model.createData()
    base = pin.SE3(pin.rpy.rpyToMatrix(0.02, -0.01, 2.1), np.array([2.2, -0.8, 0.4]))
    tool = pin.SE3(pin.rpy.rpyToMatrix(0.1, 0.2, -0.3), np.array([0.03, -0.02, 0.11]))
    noise = 0.02e-3
    poses = []
    for qi in q:
        qt = qi.copy()
        qt[2] += offset
        for _ in range(6):  # sag under gravity: theta = theta_cmd - c g(theta)
            g = pin.computeGeneralizedGravity(model, data_pin, qt)
            qt = qi.copy()
            qt[2] += offset
            qt[1] -= compliance * g[1]
        pin.framesForwardKinematics(model, data_pin, qt)
        poses.append((base * data_pin.oMf[fid] * tool).homogeneous)
    T = torch.tensor(np.stack(poses))
    gen = torch.Generator().manual_seed(7)
    position = T[:, :3, 3] + noise * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    from hybrid_pk.data.measured import MeasuredData
    from hybrid_pk.geometry import matrix_to_quat, so3_exp

    R = T[:, :3, :3] @ so3_exp(2e-5 * torch.randn(n, 3, generator=gen, dtype=torch.float64))
    data = MeasuredData(
        q=torch.tensor(q),
        position=position,
        quat=matrix_to_quat(R),
        joint_names=tuple(robot.joint_names),
        file_index=torch.zeros(n, dtype=torch.long),
        rows=torch.arange(1, n + 1),
        sources=("<pinocchio>",),
        payload=torch.full((n,), payload, dtype=torch.float64),
    )
    return robot, data, {"joint_offset:joint_3": offset, "joint_compliance:joint_2": compliance}


def test_identification_within_reported_3_sigma_in_repeated_trials():
    """Repeated seeded campaigns: every injected value within its reported 3 sigma."""
    from hybrid_pk.calibration.fit import fit, initialise_frames
    from hybrid_pk.effects import conditions_from_data

    robot = _robot("rx160")
    labels = {"joint_offset:joint_3": 6e-4, "joint_compliance:joint_2": 1.8e-6}
    z_scores = []
    for trial in range(8):
        effects = [make_effect(robot, k, v) for k, v in labels.items()]
        data, _ = simulate_campaign(
            robot, 600, effects, noise_mm=0.02, noise_deg=0.002, payload=20.0, seed=100 + trial
        )
        model = ExtendedModel(robot, [make_effect(robot, k) for k in labels])
        cond = conditions_from_data(data)
        initialise_frames(model, data, cond)
        res = fit(model, data, cond=cond)
        for label, truth in labels.items():
            sl = res.block_slice(label)
            z_scores.append((float(res.x[sl][0]) - truth) / float(res.std[sl][0]))
    z = np.asarray(z_scores)
    assert np.all(np.abs(z) < 3), f"z-scores beyond 3 sigma: {np.round(z, 2)}"
    # The reported sigma is honest, not inflated: the spread of z is about 1.
    assert 0.4 < z.std() < 1.8, f"z spread {z.std():.2f}: sigma mis-estimated ({np.round(z, 2)})"


def test_candidate_made_redundant_by_a_chosen_effect_scores_sanely():
    """Regression: after joint_offset:joint_3 is chosen on the RX160, the misalignment of
    joint_4 about y (a rotation of a zero-length origin about the parallel joint-3 axis)
    is the same motion. Its rank-deficient signature once scored F = 1e304 and hid the
    real second effect (a joint-1 gear ratio)."""
    robot = _robot("rx160")
    effects = [
        make_effect(robot, "joint_offset:joint_3", 9e-4),
        make_effect(robot, "gear_ratio:joint_1", 2.3e-4),
    ]
    data, _ = simulate_campaign(robot, 1000, effects, noise_mm=0.02, noise_deg=0.002, seed=3)
    diag = diagnose(robot, data, seed=3)
    named = {f"{c.effect}:{c.joint}" for c in diag.causes}
    assert named == {"joint_offset:joint_3", "gear_ratio:joint_1"}, diag.steps
    assert all(s["score_F"] < 1e12 for s in diag.steps), diag.steps


@pytest.mark.parametrize(
    ("effect", "value", "flagged"),
    [
        ("thermal_expansion", 1.2e-5, False),  # steel
        ("thermal_expansion", -2.5e-4, True),  # negative and 20x steel
        ("joint_compliance", 2e-6, False),
        ("joint_compliance", -2e-6, True),
    ],
)
def test_implausible_values_are_flagged(effect, value, flagged):
    from hybrid_pk.calibration.diagnosis.search import Cause, plausibility_warnings

    robot = _robot("rx160")
    data, _ = simulate_campaign(robot, 200, [], noise_mm=0.01, seed=0)
    joint = None if effect == "thermal_expansion" else "joint_2"
    cause = Cause(effect, joint, value, "-", 0.0, 0.1, 0.0, "")
    assert bool(plausibility_warnings([cause], data)) == flagged


def test_temperature_that_differs_between_files_is_flagged():
    from hybrid_pk.calibration.diagnosis.search import Cause, plausibility_warnings
    from hybrid_pk.data.measured import MeasuredData

    robot = _robot("rx160")
    a, _ = simulate_campaign(robot, 100, [], noise_mm=0.01, seed=0, temperature_range=(20, 20.2))
    b, _ = simulate_campaign(robot, 100, [], noise_mm=0.01, seed=1, temperature_range=(22, 22.2))
    b = MeasuredData(**{**b.__dict__, "sources": ("b.csv",)})
    a = MeasuredData(**{**a.__dict__, "sources": ("a.csv",)})
    data = MeasuredData.concat([a, b])
    why = plausibility_warnings(
        [Cause("thermal_expansion", None, 1.2e-5, "1/K", 0, 0, 0, "")], data
    )
    assert why
    assert "between files" in why[0]["why"]

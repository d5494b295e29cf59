"""Mountings and deflection beyond the joint axis: model, oracle, Jacobian, files, CLI.

- the deflection of ``tilt_compliance`` / ``column_bending`` against a hand-built chain
  whose extra rotation comes from pinocchio's static joint wrench;
- the structured identification Jacobian against forward-mode autodiff of the
  residual, with gravity from a levelled tracker (the base frame then moves gravity);
- gravity and mount parsing, the simulated mount (level tracker, rotated base), model
  files that keep the mounting (and old files that load upright), and the CLI.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.cli.main import main as cli
from hybrid_pk.data.measured import MeasuredData
from hybrid_pk.effects import (
    Conditions,
    ExtendedModel,
    Gravity,
    conditions_from_data,
    make_effect,
    parse_gravity,
)
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import matrix_to_quat, so3_exp, transform
from hybrid_pk.io.model_file import load_model, save_model
from hybrid_pk.robot import STANDARD_GRAVITY
from hybrid_pk.simulate import parse_mount, simulate_campaign

F64 = torch.float64
ARM7 = Path(__file__).resolve().parent / "data" / "arm7_generic.urdf"


def _robot(name: str) -> hpk.Robot:
    robot = hpk.Robot.from_urdf(name, end_link="tool0")
    robot.requires_grad_(False)
    return robot


# ----------------------------------------------------------------------------- oracle


def _pin_wrench(robot, q: np.ndarray, payload: float, gravity: np.ndarray, joint: str):
    """Force and moment (joint frame) pinocchio's RNEA transmits through ``joint``."""
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromUrdf(robot.spec.urdf_path)
    fid = model.getFrameId(robot.end_link)
    frame = model.frames[fid]
    model.inertias[frame.parentJoint] += pin.Inertia(
        payload, frame.placement.translation, np.zeros((3, 3))
    )
    model.gravity.linear = gravity
    data = model.createData()
    qp = np.zeros(model.nq)
    for i, name in enumerate(robot.joint_names):
        qp[model.idx_qs[model.getJointId(name)]] = q[i]
    pin.rnea(model, data, qp, np.zeros(model.nv), np.zeros(model.nv))
    f = data.f[model.getJointId(joint)]
    return f.linear.copy(), f.angular.copy()


@pytest.mark.parametrize(
    ("urdf", "label", "value"),
    [
        ("rx160", "tilt_compliance:joint_2", [2e-6, -1e-6]),
        ("ur10", "tilt_compliance:shoulder_pan_joint", [3e-6, 5e-6]),
        (str(ARM7), "column_bending:j4", [4e-5, 2e-5]),
        (str(ARM7), "tilt_compliance:j4", [1e-5, 3e-5]),
    ],
)
def test_deflection_matches_a_hand_built_chain_with_pinocchio_loads(urdf, label, value):
    """Expected pose: rigid FK up to joint i's frame, then the rotation ``exp(w)`` about
    the pivot, then the rest of the rigid chain; ``w`` from pinocchio's wrench."""
    robot = _robot(urdf)
    effect = make_effect(robot, label, value)
    model = ExtendedModel(robot, [effect])
    gravity = np.array([1.2, -3.0, -9.2])
    payload = 6.0
    q = robot.sample_q(8, torch.Generator().manual_seed(5))
    cond = Conditions(payload=torch.full((8,), payload, dtype=F64))
    model.gravity = Gravity(tuple(gravity), "root")
    with torch.no_grad():
        got = model.end_pose(q, cond)
        frames = robot.link_frames(q)
    i = effect.joint_index
    e1, e2 = effect.basis.numpy()
    c = np.asarray(value)
    for k, qk in enumerate(q.numpy()):
        force, moment = _pin_wrench(robot, qk, payload, gravity, effect.joint)
        if effect.kind == "column_bending":
            length = qk[i]
            a = effect.axis_unit.numpy()
            pivot = -0.5 * length * a
            moment = moment + np.cross(-pivot, force)
        else:
            length, pivot = 1.0, np.zeros(3)
        w = -length * (c[0] * (e1 @ moment) * e1 + c[1] * (e2 @ moment) * e2)
        D = transform(so3_exp(torch.tensor(w)), torch.zeros(3, dtype=F64))
        P = transform(torch.eye(3, dtype=F64), torch.tensor(pivot))
        Pinv = transform(torch.eye(3, dtype=F64), -torch.tensor(pivot))
        F_i = frames[k, i]
        rest = torch.linalg.inv(F_i) @ frames[k, robot.dof]  # joint frame i -> end link
        expected = F_i @ P @ D @ Pinv @ rest
        torch.testing.assert_close(got[k], expected, atol=1e-12, rtol=0)


def test_deflection_gradcheck_through_values_and_joints():
    robot = _robot(str(ARM7))
    tilt = make_effect(robot, "tilt_compliance:j3", [2e-6, 1e-6])
    column = make_effect(robot, "column_bending:j4", [3e-5, 1e-5])
    model = ExtendedModel(robot, [tilt, column])
    q = robot.sample_q(3, torch.Generator().manual_seed(6)).requires_grad_(True)

    def pose(q, a, b):
        params = {"effects.0.value": a, "effects.1.value": b}
        return torch.func.functional_call(model, params, (q,))

    args = (q, tilt.value.detach().clone().requires_grad_(True))
    args += (column.value.detach().clone().requires_grad_(True),)
    assert torch.autograd.gradcheck(pose, args)


def test_column_bending_needs_a_prismatic_joint():
    with pytest.raises(HybridPKError, match=r"prismatic.*tilt_compliance:joint_2"):
        make_effect(_robot("rx160"), "column_bending:joint_2")


def test_column_tilt_grows_with_extension():
    robot = _robot(str(ARM7))
    model = ExtendedModel(robot, [make_effect(robot, "column_bending:j4", [5e-5, 5e-5])])
    rigid = ExtendedModel(robot)
    q = torch.zeros(2, robot.dof, dtype=F64)
    q[0, 3], q[1, 3] = 0.05, 0.15  # extension of the prismatic joint j4 [m]
    cond = Conditions(payload=torch.full((2,), 5.0, dtype=F64))
    with torch.no_grad():
        moved = (model(q, cond)[:, :3, 3] - rigid(q, cond)[:, :3, 3]).norm(dim=-1)
    assert moved[1] > 2.5 * moved[0] > 0  # about (0.15 / 0.05) times, grows further


# ----------------------------------------------------------------------------- Jacobian


def _level_campaign(robot, effects, n=60):
    base = transform(
        so3_exp(torch.tensor([math.pi * 0.97, 0.1, 0.3], dtype=F64)),
        torch.tensor([2.0, 1.0, 0.5], dtype=F64),
    )
    tool = transform(
        so3_exp(torch.tensor([0.1, 0.2, 0.3], dtype=F64)),
        torch.tensor([0.01, 0.02, 0.1], dtype=F64),
    )
    model = ExtendedModel(robot, effects, base=base, tool=tool, gravity=Gravity.level_tracker())
    q = robot.sample_q(n, torch.Generator().manual_seed(0))
    cond = Conditions(payload=torch.full((n,), 15.0, dtype=F64))
    with torch.no_grad():
        T = model(q, cond)
    noise = 1e-5 * torch.randn(n, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    data = MeasuredData(
        q=q,
        position=T[:, :3, 3] + noise,
        quat=matrix_to_quat(T[:, :3, :3]),
        joint_names=tuple(robot.joint_names),
        file_index=torch.zeros(n, dtype=torch.long),
        rows=torch.arange(1, n + 1),
        sources=("level",),
        payload=cond.payload,
    )
    return model, data, cond


def test_structured_jacobian_matches_autodiff_with_a_levelled_tracker():
    """Frame and deflection columns are exact; the rest drops second-order couplings of
    the static load (compliance sag, deflection) on the joints and geometry, measured
    here: at most ~1.3e-3 relative (RX160, 15 kg, sag and tilt of ~1 mrad)."""
    robot = _robot("rx160")
    labels = {
        "joint_offset:joint_3": 5e-4,
        "joint_compliance:joint_2": 2e-6,
        "tilt_compliance:joint_2": [1e-6, 3e-6],
        "tilt_compliance:joint_1": [5e-7, 5e-7],
        "link_length:joint_3": [1e-4, 0.0, 2e-4],
        "axis_misalignment:joint_4": [0.0, 1e-3, 0.0],
    }
    model, data, cond = _level_campaign(
        robot, [make_effect(robot, k, v) for k, v in labels.items()]
    )
    blocks = param_blocks(model, None, False)
    problem = Problem(model, data, cond, blocks, 0.01, 1e-4)
    theta = torch.zeros_like(problem.x0)
    _, J = problem.jacobian(theta)
    J_ad = torch.func.jacfwd(problem.residual)(theta)
    start, worst = 0, {}
    for b in blocks:
        cols = slice(start, start + b.size)
        start += b.size
        err = (J[:, cols] - J_ad[:, cols]).norm(dim=0) / J_ad[:, cols].norm(dim=0)
        worst[b.label] = float(err.max())
    for label in ("base_frame.rotation", "tilt_compliance:joint_1", "tilt_compliance:joint_2"):
        assert worst[label] < 1e-6, worst
    assert max(worst.values()) < 3e-3, worst


def test_levelled_tracker_fit_recovers_gravity_and_values_from_an_identity_start():
    robot = _robot("rx160")
    truth = {"joint_compliance:joint_2": 2e-6, "tilt_compliance:joint_2": [1e-6, 3e-6]}
    effects = [make_effect(robot, k, v) for k, v in truth.items()]
    true_model, data, _ = _level_campaign(robot, effects, 150)
    model = ExtendedModel(
        robot, [make_effect(robot, k) for k in truth], gravity=Gravity.level_tracker()
    )
    cond = conditions_from_data(data)
    initialise_frames(model, data, cond)
    fit(model, data, cond=cond)
    for label, value in truth.items():
        got = model.effect(label).value.detach()
        torch.testing.assert_close(got, torch.as_tensor(value, dtype=F64), rtol=2e-2, atol=0)
    g_root = model.gravity_root(cond).detach()  # the base is nearly upside down
    torch.testing.assert_close(g_root, true_model.gravity_root(), atol=1e-3, rtol=0)
    assert float(g_root[2]) > 0.95 * STANDARD_GRAVITY


# ----------------------------------------------------------------------------- parsing


def test_parse_gravity():
    assert parse_gravity(None).is_default
    assert parse_gravity("level-tracker").levelled
    assert parse_gravity("0,0,9.81").vector == (0.0, 0.0, 9.81)
    with pytest.raises(HybridPKError, match=r"magnitude 1 m/s.*0,0,-9\.81"):
        parse_gravity("0,0,-1")
    with pytest.raises(HybridPKError, match="X,Y,Z"):
        parse_gravity("down")
    # a zero vector has no direction to scale: the example is the floor's, not 0,0,0
    with pytest.raises(HybridPKError, match=r"magnitude 0 m/s.*\(e\.g\. 0,0,-9\.81, a robot on"):
        parse_gravity("0,0,0")


@pytest.mark.parametrize(
    ("spec", "gravity", "tilt"),
    [
        ("floor", (0, 0, -1), 0),
        ("ceiling", (0, 0, 1), 180),
        ("wall", (1, 0, 0), 90),
        ("tilt:30", (math.sin(math.radians(30)), 0, -math.cos(math.radians(30))), 30),
    ],
)
def test_mounts(spec, gravity, tilt):
    mount = parse_mount(spec)
    g = mount.gravity_root / STANDARD_GRAVITY
    torch.testing.assert_close(g, torch.tensor(gravity, dtype=F64), atol=1e-12, rtol=0)
    assert abs(mount.tilt_deg - tilt) < 1e-9


def test_bad_mount_lists_the_choices():
    with pytest.raises(HybridPKError, match="floor, ceiling, wall"):
        parse_mount("roof")
    with pytest.raises(HybridPKError, match=r"0\.\.180"):
        parse_mount("tilt:200")


def test_simulated_mount_keeps_the_tracker_level():
    robot = _robot("ur10")
    truth = simulate_campaign(robot, 20, [], noise_mm=0.0, mount="tilt:40,70", seed=2)[1]
    base = torch.tensor(truth["base_frame"], dtype=F64)
    g_meas = base[:3, :3] @ torch.tensor(truth["gravity"], dtype=F64)
    torch.testing.assert_close(
        g_meas, torch.tensor([0, 0, -STANDARD_GRAVITY], dtype=F64), atol=1e-9, rtol=0
    )
    assert abs(truth["mount"]["tilt_deg"] - 40) < 1e-9
    default = simulate_campaign(robot, 20, [], noise_mm=0.0, seed=2)[1]
    assert default["mount"] is None
    assert default["gravity"] == [0.0, 0.0, -STANDARD_GRAVITY]


# ----------------------------------------------------------------------------- files


def test_model_file_keeps_the_mounting_and_old_files_load_upright(tmp_path):
    robot = _robot(str(ARM7))
    effects = [
        make_effect(robot, "column_bending:j4", [3e-5, 1e-5]),
        make_effect(robot, "tilt_compliance:j1", [1e-6, 2e-6]),
        make_effect(robot, "joint_compliance:j2", 1e-6),
    ]
    model = ExtendedModel(robot, effects, gravity=Gravity.level_tracker(), frame_sets=2)
    with torch.no_grad():
        model.base.rotvec.copy_(torch.tensor([[3.0, 0.1, 0.0], [0.0, 1.5, 0.2]]))
    path = save_model(tmp_path / "m.pt", model)
    loaded = load_model(path).model
    assert loaded.gravity == Gravity.level_tracker()
    q = robot.sample_q(9, torch.Generator().manual_seed(3))
    cond = Conditions(payload=torch.full((9,), 4.0, dtype=F64), group=torch.arange(9) % 2)
    with torch.no_grad():
        assert torch.equal(loaded(q, cond), model(q, cond))
    payload = torch.load(path, weights_only=True)
    assert payload["version"] == 2
    # a version-1 file (written before mountings existed) means upright
    del payload["gravity"]
    payload["version"] = 1
    torch.save(payload, tmp_path / "old.pt")
    assert load_model(tmp_path / "old.pt").model.gravity.is_default
    upright = save_model(tmp_path / "up.pt", ExtendedModel(robot, effects))
    assert torch.load(upright, weights_only=True)["version"] == 1  # older readers read it


# ----------------------------------------------------------------------------- CLI


def test_cli_simulate_mount_then_calibrate_level_tracker(tmp_path, capsys):
    data = tmp_path / "ceiling.csv"
    rc = cli(
        ["simulate", "rx160", "--n", "250", "--effects", "joint_compliance:joint_2=2e-6",
         "--mount", "ceiling", "--payload", "20", "--noise-mm", "0.01", "--noise-deg",
         "0.001", "--seed", "4", "--out", str(data)]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0
    assert "mounted ceiling (180.0 deg from upright)" in out, out
    truth = json.loads(Path(f"{data}.truth.json").read_text())
    assert truth["gravity"][2] == pytest.approx(STANDARD_GRAVITY)
    values = {}
    for gravity in ("level-tracker", "0,0,9.80665", None):
        model = tmp_path / f"m{len(values)}.pt"
        argv = ["calibrate", str(data), "--robot", "rx160", "--out", str(model), "--no-urdf"]
        argv += ["--effects", "joint_compliance:joint_2"]
        argv += [] if gravity is None else ["--gravity", gravity]
        assert cli(argv) == 0
        out = capsys.readouterr().out
        loaded = load_model(model)
        values[gravity] = float(loaded.model.effects[0].value.detach())
        if gravity == "level-tracker":
            assert "root z axis 180.0 deg from upright (level-tracker)" in out, out
            assert loaded.model.gravity.levelled
    assert values["level-tracker"] == pytest.approx(2e-6, rel=0.01)
    assert values["0,0,9.80665"] == pytest.approx(2e-6, rel=0.01)
    assert values[None] == pytest.approx(-2e-6, rel=0.01)  # upright gravity: wrong sign


def test_cli_gravity_errors_are_one_line(tmp_path, capsys):
    rc = cli(["simulate", "rx160", "--n", "5", "--gravity", "level-tracker",
              "--out", str(tmp_path / "x.csv")])  # fmt: skip
    err = capsys.readouterr().err
    assert rc != 0
    assert "level-tracker is what calibrate and diagnose assume" in err
    rc = cli(["simulate", "rx160", "--n", "5", "--mount", "tilt:abc",
              "--out", str(tmp_path / "x.csv")])  # fmt: skip
    assert rc != 0
    assert "tilt:DEG" in capsys.readouterr().err


# ----------------------------------------------------------------------------- evidence


@pytest.mark.parametrize(
    ("urdf", "label", "value"),
    [
        ("rx160", "tilt_compliance:joint_2", [1e-6, 2e-6]),
        (str(ARM7), "column_bending:j4", [4e-4, 2e-4]),
    ],
)
def test_deflection_evidence_shows_the_law_and_a_plot(tmp_path, urdf, label, value):
    """The partial residual's tilt against the predicted tilt: slope 1 (points_value =
    the value) when the deflection is there, and a plot file."""
    from hybrid_pk.calibration.diagnosis import Cause
    from hybrid_pk.report.evidence import cause_evidence
    from hybrid_pk.report.plots import evidence_plot

    robot = _robot(urdf)
    data, _ = simulate_campaign(
        robot, 300, [make_effect(robot, label, value)], noise_mm=0.005, payload=10.0, seed=8
    )
    model = ExtendedModel(robot, [make_effect(robot, label)])
    cond = conditions_from_data(data)
    initialise_frames(model, data, cond)
    fit(model, data, cond=cond)
    fitted = model.effects[0].report_value()
    kind, joint = label.split(":")
    cause = Cause(kind, joint, fitted, model.effects[0].unit, [0.0, 0.0], 0.1, 0.0, "")
    ev = cause_evidence(cause, data, model)
    assert ev.points_value == pytest.approx(ev.value, rel=0.1), (ev.points_value, ev.value)
    assert ev.value == pytest.approx(float(np.linalg.norm(value)), rel=0.05)
    assert ev.x.shape == ev.y.shape
    assert ev.x.size >= 300  # both components of most rows
    assert evidence_plot(ev, tmp_path / "tilt.png").stat().st_size > 10_000

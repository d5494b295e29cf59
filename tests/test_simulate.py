"""Virtual measurement campaigns: determinism, exactness, noise, trajectories, presets, CLI."""

from __future__ import annotations

import json
import math

import pytest
import torch

import hybrid_pk as hpk
import hybrid_pk.simulate as sim
from hybrid_pk.cli.main import main
from hybrid_pk.data import read_table_for
from hybrid_pk.effects import make_effect
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.geometry import quat_to_matrix, so3_log
from hybrid_pk.simulate import parse_effects, random_effects, simulate_campaign
from hybrid_pk.simulate.effect_specs import effects_from_file
from hybrid_pk.simulate.trajectories import ISO_CYCLE, make_trajectory
from tests.helpers import assert_quats_close, assert_transforms_close

pytestmark = pytest.mark.usefixtures("one_thread")

ROBOTS = ["rx160", "ur10"]


@pytest.fixture(scope="module")
def robots() -> dict[str, hpk.Robot]:
    return {name: hpk.Robot.from_urdf(name) for name in ROBOTS}


def test_public_names_resolve():
    for name in sim.__all__:
        assert getattr(sim, name) is not None, name


# ----------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("name", ROBOTS)
def test_noise_free_nominal_with_known_frames_is_fk(robots, name):
    robot = robots[name]
    data, truth = simulate_campaign(robot, 40, "none", noise_mm=0.0, known_frames=True, seed=3)
    T = robot.fk(data.q).detach()
    assert torch.allclose(data.position, T[:, :3, 3], rtol=0, atol=1e-12)
    assert_transforms_close(data.T_measured(), T, atol_pos=1e-12, atol_rot=1e-12)
    assert truth["effects"] == []
    assert truth["base_frame"] == torch.eye(4, dtype=torch.float64).tolist()
    assert truth["dataset_error"]["position_mm"]["max"] == 0.0


def test_unknown_frames_data_is_base_fk_tool_of_truth(robots):
    robot = robots["rx160"]
    data, truth = simulate_campaign(robot, 40, "none", noise_mm=0.0, seed=11)
    truth = json.loads(json.dumps(truth))  # exactly what FILE.truth.json holds
    base = torch.tensor(truth["base_frame"], dtype=torch.float64)
    tool = torch.tensor(truth["tool_frame"], dtype=torch.float64)
    expected = base @ robot.fk(data.q).detach() @ tool
    assert_transforms_close(data.T_measured(), expected, atol_pos=1e-12, atol_rot=1e-9)
    # A tracker 2-4 m away and a 50-200 mm tool, not identity frames.
    tracker_distance = float(torch.linalg.inv(base)[:2, 3].norm())
    assert 2.0 <= tracker_distance <= 4.0
    assert 0.05 <= float(tool[:3, 3].norm()) <= 0.2
    assert (data.quat[:, 0] >= 0).all()


def test_truth_effects_reproduce_the_data(robots):
    robot = robots["rx160"]
    spec = "joint_offset:joint_2=1e-3; link_length:joint_3=0,0,5e-4; backlash:joint_4=4e-4"
    data, truth = simulate_campaign(robot, 60, spec, noise_mm=0.0, seed=5)
    entries = json.loads(json.dumps(truth))["effects"]
    effects = sim.effect_specs.effects_from_entries(robot, entries, "truth")
    base = torch.tensor(truth["base_frame"], dtype=torch.float64)
    tool = torch.tensor(truth["tool_frame"], dtype=torch.float64)
    model = hpk.effects.ExtendedModel(robot, effects, base=base, tool=tool)
    cond = hpk.effects.Conditions(
        payload=data.payload, direction=hpk.effects.approach_direction(data.q)
    )
    with torch.no_grad():
        T = model(data.q, cond)
    assert_transforms_close(data.T_measured(), T, atol_pos=1e-12, atol_rot=1e-9)
    nominal = pose_error(T, base @ robot.fk(data.q).detach() @ tool).position_mm
    assert truth["dataset_error"]["position_mm"]["mean"] == pytest.approx(float(nominal.mean()))


# ----------------------------------------------------------------------------- determinism


def test_same_seed_same_files_other_seed_differs(tmp_path):
    def run(seed: int, name: str) -> tuple[bytes, bytes]:
        out = tmp_path / name
        argv = ["simulate", "ur10", "--n", "30", "--effects", "random:2", "--noise-mm", "0.02"]
        argv += ["--noise-deg", "0.01", "--seed", str(seed), "--out", str(out)]
        assert main(argv) == 0
        return out.read_bytes(), (tmp_path / f"{name}.truth.json").read_bytes()

    first, again, other = run(4, "a.csv"), run(4, "b.csv"), run(5, "c.csv")
    assert first == again
    assert first[0] != other[0]
    assert first[1] != other[1]


def test_noise_std_matches_request(robots):
    robot = robots["ur10"]
    n, noise_mm, noise_deg = 4000, 0.05, 0.02
    data, _ = simulate_campaign(
        robot, n, "none", noise_mm=noise_mm, noise_deg=noise_deg, known_frames=True, seed=8
    )
    T = robot.fk(data.q).detach()
    dp_mm = 1e3 * (data.position - T[:, :3, 3])
    std_mm = dp_mm.std(dim=0)
    assert torch.allclose(std_mm, torch.full((3,), noise_mm, dtype=torch.float64), rtol=0.1)
    # Right-multiplied noise: R_meas = R_true exp(w), so w = log(R_true^T R_meas).
    w = so3_log(T[:, :3, :3].transpose(-1, -2) @ quat_to_matrix(data.quat))
    std_deg = torch.rad2deg(w).std(dim=0)
    assert torch.allclose(std_deg, torch.full((3,), noise_deg, dtype=torch.float64), rtol=0.1)
    assert abs(float(dp_mm.mean())) < 0.1 * noise_mm


# ----------------------------------------------------------------------------- trajectories


@pytest.mark.parametrize("kind", sim.TRAJECTORIES)
@pytest.mark.parametrize("name", ROBOTS)
def test_trajectory_stays_within_joint_limits(robots, name, kind):
    robot = robots[name]
    traj = make_trajectory(robot, kind, 120, torch.Generator().manual_seed(2))
    lower, upper = robot.joint_limits
    assert traj.q.shape == (120, robot.dof)
    assert bool(torch.isfinite(traj.q).all())
    assert bool(((traj.q >= lower) & (traj.q <= upper)).all())


@pytest.mark.parametrize("name", ROBOTS)
def test_iso_cube_repeats_its_five_poses(robots, name):
    robot = robots[name]
    traj = make_trajectory(robot, "iso-cube", 23, torch.Generator())
    assert traj.pose[:5].tolist() == list(ISO_CYCLE)
    assert traj.pose.tolist() == [ISO_CYCLE[k % 5] for k in range(23)]
    p = robot.fk(traj.q).detach()[:, :3, 3]
    for pose in range(1, 6):
        rows = traj.pose == pose
        assert torch.allclose(p[rows], p[rows][0].expand_as(p[rows]), rtol=0, atol=1e-12)
    distinct = torch.stack([p[traj.pose == k][0] for k in range(1, 6)])
    cube = sim.iso_cube(robot)
    assert torch.allclose(distinct, cube.points, rtol=0, atol=1e-6)
    assert float(torch.cdist(distinct, distinct).add(torch.eye(5) * 1e3).min()) > 0.1
    assert float(torch.linalg.norm(cube.points[1] - cube.points[0])) == pytest.approx(
        0.8 * math.sqrt(3) / 2 * cube.side
    )


@pytest.mark.parametrize("name", ROBOTS)
def test_zigzag_is_a_raster_at_fixed_orientation(robots, name):
    robot = robots[name]
    cube = sim.iso_cube(robot)
    traj = make_trajectory(robot, "zigzag", 200, torch.Generator())
    T = robot.fk(traj.q).detach()
    angle = so3_log(cube.rotation.expand(200, 3, 3).transpose(-1, -2) @ T[:, :3, :3]).norm(dim=-1)
    assert float(angle.max()) < 1e-6
    offset = (T[:, :3, 3] - cube.centre).abs()
    assert float(offset.max()) <= cube.side / 2 + 1e-6
    step = (T[1:, :3, 3] - T[:-1, :3, 3]).norm(dim=-1)
    assert float(step.max()) < 2 * float(step.median())  # equally spaced along the path
    assert float((traj.q[1:] - traj.q[:-1]).abs().max()) < 0.5  # one IK branch throughout


def test_continuous_has_monotonic_time_and_smooth_joints(robots):
    robot = robots["rx160"]
    traj = make_trajectory(robot, "continuous", 300, torch.Generator().manual_seed(1))
    dt = traj.t[1:] - traj.t[:-1]
    assert bool((dt > 0).all())
    assert torch.allclose(dt, torch.full_like(dt, 0.1))  # 10 Hz
    speed = (traj.q[1:] - traj.q[:-1]).abs() / dt[:, None]
    assert float(speed.max()) < 2.0  # [rad/s]


def test_conditions_columns(robots):
    robot = robots["ur10"]
    data, truth = simulate_campaign(
        robot, 50, "none", noise_mm=0.0, payload_range=(2.0, 8.0), position_only=True, seed=1
    )
    assert data.quat is None
    assert bool(((data.payload >= 2.0) & (data.payload <= 8.0)).all())
    assert len(set(data.payload.tolist())) > 1
    assert data.temperature[0] == 20.0
    assert data.temperature[-1] == pytest.approx(28.0)
    assert bool((data.temperature[1:] >= data.temperature[:-1]).all())
    assert truth["payload_range"] == [2.0, 8.0]
    no_temp, _ = simulate_campaign(robot, 5, "none", noise_mm=0.0, temperature_range=None)
    assert no_temp.temperature is None
    assert no_temp.payload is not None


# ----------------------------------------------------------------------------- presets


def test_paper_preset_rx160_20kg_dataset_error(robots):
    _, truth = simulate_campaign(robots["rx160"], 2000, "paper", noise_mm=0.0, payload=20.0, seed=9)
    assert [e["effect"] for e in truth["effects"]] == ["joint_compliance"] * 3
    assert [e["joint"] for e in truth["effects"]] == ["joint_2", "joint_3", "joint_5"]
    assert 1.4 <= truth["dataset_error"]["position_mm"]["mean"] <= 2.2


def test_paper_preset_other_robot_is_scaled_to_the_same_error(robots):
    effects = sim.paper_effects(robots["ur10"])
    assert [e.kind for e in effects] == ["joint_compliance"] * 3
    _, truth = simulate_campaign(robots["ur10"], 1000, effects, noise_mm=0.0, payload=20.0)
    assert 1.4 <= truth["dataset_error"]["position_mm"]["mean"] <= 2.2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_k_distinct_effects_of_useful_size(robots, seed):
    robot = robots["rx160"]
    effects = random_effects(robot, 3, seed=seed)
    assert len({e.label for e in effects}) == 3
    assert [e.label for e in random_effects(robot, 3, seed=seed)] == [e.label for e in effects]
    for e in effects:
        _, truth = simulate_campaign(robot, 400, [e], noise_mm=0.0, seed=seed)
        assert 0.1 <= truth["dataset_error"]["position_mm"]["mean"] <= 1.5, e


def test_random_avoids_effects_given_explicitly(robots):
    robot = robots["rx160"]
    spec = "joint_offset:joint_2=1e-3; random:8; link_length:joint_3=0,0,1e-4"
    for seed in range(3):
        labels = [e.label for e in parse_effects(robot, spec, seed=seed)]
        assert len(labels) == 10
        assert len(set(labels)) == 10
        assert labels[0] == "joint_offset:joint_2"
        assert labels[-1] == "link_length:joint_3"


def test_random_default_k_and_hidden_flag(robots):
    effects = parse_effects(robots["ur10"], "random", seed=3)
    assert len(effects) == 2
    assert sim.is_hidden_spec(" random:4 ; none")
    assert not sim.is_hidden_spec("paper")


# ----------------------------------------------------------------------------- spec parsing


def test_spec_forms(robots, tmp_path):
    robot = robots["rx160"]
    assert parse_effects(robot, "none") == []
    assert parse_effects(robot, "  ") == []
    effects = parse_effects(
        robot,
        " joint_offset:joint_2 = 1e-3 ;link_length:joint_3=0,0,5e-4; "
        "joint_eccentricity:joint_2=3e-4,-2e-4;thermal_expansion=1.2e-5",
    )
    assert [e.label for e in effects] == [
        "joint_offset:joint_2",
        "link_length:joint_3",
        "joint_eccentricity:joint_2",
        "thermal_expansion",
    ]
    assert effects[1].report_value() == [0.0, 0.0, 5e-4]
    assert effects[2].report_value() == [3e-4, -2e-4]
    # A truth JSON is a spec: the same effects and values.
    _, truth = simulate_campaign(robot, 10, effects, noise_mm=0.0)
    path = tmp_path / "t.truth.json"
    path.write_text(json.dumps(truth))
    again = effects_from_file(robot, path)
    assert [(e.label, e.report_value()) for e in again] == [
        (e.label, e.report_value()) for e in effects
    ]
    assert [e.label for e in parse_effects(robot, str(path))] == [e.label for e in effects]


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("joint_ofset:joint_2=1e-3", "known effects: axis_misalignment, backlash"),
        ("joint_offset:joint_9=1e-3", "joint_1, joint_2, joint_3"),
        ("joint_offset=1e-3", "needs a joint of rx160"),
        ("link_length:joint_3=0,5e-4", "takes 3 comma-separated values [m], got 2"),
        ("joint_eccentricity:joint_2=1e-3", "takes 2 comma-separated values [rad], got 1"),
        ("joint_offset:joint_2=1e-3,0", "takes one value [rad], got 2"),
        ("axis_misalignment:joint_5=1e-3,0,0,0", "takes 3 comma-separated values [rad], got 4"),
        ("axis_misalignment:joint_5=0,1e-3,0", "that is a joint_offset"),
        ("joint_offset:joint_2=abc", "'abc' is not a number"),
        ("joint_offset:joint_2", "no value; write joint_offset:JOINT=VALUE"),
        ("thermal_expansion:joint_2=1e-5", "not per joint"),
        ("backlash:joint_2=-1e-4", "must be >= 0"),
        ("random:0", "random:K with K >= 1"),
        ("joint_offset:joint_2=1e-3; joint_offset:joint_2=2e-3", "given twice"),
        ("missing_file.json", "no such file"),
    ],
)
def test_spec_errors_are_one_line(robots, spec, expected):
    with pytest.raises(hpk.HybridPKError) as info:
        parse_effects(robots["rx160"], spec)
    message = str(info.value)
    assert expected in message
    assert "\n" not in message


def test_campaign_argument_errors(robots):
    robot = robots["rx160"]
    with pytest.raises(hpk.HybridPKError, match="unknown trajectory 'spiral'"):
        simulate_campaign(robot, 5, "none", noise_mm=0.0, trajectory="spiral")
    with pytest.raises(hpk.HybridPKError, match="noise_mm must be"):
        simulate_campaign(robot, 5, "none", noise_mm=-1.0)
    with pytest.raises(hpk.HybridPKError, match="seed must be an integer >= 0"):
        simulate_campaign(robot, 5, "none", noise_mm=0.0, seed=-1)
    thermal = [make_effect(robot, "thermal_expansion", 1e-5)]
    with pytest.raises(hpk.HybridPKError, match="needs a temperature"):
        simulate_campaign(robot, 5, thermal, noise_mm=0.0, temperature_range=None)
    # beyond what the table reader takes back (grams, kelvin): refused here too
    with pytest.raises(hpk.HybridPKError, match="no arm carries more than 2300 kg"):
        simulate_campaign(robot, 5, "none", noise_mm=0.0, payload=5000.0)
    with pytest.raises(hpk.HybridPKError, match="LO <= HI <= 100"):
        simulate_campaign(robot, 5, "none", noise_mm=0.0, temperature_range=(290.0, 300.0))


# ----------------------------------------------------------------------------- CLI


def test_cli_writes_table_and_truth(tmp_path, capsys, robots):
    out = tmp_path / "campaign.parquet"
    argv = ["simulate", "rx160", "--n", "25", "--effects", "random:2", "--noise-mm", "0.01"]
    argv += ["--trajectory", "iso-cube", "--payload", "5", "--seed", "2", "--out", str(out)]
    assert main(argv) == 0
    stdout = capsys.readouterr().out
    truth = json.loads((tmp_path / "campaign.parquet.truth.json").read_text())
    assert "effects hidden; see" in stdout
    for e in truth["effects"]:  # hidden effects are not printed
        assert e["effect"] not in stdout
    assert (truth["n"], truth["trajectory"], len(truth["effects"])) == (25, "iso-cube", 2)
    # The table passes the reader's checks (limits, unit quaternions, degrees).
    data = read_table_for(out, robots["rx160"], n_params=None)
    assert data.n == 25
    assert data.has_orientation
    assert torch.all(data.payload == 5.0)
    assert_quats_close(data.quat, data.quat / data.quat.norm(dim=-1, keepdim=True), 1e-12)


@pytest.mark.parametrize("trajectory", ["iso-cube", "zigzag"])
def test_cli_noise_free_cube_campaign(tmp_path, capsys, trajectory):
    # one flange orientation and no noise: the frame check of the campaign met a rounding
    # -1e-30 of information over an error of ~0 and stopped with 'math domain error'
    argv = ["simulate", "ur10", "--n", "60", "--trajectory", trajectory, "--seed", "1"]
    assert main([*argv, "--no-progress", "--out", str(tmp_path / "c.csv")]) == 0
    assert "tool translation (all three components): not determined" in capsys.readouterr().out


def test_cli_notes_an_effect_beyond_credible_size(tmp_path, capsys):
    # before: "joint_offset:joint_2 = 5 rad" (degrees meant) passed without a word; the
    # diagnosis then called the model structurally wrong
    size = float(torch.empty(()).uniform_(0.1, 3.0))  # rad: beyond the 5 deg limit
    argv = ["simulate", "rx160", "--n", "20", "--no-progress", "--out", str(tmp_path / "x.csv")]
    argv += ["--effects", f"joint_offset:joint_2={size};gear_ratio:joint_3=3e-4"]
    assert main(argv) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "credibly" in line]
    assert notes == [
        f"note: joint_offset:joint_2 = {size:.4g} rad is beyond what such an effect can "
        "credibly be (0.0873 rad): a diagnosis of these rows reports the model as "
        "structurally wrong, not this as a cause"
    ], notes


def test_cli_bad_effects_exit_2_one_line(tmp_path, capsys):
    out = tmp_path / "x.csv"
    argv = ["simulate", "rx160", "--n", "5", "--effects", "joint_offset:joint_2=1,2"]
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "takes one value" in err
    assert not out.exists()


def test_cli_help_states_units(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for unit in ("[mm]", "[deg]", "[kg]", "[°C]"):
        assert unit in text


def test_hardening_spring_is_ground_truth_only():
    """Outside the vocabulary (no diagnosis offers it); softer near zero torque."""
    from hybrid_pk.effects import EFFECTS, Conditions
    from hybrid_pk.simulate.unmodelled import UNMODELLED_KINDS, HardeningCompliance

    robot = hpk.Robot.from_urdf("rx160")
    assert not set(UNMODELLED_KINDS) & set(EFFECTS)
    effect = HardeningCompliance(robot, "joint_2", 2e-6, tau0=50.0)
    q = robot.sample_q(64, torch.Generator().manual_seed(0))
    payload = torch.full((64,), 10.0, dtype=torch.float64)
    with torch.no_grad():
        tau = robot.gravity_torques(q, payload=payload)[:, 1]
        dq = effect.apply_q(q, Conditions(payload=payload)) - q
    expected = -2e-6 * 50.0 * torch.tanh(tau / 50.0)
    torch.testing.assert_close(dq[:, 1], expected, rtol=1e-12, atol=1e-15)
    assert float(dq[:, [0, 2, 3, 4, 5]].abs().max()) == 0.0
    # saturates at c tau0; near zero torque the slope is c
    assert float(dq[:, 1].abs().max()) <= 2e-6 * 50.0
    with pytest.raises(ValueError, match="tau0"):
        HardeningCompliance(robot, "joint_2", 1e-6, tau0=0.0)

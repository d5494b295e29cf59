"""Pose planning (issue 15): D-optimal choice of poses, its prediction checked against
real fits, joint tables, ``simulate --poses`` and the ``plan`` command."""

from __future__ import annotations

import json
import math

import pytest
import torch

from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.calibration.planning import (
    design_quality,
    plan_poses,
    pose_information,
    select_poses,
    travel_order,
)
from hybrid_pk.cli.main import main
from hybrid_pk.data.joint_table import read_joint_table, write_joint_table
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.errors import DataError, HybridPKError
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.trajectories import joint_box
from tests.dh_reader import erd_root

F64 = torch.float64
EFFECTS = ["joint_offset:joint_3", "joint_compliance:joint_2"]


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def plan(rx160):
    return plan_poses(rx160, 30, effects=EFFECTS, candidates=400, seed=3, payload=20.0)


# ----------------------------------------------------------------------------- the design


def test_plan_shapes_limits_and_determinism(rx160, plan):
    lo, hi = rx160.joint_limits
    assert plan.q.shape == (30, rx160.dof)
    assert plan.q_random.shape == (30, rx160.dof)
    assert bool(((plan.q >= lo) & (plan.q <= hi)).all())
    assert len(set(map(tuple, plan.q.tolist()))) == 30, "a pose was chosen twice"
    assert plan.names[0] == "base_frame.translation[0]"
    assert plan.names[-1] == EFFECTS[1]
    again = plan_poses(rx160, 30, effects=EFFECTS, candidates=400, seed=3, payload=20.0)
    assert torch.equal(again.q, plan.q)


def test_planned_poses_are_more_informative_than_random(plan):
    assert plan.planned.log_det > plan.random.log_det + 1.0
    # geometric mean of the predicted variances falls
    ratio = (plan.planned.std / plan.random.std).log().mean().exp()
    assert float(ratio) < 0.95


def test_exchange_never_lowers_the_greedy_determinant(rx160, plan):
    model = ExtendedModel(rx160, [make_effect(rx160, e) for e in EFFECTS])
    model.requires_grad_(False)
    blocks = plan.blocks
    gen = torch.Generator().manual_seed(0)
    lo, hi = rx160.joint_limits
    q = lo + torch.rand(300, rx160.dof, generator=gen, dtype=F64) * (hi - lo)
    cond = Conditions(payload=torch.full((300,), 20.0, dtype=F64))
    J = pose_information(model, q, cond, blocks, 0.02, 0.002)
    scale = torch.ones(J.shape[-1], dtype=F64)
    greedy, _ = select_poses(J, 20, max_passes=0)
    exchanged, swaps = select_poses(J, 20, max_passes=3)
    gain = design_quality(J[exchanged], scale).log_det - design_quality(J[greedy], scale).log_det
    assert swaps > 0  # the exchange did something here: the comparison is not of equals
    assert gain > 0, (swaps, gain)  # each swap it keeps raises the determinant


def test_prediction_matches_the_fit_covariance(rx160, plan):
    """The planned std is the std that the fit reports on a campaign at those poses."""
    data, _ = simulate_campaign(
        rx160, None, "none", poses=plan.q, noise_mm=0.02, noise_deg=0.002, payload=20.0,
        known_frames=True, temperature_range=None, seed=5,
    )  # fmt: skip
    model = ExtendedModel(rx160, [make_effect(rx160, e) for e in EFFECTS])
    cond = conditions_from_data(data)
    initialise_frames(model, data, cond)
    res = fit(model, data, cond=cond, sigma_pos_mm=0.02, sigma_rot_rad=math.radians(0.002))
    ratio = res.std / plan.planned.std
    # The same covariance up to one factor: the fit scales it by its a-posteriori
    # variance factor sqrt(chi2 / dof), a draw of the noise whose own spread is
    # 1 / sqrt(2 dof) (0.04 here); the plan uses the stated noise.
    assert float((ratio / ratio.mean() - 1).abs().max()) < 0.01, ratio
    dof = res.n_obs - res.n_params
    assert abs(float(ratio.mean()) - 1) < 3.5 / math.sqrt(2 * dof), (float(ratio.mean()), dof)


def test_predicted_position_error_matches_repeated_fits(rx160, plan):
    """The plan's RMS position error over the box is what fits at its poses show: the
    calibrated model against the truth at random poses of the box, over noise draws."""
    lo, hi = joint_box(rx160)
    q_test = lo + torch.rand(
        500, rx160.dof, generator=torch.Generator().manual_seed(9), dtype=F64
    ) * (hi - lo)
    cond_test = Conditions(payload=torch.full((500,), 20.0, dtype=F64))
    truth = ExtendedModel(rx160, [make_effect(rx160, e) for e in EFFECTS])
    truth.requires_grad_(False)
    with torch.no_grad():
        p_true = truth(q_test, cond_test)[:, :3, 3]
    squares = []
    for seed in range(12):
        data, _ = simulate_campaign(
            rx160, None, "none", poses=plan.q, noise_mm=0.02, noise_deg=0.002, payload=20.0,
            known_frames=True, temperature_range=None, seed=100 + seed,
        )  # fmt: skip
        model = ExtendedModel(rx160, [make_effect(rx160, e) for e in EFFECTS])
        cond = conditions_from_data(data)
        initialise_frames(model, data, cond)
        fit(model, data, cond=cond, sigma_pos_mm=0.02, sigma_rot_rad=math.radians(0.002))
        with torch.no_grad():
            err = 1e3 * (model(q_test, cond_test)[:, :3, 3] - p_true)
        squares.append(float(err.pow(2).sum(-1).mean()))
    observed = math.sqrt(sum(squares) / len(squares))
    # 12 draws of about 18 parameters: the observed RMS has a spread of about 5 %
    assert abs(observed / plan.planned.position_rms_mm - 1) < 0.2, (
        observed,
        plan.planned.position_rms_mm,
    )
    assert plan.random.position_rms_mm > 0


def test_unidentifiable_parameter_is_reported(rx160):
    # joint_1's offset turns the whole arm like the base frame's z rotation
    p = plan_poses(rx160, 12, effects=["joint_offset:joint_1"], candidates=100, seed=0)
    assert math.isinf(float(p.planned.std[-1]))
    assert math.isinf(float(p.random.std[-1]))


def test_joint_box_and_left_out_effects(rx160):
    box = {"joint_2": (-0.5, 0.5), "joint_3": (0.2, 1.0)}
    p = plan_poses(rx160, 10, effects=["thermal_expansion"], box=box, candidates=80, seed=1)
    for name, (a, b) in box.items():
        j = rx160.joint_names.index(name)
        assert bool(((p.q[:, j] >= a) & (p.q[:, j] <= b)).all())
        assert bool(((p.q_random[:, j] >= a) & (p.q_random[:, j] <= b)).all())
    assert [e for e, _ in p.left_out] == ["thermal_expansion"]
    assert p.names[-1] == "tool_frame.rotation[2]"  # frames only


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"box": {"elbow": (0.0, 1.0)}}, "unknown joint 'elbow'"),
        ({"box": {"joint_2": (5.0, 6.0)}}, "beyond its limits"),
        ({"candidates": 5}, "N <= candidates"),
        ({"criterion": "x"}, "unknown criterion"),
    ],
)
def test_plan_argument_errors(rx160, kwargs, message):
    with pytest.raises(HybridPKError, match=message):
        plan_poses(rx160, 10, **kwargs)


def test_travel_order_visits_every_pose_once():
    q = torch.rand(25, 6, generator=torch.Generator().manual_seed(2), dtype=F64)
    order = travel_order(q)
    assert sorted(order.tolist()) == list(range(25))
    path = (q[order][1:] - q[order][:-1]).abs().amax(-1).sum()
    shuffled = (q[1:] - q[:-1]).abs().amax(-1).sum()
    assert path < shuffled


# ----------------------------------------------------------------------------- files, CLI


def test_joint_table_round_trip_and_errors(tmp_path, rx160, plan):
    path = write_joint_table(tmp_path / "p.csv", plan.q, rx160.joint_names)
    q, rest = read_joint_table(path, rx160)
    assert torch.equal(q, plan.q)
    assert rest.shape[1] == 0
    text = path.read_text().splitlines()
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join([text[0], text[1], "0,0,abc,0,0,0"]) + "\n")
    with pytest.raises(DataError, match=r"bad.csv, row 2, column 'joint_3': text 'abc' in a"):
        read_joint_table(bad, rx160)
    bad.write_text("joint_1,joint_2,joint3,joint_4,joint_5,joint_6\n0,0,0,0,0,0\n")
    with pytest.raises(DataError, match=r"missing joint column\(s\) 'joint_3'.*found 'joint3'"):
        read_joint_table(bad, rx160)


def test_simulate_at_given_poses(rx160, plan):
    data, truth = simulate_campaign(rx160, None, "random:2", poses=plan.q, noise_mm=0.0, seed=4)
    assert torch.equal(data.q, plan.q.to(data.q.dtype))
    assert truth["trajectory"] == "poses"
    with pytest.raises(HybridPKError, match="30 poses"):
        simulate_campaign(rx160, 12, "none", poses=plan.q, noise_mm=0.0)


def test_plan_and_simulate_cli(tmp_path, capsys):
    poses, doc = tmp_path / "poses.csv", tmp_path / "plan.json"
    box = tmp_path / "box.json"
    box.write_text(json.dumps({"joint_5": [-1.0, 1.0]}))
    argv = ["plan", "rx160", "--n", "14", "--effects", "joint_offset:joint_2", "--candidates"]
    argv += ["150", "--joint-box", str(box), "--seed", "2", "--out", str(poses), "--json", str(doc)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "joint_offset:joint_2" in out
    assert "condition number" in out
    assert "14 random" in out
    plan_doc = json.loads(doc.read_text())
    assert len(plan_doc["parameters"]) == 13
    assert plan_doc["condition"]["planned"] > 1
    assert "position error over the box" in out
    assert 0 < plan_doc["position_rms_mm"]["planned"] < 1
    assert main(["simulate", "rx160", "--poses", str(poses), "--out", str(tmp_path / "m.csv")]) == 0
    assert "simulated 14 rows of rx160: poses of" in capsys.readouterr().out


def test_plan_cli_hint_runs_as_printed_on_a_urdf_of_several_leaves(tmp_path, capsys):
    """The printed ``simulate`` command names the chosen --end-link (UR5 of
    example-robot-data: leaves ee_link, base, tool0), so it runs as printed."""
    urdf = erd_root() / "ur_description" / "urdf" / "ur5_robot.urdf"
    poses = tmp_path / "poses.csv"
    argv = ["plan", str(urdf), "--end-link", "tool0", "--n", "8", "--candidates", "40"]
    assert main([*argv, "--seed", "0", "--out", str(poses), "--no-progress"]) == 0
    hint = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("measure them:"))
    command = hint.removeprefix("measure them: hybrid-pk ").split(" ... ")[0].split()
    assert main([*command, "--no-progress", "--out", str(tmp_path / "m.csv")]) == 0
    assert "simulated 8 rows of ur5" in capsys.readouterr().out


def test_plan_cli_errors_are_one_line(tmp_path, capsys):
    box = tmp_path / "box.json"
    box.write_text('{"joint_5": [1.0]}')
    base = ["plan", "rx160", "--n", "5", "--seed", "0", "--out", str(tmp_path / "p.csv")]
    assert main([*base, "--joint-box", str(box)]) == 2
    assert "must be [lower, upper]" in capsys.readouterr().err
    assert main([*base, "--effects", "joint_offset:elbow"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "elbow" in err


def test_plan_cli_warns_about_parameters_no_pose_separates(tmp_path, capsys):
    argv = ["plan", "rx160", "--n", "8", "--effects", "joint_offset:joint_1", "--candidates"]
    argv += ["40", "--seed", "0", "--out", str(tmp_path / "p.csv"), "--no-progress"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "not identifiable" in out
    assert "no poses separate base_frame.rotation[2], joint_offset:joint_1" in out


def test_a_joint_box_in_degrees_is_refused(tmp_path, capsys, rx160):
    """--joint-box {"joint_1": [-90, 90]}: degrees, beyond the joint's limits by far: a
    one-line error naming the limits and the unit (before: clipped to the limits without
    a word, so the plan spanned the whole range). A box a rounding beyond a limit (within
    the 2 % margin the box keeps) is clipped as before."""
    box = tmp_path / "box.json"
    base = ["plan", "rx160", "--n", "5", "--candidates", "40", "--seed", "0"]
    base += ["--out", str(tmp_path / "p.csv"), "--no-progress", "--joint-box", str(box)]
    box.write_text('{"joint_1": [-90, 90]}')
    assert main(base) == 2
    err = capsys.readouterr().err
    assert "reaches beyond its limits" in err, err
    assert "rad" in err
    assert str(box) in err, err  # the file named (before: only 'joint box: joint_1 ...')
    assert err.count("\n") == 1, err
    lo, hi = (float(x[0]) for x in rx160.joint_limits)
    box.write_text(json.dumps({"joint_1": [round(lo, 2) - 0.005, round(hi, 2) + 0.005]}))
    assert main(base) == 0


def test_a_truth_file_given_as_effects_names_its_effects(tmp_path, capsys):
    """plan --effects CAMPAIGN.truth.json (simulate's file, where a diagnosis is wanted):
    the error gives the truth's effects as the list to pass, or says they are hidden
    (before: only 'has no causes list of a diagnosis JSON file')."""
    for spec, want in (
        ("joint_offset:joint_2=1e-3", "its effects as a list are joint_offset:joint_2"),
        ("random:1", "whose effects are hidden"),
    ):
        out = tmp_path / "c.csv"
        argv = ["simulate", "rx160", "--n", "5", "--effects", spec, "--out", str(out)]
        assert main([*argv, "--no-progress"]) == 0
        capsys.readouterr()
        argv = ["plan", "rx160", "--n", "5", "--candidates", "40", "--seed", "0", "--out"]
        argv += [str(tmp_path / "p.csv"), "--effects", f"{out}.truth.json"]
        assert main(argv) == 2
        assert want in capsys.readouterr().err

"""The mimic-joint robot through the library and the command line: model file, corrected
URDF (mimic tags kept), simulate -> diagnose -> calibrate -> evaluate -> ik with the
robot's joints as the data's columns, and a hidden effect found on it."""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.blocked import practical_margin
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.calibration.diagnosis.variants import with_effects
from hybrid_pk.calibration.problem import Problem, param_blocks
from hybrid_pk.cli.main import main
from hybrid_pk.effects import EFFECTS, conditions_from_data
from hybrid_pk.io.hybrid_file import load_hybrid
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import RUN_SEED, run_rng

F64 = torch.float64
JOINTS = ["column_prismatic_joint", *(f"dsr_joint{i}" for i in range(1, 7))]
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def robot() -> hpk.Robot:
    robot = hpk.Robot.from_urdf("column_arm", end_link="tool0")
    robot.requires_grad_(False)
    return robot


def _model(robot) -> hpk.ExtendedModel:
    effects = [
        hpk.make_effect(robot, "link_length:column_top_joint", [0.001, -0.002, 0.0005]),
        hpk.make_effect(robot, "axis_misalignment:dsr_joint3", [0.002, 0.0, -0.001]),
        hpk.make_effect(robot, "link_length:dsr_joint5", [0.0, 0.001, 0.0]),
        hpk.make_effect(robot, "joint_offset:column_prismatic_joint", 0.003),
        hpk.make_effect(robot, "joint_offset:dsr_joint2", -0.002),
    ]
    return hpk.ExtendedModel(robot, effects)


def test_exported_urdf_keeps_mimic_tags_and_reproduces_the_model(robot, tmp_path):
    model = _model(robot)
    path = hpk.export_urdf(model, tmp_path / "cal.urdf", fold_joint_offsets=True)
    text = path.read_text(encoding="utf-8")
    assert text.count('<mimic joint="column_prismatic_joint"') == 2
    assert "joint_offset:column_prismatic_joint" in text  # listed in the header
    exported = hpk.Robot.from_urdf(path, end_link="tool0")
    assert exported.joint_names == robot.joint_names
    assert exported.chain_joint_names == robot.chain_joint_names
    q = robot.sample_q(64, torch.Generator().manual_seed(0))
    with torch.no_grad():
        worst = (exported.fk(q) - model.end_pose(q)).abs().max()
    assert float(worst) < 1e-12


def test_model_file_round_trip(robot, tmp_path):
    model = _model(robot)
    hpk.save_model(tmp_path / "m.pt", model)
    loaded = hpk.load_model(tmp_path / "m.pt").model
    assert loaded.robot.joint_names == JOINTS
    q = robot.sample_q(16, torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert torch.equal(loaded(q), model(q))


def _run(capsys, *argv) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out + captured.err


@pytest.mark.slow
def test_command_line_end_to_end(tmp_path, capsys):
    """simulate -> diagnose -> calibrate -> evaluate -> ik; the table holds the robot's
    7 joints (the cylinder, not the two mimic segments)."""
    sim = tmp_path / "campaign.csv"
    # the column head's shift between two prismatic segments is a base-frame shift
    effects = "joint_offset:dsr_joint3=1.5e-3;link_length:column_top_joint=0,1e-3,0"
    end = ("--end-link", "tool0")
    rc, out = _run(
        capsys, "simulate", "column_arm", *end, "--n", 300, "--effects", effects,
        "--noise-mm", 0.02, "--position-only", "--seed", 3, "--out", sim,
    )  # fmt: skip
    assert rc == 0, out
    table = pd.read_csv(sim)
    assert [c for c in table.columns if "joint" in c] == JOINTS

    diag = tmp_path / "diagnosis.json"
    rc, out = _run(capsys, "diagnose", sim, "--robot", "column_arm", *end, "--json", diag)
    assert rc == 0, out
    causes = json.loads(diag.read_text())["causes"]
    assert [(c["effect"], c["joint"]) for c in causes] == [("joint_offset", "dsr_joint3")]
    assert causes[0]["value"] == pytest.approx(1.5e-3, rel=0.2)

    model = tmp_path / "model.pt"
    rc, out = _run(
        capsys, "calibrate", sim, "--robot", "column_arm", *end, "--effects", diag, "--out", model
    )
    assert rc == 0, out
    assert (tmp_path / "model.pt.urdf").read_text().count("<mimic ") == 2

    report = tmp_path / "evaluation.json"
    rc, out = _run(capsys, "evaluate", model, sim, "--json", report)
    assert rc == 0, out
    assert json.loads(report.read_text())["position_mm"]["mean"] < 0.05

    targets = tmp_path / "targets.csv"
    table.head(3)[["x", "y", "z"]].to_csv(targets, index=False)
    solutions = tmp_path / "solutions.csv"
    rc, out = _run(capsys, "ik", model, targets, "--out", solutions, "--seeds", 16)
    assert rc == 0, out
    found = pd.read_csv(solutions)
    assert [c for c in found.columns if "joint" in c] == JOINTS
    assert sorted(found["target"].unique()) == [0, 1, 2]
    assert float(found["position_error_mm"].max()) < 1e-3


def test_train_with_the_default_inputs_reads_every_joint_and_says_why(tmp_path, capsys):
    """The default preset's physics inputs do not handle mimic joints yet: ``train``
    without --inputs trains on every joint (a note says so) instead of stopping; given
    explicitly, the physics inputs are refused with the reason."""
    sim, model, hybrid = tmp_path / "campaign.csv", tmp_path / "model.pt", tmp_path / "h.pt"
    end = ("--end-link", "tool0")
    rc, out = _run(
        capsys, "simulate", "column_arm", *end, "--n", 200, "--effects",
        "joint_offset:dsr_joint3=1.5e-3", "--noise-mm", 0.02, "--position-only", "--seed", 3,
        "--out", sim,
    )  # fmt: skip
    assert rc == 0, out
    rc, out = _run(capsys, "calibrate", sim, "--robot", "column_arm", *end, "--effects",
                   "none", "--out", model, "--no-urdf")  # fmt: skip
    assert rc == 0, out
    train = ("train", sim, "--model", model, "--epochs", 2, "--no-progress")
    rc, out = _run(capsys, *train, "--out", hybrid)
    assert rc == 0, out
    assert "note: 'column_arm' has mimic joints" in out
    assert "--inputs joints" in out
    assert load_hybrid(hybrid).input_label == "joints"
    given = tmp_path / "given.pt"
    rc, out = _run(capsys, *train, "--inputs", "frame1+torque", "--out", given)
    assert rc != 0
    assert "mimic joints" in out
    assert "Traceback" not in out
    assert not given.exists()


def _hidden(robot: hpk.Robot, rng: np.random.Generator) -> tuple[str, object]:
    """A random effect with a signature that no frame can take (unit size)."""
    kind = str(rng.choice(["joint_offset", "gear_ratio", "joint_compliance", "axis_misalignment"]))
    if kind == "axis_misalignment":
        label = f"{kind}:{rng.choice(['dsr_joint2', 'dsr_joint3', 'dsr_joint5'])}"
        basis = hpk.make_effect(robot, label).basis
        uv = rng.normal(size=2)
        return label, (torch.tensor(uv / np.linalg.norm(uv)) @ basis).tolist()
    joints = ["dsr_joint2", "dsr_joint3"] if kind == "joint_compliance" else JOINTS[2:6]
    sign = 1.0 if kind == "joint_compliance" else float(rng.choice([-1.0, 1.0]))
    return f"{kind}:{rng.choice(joints)}", sign


def _correction(robot: hpk.Robot, label: str, value, data) -> torch.Tensor:
    """The point motion [mm] of ``label`` at ``value`` on ``data``'s rows that the frames
    cannot absorb (linearised at the nominal robot, position only)."""
    trial = with_effects(hpk.ExtendedModel(robot, []), [hpk.make_effect(robot, label, value)])
    blocks = param_blocks(trial, None, True)
    problem = Problem(trial, data, conditions_from_data(data, False), blocks, 1.0, 1e-3)
    _, J = problem.jacobian(torch.zeros_like(problem.x0))
    J, k = J.detach(), blocks[-1].size
    theta = (problem.x0 / problem.scale)[-k:]  # the effect's parameters, scaled
    signal = J[:, -k:] @ theta
    frames = J[:, :-k]
    return signal - frames @ torch.linalg.lstsq(frames, signal[:, None]).solution[:, 0]


def _exact_stand_in(diag, named: dict, label: str) -> str | None:
    """The one named cause that the diagnosis reports as exactly alike ``label`` (its
    signature and the hidden one's at |cos| >= 0.9995, 1.0000 as printed: no data of
    this robot can tell them apart, e.g. a tilt of an origin about the line the joint
    before it turns about is that joint's offset); None otherwise."""
    if len(named) != 1:
        return None
    (other,) = named
    for entry in diag.ambiguous:
        cos = re.search(r"\|cos\| = ([0-9.]+)", entry.get("why", ""))
        if set(entry["effects"]) == {other, label} and cos and float(cos.group(1)) >= 0.9995:
            return other
    return None


def _carry_over_size(robot: hpk.Robot, label: str, value, data, noise_mm: float) -> float:
    """How many times ``value`` of ``label`` it takes to raise the campaign's RMS error
    (3-D, per row) by the diagnosis' practical margin once the frames have absorbed
    what they can: the smallest such effect the selection by what carries over can name
    (linearised; an in-sample estimate: at seed 12345 an effect of exactly this size
    gained 0.0028 mm on the blocked hold-out against the margin's 0.0021 mm)."""
    moved = float(_correction(robot, label, value, data).norm()) / data.n**0.5  # RMS [mm]
    noise = 3**0.5 * noise_mm  # the 3-D noise per row
    # RMS error with the effect: sqrt(noise^2 + s^2); it must exceed noise by the margin
    needed = ((noise + practical_margin(noise_mm)) ** 2 - noise**2) ** 0.5
    return needed / moved


def test_hidden_effect_on_the_mimic_robot(robot):
    """Kind, joint, sign and size drawn per run; 500 position-only rows, unknown frames.
    The size is drawn around the kind's typical scale but never below twice the size the
    practical margin requires (:func:`_carry_over_size`): a joint compliance of 0.5 x
    its scale moves the point of this arm by ~9 um after the frames (seed 12345), below
    what a 0.02 mm campaign of 500 rows can show out of sample."""
    rng = run_rng("mimic hidden effect")
    label, unit = _hidden(robot, rng)
    scale = EFFECTS[label.split(":")[0]].scale
    # 2-3 x the margin's size: the gain grows with the square of the size, so the
    # blocked gain is drawn 4-9 x the margin, room for its noise and extrapolation loss
    factor, above = float(rng.uniform(0.5, 2.0)), float(rng.uniform(2.0, 3.0))
    seed = int(rng.integers(1 << 30))
    noise_mm = 0.02
    # the joint draws come from their own stream: the same poses whatever the effect
    data, _ = simulate_campaign(
        robot, 500, "none", noise_mm=noise_mm, position_only=True, payload=5.0, seed=seed
    )
    unit_value = (np.asarray(unit) * scale).tolist()
    factor = max(factor, above * _carry_over_size(robot, label, unit_value, data, noise_mm))
    effect = hpk.make_effect(robot, label, (np.asarray(unit) * scale * factor).tolist())
    data, _ = simulate_campaign(
        robot, 500, [effect], noise_mm=noise_mm, position_only=True, payload=5.0, seed=seed
    )
    where = f"seed {RUN_SEED}: {label} = {effect.report_value()} ({factor:.2g} x its scale)"
    diag = diagnose(robot, data, seed=0)
    named = {f"{c.effect}:{c.joint}": c for c in diag.causes}
    other = _exact_stand_in(diag, named, label)
    if other is not None:  # named as what it is in this data; the same correction (20 %)
        truth = _correction(robot, label, effect.report_value(), data)
        made = _correction(robot, other, named[other].value, data)
        assert float((made - truth).norm()) < 0.2 * float(truth.norm()), f"{where}: {other}"
        return
    assert list(named) == [label], f"{where}: named {list(named)}; steps {diag.steps}"
    found = np.asarray(named[label].value, dtype=float)
    true = np.asarray(effect.report_value(), dtype=float)
    assert np.linalg.norm(found - true) < 0.2 * np.linalg.norm(true), f"{where}: found {found}"


def test_column_bending_of_the_mimic_column_is_named_within_20_percent(robot):
    """Acceptance: a position-only diagnosis of a simulated 500-row campaign of the
    mimic column with a column deflection names it, within 20 % of its value. Segment,
    bending direction, size (0.5-2 mm at the tool), payload and noise drawn per run."""
    if "column_bending" not in EFFECTS:  # phys's deflection effects, not on this branch yet
        pytest.skip("column_bending is not in the effect vocabulary of this checkout")
    rng = run_rng("mimic column bending")
    joint = str(rng.choice(["column_middle_joint", "column_top_joint"]))
    direction = np.abs(rng.normal(size=2)) + 0.2  # compliances about two axes: positive
    direction /= np.linalg.norm(direction)
    label = f"column_bending:{joint}"
    payload, noise = float(rng.uniform(0.0, 8.0)), float(rng.uniform(0.02, 0.05))
    # Probe at the effect's own scale (1e-6 rad/Nm/m), where the error is linear in it.
    scale = EFFECTS["column_bending"].scale
    unit = hpk.make_effect(robot, label, (direction * scale).tolist())
    _, probe = simulate_campaign(
        robot, 500, [unit], noise_mm=0.0, known_frames=True, payload=payload, seed=1
    )
    size = scale * float(rng.uniform(0.5, 2.0)) / probe["dataset_error"]["position_mm"]["mean"]
    effect = hpk.make_effect(robot, label, (direction * size).tolist())
    seed = int(rng.integers(1 << 30))
    data, _ = simulate_campaign(
        robot, 500, [effect], noise_mm=noise, position_only=True, payload=payload, seed=seed
    )
    where = f"seed {RUN_SEED}: {label} = {effect.report_value()}, noise {noise:.3f} mm"
    diag = diagnose(robot, data, seed=0)
    named = {f"{c.effect}:{c.joint}": c for c in diag.causes}
    assert label in named, f"{where}: named {list(named)}; ambiguous {diag.ambiguous}"
    found = np.asarray(named[label].value, dtype=float)
    true = np.asarray(effect.report_value(), dtype=float)
    err = np.linalg.norm(found - true) / np.linalg.norm(true)
    assert err < 0.2, f"{where}: found {found.tolist()} ({err:.0%} off)"

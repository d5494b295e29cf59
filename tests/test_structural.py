"""A cause is a small correction of the URDF (issue 11): implausible values and
frame-dominated signatures are never plain causes, and a structurally wrong URDF gets
the structural message with the joint and the size of the error, not a cause list."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.calibration.diagnosis.frame_share import determined_part, frame_share
from hybrid_pk.calibration.diagnosis.plausibility import implausibility
from hybrid_pk.calibration.diagnosis.split import split_campaign
from hybrid_pk.calibration.diagnosis.structural import (
    MAX_ROTATION_DEG,
    MAX_TRANSLATION_M,
    locate_structural_error,
)
from hybrid_pk.calibration.fit import fit
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import RUN_SEED, run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

URDF = Path(__file__).resolve().parents[1] / "urdf" / "rx160.urdf"
SHOULDER = '<origin xyz="0.15 0 0" rpy="0 0 0"/>'  # joint_2: the arm on the turret


def _turned_rx160(tmp_path: Path, rpy: str) -> Robot:
    """The RX160 whose arm is mounted on the turret turned by ``rpy`` (URDF rpy text)."""
    text = URDF.read_text()
    assert text.count(SHOULDER) == 1
    path = tmp_path / "rx160_turned.urdf"
    path.write_text(text.replace(SHOULDER, f'<origin xyz="0.15 0 0" rpy="{rpy}"/>'))
    robot = Robot.from_urdf(str(path))
    robot.requires_grad_(False)
    return robot


def test_values_beyond_a_small_correction_are_named(rx160):
    def check(label, value):
        return implausibility(make_effect(rx160, label, value), rx160)

    assert check("joint_offset:joint_3", math.radians(0.9 * MAX_ROTATION_DEG)) is None
    assert "rotation of 6°" in check("joint_offset:joint_3", math.radians(6.0))["why"]
    assert check("axis_misalignment:joint_2", [1.48, 0.0, 0.0]) is not None  # issue 11's 85°
    assert check("link_length:joint_3", [0.0, 0.0, 0.9 * MAX_TRANSLATION_M]) is None
    assert "translation of 60 mm" in check("link_length:joint_3", [0.06, 0.0, 0.0])["why"]
    assert check("gear_ratio:joint_2", 0.02) is not None
    assert check("backlash:joint_4", math.radians(2.0)) is not None
    assert "metal joints" in check("joint_compliance:joint_2", 2e-3)["why"]
    assert check("joint_compliance:joint_2", 2e-6) is None
    assert check("thermal_expansion", 2e-5) is None  # aluminium
    assert "thermal expansion of 0.003 1/K" in check("thermal_expansion", 3e-3)["why"]
    # a cobot's soft joint (5e-4 rad/Nm) is credible per Nm, but not under the RX160's
    # shoulder load: the bend it would make under the poses' gravity decides
    assert check("joint_compliance:joint_2", 5e-4) is None
    data, _ = simulate_campaign(rx160, 40, "none", noise_mm=0.0, seed=3, position_only=True)
    bent = implausibility(make_effect(rx160, "joint_compliance:joint_2", 5e-4), rx160, data)
    assert "would bend joint_2" in bent["why"]
    assert "metal" not in bent["why"]
    # a bearing's tilt likewise: per Nm credible, under the shoulder's moment not
    tilt = make_effect(rx160, "tilt_compliance:joint_2", [9e-4, 9e-4])
    assert implausibility(tilt, rx160) is None
    assert "would tilt joint_2" in implausibility(tilt, rx160, data)["why"]
    small = make_effect(rx160, "tilt_compliance:joint_2", [1e-6, 1e-6])
    assert implausibility(small, rx160, data) is None


def test_a_frame_change_dressed_as_a_link_length_is_mostly_the_frames(rx160):
    """A shift of joint 2's origin along the turret axis is a base translation; along
    the upper arm it is not."""
    data, truth = simulate_campaign(rx160, 80, "none", noise_mm=0.0, seed=2, position_only=True)
    cond = conditions_from_data(data)
    shares = {}
    for name, dp in (("vertical", [0.0, 0.0, 2e-3]), ("along x", [2e-3, 0.0, 0.0])):
        model = ExtendedModel(
            rx160,
            [make_effect(rx160, "link_length:joint_2", dp)],
            base=torch.tensor(truth["base_frame"], dtype=torch.float64),
            tool=torch.tensor(truth["tool_frame"], dtype=torch.float64),
        )
        shares[name] = frame_share(model, "link_length:joint_2", data, cond)[0]
    assert shares["vertical"] > 0.999
    assert shares["along x"] < 0.9


def test_the_frame_share_judges_only_the_components_the_rows_determine(rx160):
    """Sweep seed 818181: a shoulder misalignment's component about the vertical traded
    with the base frame to -3.3 mrad (std 7 mrad: undetermined) beside a 0.33 mrad
    component the rows pin down; 98 % of the whole value's displacement was the frames'
    and a real cause was withheld. Judged on what the rows determine, it is physical."""
    rng = run_rng("frame-share-determined")
    data, truth = simulate_campaign(rx160, 200, "none", noise_mm=0.0, seed=int(rng.integers(1e6)))
    cond = conditions_from_data(data)
    vertical = float(rng.uniform(2e-3, 5e-3)) * float(rng.choice([-1, 1]))  # [rad], traded
    across = float(rng.uniform(0.2e-3, 0.6e-3)) * float(rng.choice([-1, 1]))  # [rad], real
    label = "axis_misalignment:joint_2"
    model = ExtendedModel(
        rx160,
        [make_effect(rx160, label, [across, 0.0, vertical])],
        base=torch.tensor(truth["base_frame"], dtype=torch.float64),
        tool=torch.tensor(truth["tool_frame"], dtype=torch.float64),
    )
    v = model.effect(label).value.detach()  # on the effect's own basis
    std = torch.where(v.abs() > 1e-3, v.abs() * rng.uniform(0.4, 2.0), v.abs() / 50)
    why = f"HYBRID_PK_TEST_SEED={RUN_SEED}, across {across}, vertical {vertical}, std {std}"
    whole = frame_share(model, label, data, cond)[0]
    determined = frame_share(model, label, data, cond, std.tolist())[0]
    assert whole > 0.9, why  # the old reading: mostly the frames
    assert determined < 0.2, why  # the determined component moves the points itself
    assert determined_part(model.effect(label), (v.abs() / 50).tolist()) is None  # all kept
    assert frame_share(model, label, data, cond, (v.abs()).tolist())[0] == 0.0  # none: 0


@pytest.mark.slow
def test_an_arm_mounted_turned_by_90_degrees_gets_the_structural_message(tmp_path, capsys):
    """Acceptance of issue 11: the campaign of an RX160 whose arm sits on the turret
    turned by 90° (URDF untouched) gets the structural message at joint_2, not causes."""
    turned = _turned_rx160(tmp_path, "0 0 1.5707963267948966")
    data, _ = simulate_campaign(turned, 150, "none", noise_mm=0.05, noise_deg=0.005, seed=1)
    table = tmp_path / "turned.csv"
    write_table(table, data)
    out_json = tmp_path / "diag.json"
    report = tmp_path / "report"
    rc = main(["diagnose", str(table), "--robot", "rx160", "--json", str(out_json),
               "--report", str(report)])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0
    doc = json.loads(out_json.read_text())
    assert doc["causes"] == []
    structural = doc["structural"]
    assert structural["structurally_wrong"]
    assert structural["location"]["joint"] == "joint_2"
    assert structural["location"]["holdout_mean_mm_after"] < 0.2  # [mm], noise level
    # the turret turns the arm about the vertical, not about joint_2's own axis (y)
    assert structural["location"]["joint_zero_deg"] is None
    assert "its zero is off" not in out
    assert doc["nominal"]["position_mm"]["mean"] > 100.0
    assert "causes: withheld, the URDF looks structurally wrong" in out
    assert "structural: the URDF looks structurally wrong at joint_2" in out
    # the search stopped on two implausible candidates: which, why, the rest untested
    stops = [w for w in doc["warnings"] if "the search stopped after 2" in w["why"]]
    assert len(stops) == 1, doc["warnings"]
    assert "not a small correction of the URDF" in stops[0]["why"], stops
    assert "candidates after them were not tested" in stops[0]["why"], stops
    text = (report / "report.md").read_text()
    assert "## The URDF looks structurally wrong" in text
    assert "Withheld: the URDF looks structurally wrong" in text


@pytest.mark.slow
def test_a_large_joint_offset_is_reported_as_a_wrong_urdf_not_as_a_cause(rx160):
    """An 11° offset of joint 3 is statistically obvious but no calibration error: the
    diagnosis says the URDF is wrong at joint_3 by that much, and lists no cause."""
    data, _ = simulate_campaign(rx160, 150, "joint_offset:joint_3=0.2", noise_mm=0.05,
                                noise_deg=0.005, seed=3)  # fmt: skip
    result = diagnose(rx160, data)
    assert result.causes == []
    structural = result.structural
    assert structural["structurally_wrong"]
    assert [f["cause"] for f in structural["findings"]][:1] == ["joint_offset:joint_3"]
    location = structural["location"]
    assert location["joint"] == "joint_3"
    assert location["rotation_deg"] == pytest.approx(math.degrees(0.2), rel=0.02)
    assert abs(location["rotation_axis"][1]) > 0.99  # about joint 3's own axis (y)
    # so it is joint 3's zero: the commanded values lack the 0.2 rad the campaign added
    assert location["joint_zero_deg"] == pytest.approx(math.degrees(0.2), rel=0.02)
    assert "its zero is off by +11.46° " in structural["message"], structural["message"]


def test_the_evidence_plot_of_a_link_length_shows_its_physical_signature(rx160):
    """A shift of joint 2's origin of (0.5, 0, 3) mm: its vertical 3 mm are a base
    translation (the frame trade-off); the evidence shows the 0.5 mm that only the link
    length makes, on a slope-1 line."""
    from hybrid_pk.calibration.diagnosis import Cause
    from hybrid_pk.report.evidence import cause_evidence

    truth = [make_effect(rx160, "link_length:joint_2", [5e-4, 0.0, 3e-3])]
    data, sim = simulate_campaign(rx160, 120, truth, noise_mm=0.005, seed=5, position_only=True)
    model = ExtendedModel(
        rx160,
        [make_effect(rx160, "link_length:joint_2", [5e-4, 0.0, 3e-3])],
        base=torch.tensor(sim["base_frame"], dtype=torch.float64),
        tool=torch.tensor(sim["tool_frame"], dtype=torch.float64),
    )
    cause = Cause("link_length", "joint_2", [5e-4, 0.0, 3e-3], "m", [1e-5] * 3, 1.0, None, "")
    ev = cause_evidence(cause, data, model)
    assert float(abs(ev.x).max()) < 1.0  # [mm]: the 0.5 mm signature, not the 3 mm shift
    assert float(abs(ev.x).max()) > 0.3
    slope = float((ev.x * ev.y).sum() / (ev.x * ev.x).sum())
    assert slope == pytest.approx(1.0, abs=0.05)


def test_calibrate_does_not_let_a_large_value_pass_for_a_cause(rx160, tmp_path, capsys):
    data, _ = simulate_campaign(rx160, 60, "joint_offset:joint_3=0.2", noise_mm=0.05,
                                noise_deg=0.005, seed=4)  # fmt: skip
    table = tmp_path / "offset.csv"
    write_table(table, data)
    rc = main(["calibrate", str(table), "--robot", "rx160", "--effects", "joint_offset:joint_3",
               "--no-urdf", "--out", str(tmp_path / "m.pt")])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0
    assert "warning: joint_offset:joint_3: a rotation of 11.5° is beyond" in out
    assert "the URDF is wrong there" in out


def test_rows_of_a_larger_sibling_robot_name_no_cause_and_say_so(rx160, tmp_path):
    """Rows of an arm 30 % larger than the URDF (every origin scaled: a sibling model,
    as a UR5's rows given the UR10's URDF) and a random temperature span: a uniform
    stretch is exactly a thermal expansion of 0.3 / (T - 20 °C), which was named as a
    cause (-0.04 1/K and the like). It is no small correction: nothing is named, and the
    structural message says the rows may not be this URDF's robot."""
    text = URDF.read_text()
    scaled = re.sub(
        r'xyz="([^"]+)"',
        lambda m: 'xyz="' + " ".join(f"{1.3 * float(v):.6g}" for v in m.group(1).split()) + '"',
        text,
    )
    path = tmp_path / "rx160_larger.urdf"
    path.write_text(scaled)
    larger = Robot.from_urdf(str(path))
    larger.requires_grad_(False)
    data, _ = simulate_campaign(larger, 400, "none", noise_mm=0.02, noise_deg=0.002, seed=RUN_SEED)
    result = diagnose(rx160, data).to_json()
    assert result["causes"] == [], result["causes"]
    found = [f["cause"] for f in result["structural"]["findings"]]
    assert "thermal_expansion" in found, found
    assert "not this URDF's robot" in result["structural"]["message"]


def test_an_offset_is_named_at_its_joint_not_as_the_next_joints_turn_and_move(rx160):
    """An offset d at joint_2 is exactly a full origin correction of joint_3 (its origin
    turned by d about joint_2's axis and moved by R(d) p - p, the 825 mm upper arm): a
    hint at joint_3 explained the error there, and the search named joint_3 with a
    move of a hundred-odd mm. The joint before predicts the hold-out as well with a
    smaller move: it is named (sweep seed 424242 of tests/test_budget.py). Its move is
    the rows' noise: at sweep seed 141414 it was reported as 37 mm, a move of joint 2's
    origin along joint 1's axis that is exactly a base translation (the structural fits
    hold no frame prior); the reported move leaves such directions out."""
    rng = run_rng("structural joint before")
    offset = float(rng.uniform(0.15, 0.3)) * float(rng.choice([-1.0, 1.0]))  # [rad]
    data, _ = simulate_campaign(rx160, 150, f"joint_offset:joint_2={offset}", noise_mm=0.05,
                                noise_deg=0.005, seed=int(rng.integers(1000)))  # fmt: skip
    split = split_campaign(data, conditions_from_data(data), 0.2, 0)
    nominal = ExtendedModel(rx160)
    initialise_with_priors(nominal, split.train, split.cond_fit, None)
    res = fit(nominal, split.train, cond=split.cond_fit)
    sigmas = (res.sigma_pos_mm, res.sigma_rot_rad)
    found = locate_structural_error(nominal, split, sigmas, hint=["joint_3"])
    lever_mm = 1e3 * float(np.linalg.norm(rx160.spec.origins[2][:3, 3]))  # joint_3's origin
    next_move = 2 * abs(math.sin(offset / 2)) * lever_mm  # what joint_3's correction moves
    assert found["joint"] == "joint_2", (offset, found)
    assert found["translation_mm"] < next_move, (offset, found, next_move)
    # an offset moves no origin: 0.02-0.6 mm at seeds 1-8, 141414, 424242 (0.05 mm noise)
    assert found["translation_mm"] < 1.0, (offset, found)
    assert abs(found["rotation_deg"] - math.degrees(abs(offset))) < 0.05, (offset, found)
    # all of it about joint_2's own axis: the joint's zero, with the offset's sign
    assert abs(found["joint_zero_deg"] - math.degrees(offset)) < 0.05, (offset, found)

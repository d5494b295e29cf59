"""A set-up transfer: the lifting-column arm calibrated standing upright, re-stationed on
an 8° tilted base (issue 27). Only the base frame is re-fitted, on rows of one flange
orientation (a total station's stationing); gravity comes from the levelled instrument
(``--gravity level-tracker``), so the calibrated compliance follows the tilt. The
campaign and the commands are ``experiments/restation.py``'s."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.restation import restation
from tests.helpers import RUN_SEED, run_rng

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]

# The construction robot: nominal + frames 10.07 mm at a noise of 0.75 mm, some
# 13 sigma; the effects at scale 1 give 1-3 mm, so 0.1 mm keeps that regime (a ratio of
# 0.3 needs a noise floor well under 0.3x the nominal error).
NOISE_MM = 0.1
N_CALIBRATION = 600


def test_restationed_on_a_tilted_base(tmp_path):
    """Either outcome passes, each checked: the extended model carries to the tilted
    set-up with at most 0.3 of nominal + frames' error, or (a draw whose unmodelled
    spring is a large share of a small error) the hidden physics is named, each value
    within 10 %, and carries at least as well as the hidden vocabulary effects at
    their true values (the spring left out)."""
    r = restation(lambda: run_rng("restation"), RUN_SEED % 1000, tmp_path, 1.0, NOISE_MM,
                  N_CALIBRATION)  # fmt: skip
    print(f"re-stationed at 8 deg: {r} (seed {RUN_SEED})")
    assert np.isfinite(r["ratio"])
    if r["ratio"] <= 0.3:
        return
    # A draw whose unmodelled spring is a large share of a small error (seed 404: 1.06 mm
    # nominal + frames, 0.33 mm left) cannot reach 0.3 with any vocabulary model: then
    # the hidden physics must be what was named, and carry better than it does alone.
    for label, value in r["hidden"].items():
        assert label in r["named"], (r, RUN_SEED)
        assert abs(r["named"][label] / value - 1) < 0.1, (label, r, RUN_SEED)
    assert r["extended"] <= r["truth"], (r, RUN_SEED)


def test_a_soft_joint_carries_to_the_tilted_set_up_at_the_construction_robots_noise(tmp_path):
    """The issue's construction robot: 0.75 mm noise, 444 rows, nominal + frames some ten
    times the noise (the effects at 4x: 6-24 mm), the loaded joint as soft as a cobot's
    (1e-4 .. 2.6e-4 rad/Nm). Its compliance is named (within 10 %), so the model follows
    the tilt; with the old 1e-4 rad/Nm limit it was flagged, the search stopped, and the
    ratio was 0.56 (median of 15 seeds, up to 1.0; today 0.105, at most 0.40:
    ``python experiments/restation.py --scale 4 --noise 0.75 --rows 444 --seeds 1-15``)."""
    r = restation(lambda: run_rng("restation-x4"), RUN_SEED % 1000, tmp_path, 4.0, 0.75, 444)
    print(f"construction robot's regime: {r} (seed {RUN_SEED})")
    soft = next(label for label in r["hidden"] if label.startswith("joint_compliance"))
    assert soft in r["named"], (r, RUN_SEED)
    assert abs(r["named"][soft] / r["hidden"][soft] - 1) < 0.1, (r, RUN_SEED)
    assert r["ratio"] <= 0.5, (r, RUN_SEED)


def test_a_tilted_re_stationing_names_a_fixed_mounting(tmp_path, capsys):
    """Calibrated with gravity fixed in the robot frame (the default), a model whose
    compliance cannot follow a re-stationing: the re-fit says how far the base tilted
    and that ``--gravity level-tracker`` would follow it; with it, no note."""
    import torch

    import hybrid_pk as hpk
    from hybrid_pk.cli.main import main
    from hybrid_pk.data import write_table
    from hybrid_pk.simulate import simulate_campaign
    from hybrid_pk.simulate.mounting import parse_mount

    robot = hpk.Robot.from_urdf("column_arm", end_link="tool0")
    robot.requires_grad_(False)
    soft = [hpk.make_effect(robot, "joint_compliance:dsr_joint2", 5e-5)]
    kw = {"noise_mm": 0.1, "position_only": True, "temperature_range": None}
    upright, truth = simulate_campaign(robot, 300, soft, mount=parse_mount("floor"), seed=1, **kw)
    tool = torch.tensor(truth["tool_frame"], dtype=torch.float64)  # the same prism
    tilted, _ = simulate_campaign(
        robot, 80, soft, mount=parse_mount("tilt:8"), seed=2, tool=tool, **kw
    )
    cal, moved = (
        write_table(tmp_path / "cal.csv", upright),
        write_table(tmp_path / "st.csv", tilted),
    )
    notes = {}
    for gravity in ([], ["--gravity", "level-tracker"]):
        model = tmp_path / f"m{len(gravity)}.pt"
        argv = ["calibrate", str(cal), "--robot", "column_arm", "--end-link", "tool0",
                "--effects", "joint_compliance:dsr_joint2", "--out", str(model), "--no-urdf",
                *gravity]  # fmt: skip
        assert main(argv) == 0
        capsys.readouterr()
        argv = ["calibrate", str(moved), "--model", str(model), "--refit", "base",
                "--out", str(tmp_path / "r.pt"), "--no-urdf"]  # fmt: skip
        assert main(argv) == 0
        notes[bool(gravity)] = [ln for ln in capsys.readouterr().out.splitlines() if "note:" in ln]
    assert len(notes[False]) == 1, notes
    assert "tilts the robot by 8.0 deg" in notes[False][0], notes
    assert "--gravity level-tracker" in notes[False][0], notes
    assert notes[True] == [], notes

"""A set-up transfer: the lifting-column arm calibrated standing upright, re-stationed on
an 8° tilted base (issue 27). Only the base frame is re-fitted, on rows of one flange
orientation (a total station's stationing); gravity comes from the levelled instrument
(``--gravity level-tracker``), so the calibrated compliance follows the tilt."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.ik import solve_ik
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.simulate.mounting import parse_mount
from hybrid_pk.simulate.unmodelled import HardeningCompliance, rms_gravity_torques
from tests.helpers import RUN_SEED, run_rng

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]

ROBOT = "column_arm"
TILT = "tilt:8"
# The construction robot: nominal + frames 10.07 mm at a noise of 0.75 mm, some
# 13 sigma; the effects below give 1-3 mm, so 0.1 mm keeps that regime (a ratio of 0.3
# needs a noise floor well under 0.3x the nominal error).
NOISE_MM = 0.1
N_CALIBRATION = 600
N_STATION = 80  # the stationing rows
N_JUDGED = 400
# A joint is gravity-loaded when its RMS holding torque exceeds this [Nm]: a 1-3 mrad
# sag then needs under 1e-4 rad/Nm, the largest compliance the diagnosis lists as a small
# correction.
LOADED_NM = 20.0


def _robot() -> hpk.Robot:
    robot = hpk.Robot.from_urdf(ROBOT, end_link="tool0")
    robot.requires_grad_(False)
    return robot


def _hidden(robot, rng, gravity) -> tuple[list, str]:
    """A compliance of one loaded joint (1-3 mrad RMS sag) and an offset of a random arm
    joint before the wrist (2-5 mrad), the sizes of the rotations named on the issue's
    construction robot (nominal + frames then errs some ten times the noise), and the
    unmodelled hardening spring on another loaded joint (0.5-1 mrad saturated), under
    ``gravity`` (root frame)."""
    rms = rms_gravity_torques(robot, 0.0, torch.Generator().manual_seed(0))
    names = list(robot.joint_names)
    revolute = [t == "revolute" for t in robot.joint_types]
    loaded = [n for n, t, r in zip(names, rms, revolute, strict=True) if r and t > LOADED_NM]
    soft, spring = (str(n) for n in rng.choice(loaded, 2, replace=False))
    c = rng.uniform(1e-3, 3e-3) / float(rms[names.index(soft)])
    offset = str(rng.choice(names[2:5]))
    sign = float(rng.choice([-1, 1]))
    effects = [
        hpk.make_effect(robot, f"joint_compliance:{soft}", c),
        hpk.make_effect(robot, f"joint_offset:{offset}", sign * rng.uniform(2e-3, 5e-3)),
    ]
    tau0 = 0.4 * float(rms[names.index(spring)])  # the demo's knee (UNMODELLED_KNEE)
    deflection = rng.uniform(5e-4, 1e-3)
    extra = HardeningCompliance(robot, spring, deflection / tau0, tau0, gravity=gravity)
    return [*effects, extra], f"compliance {soft} {c:.3g}, offset {offset}, spring {spring}"


def _one_orientation(robot, n: int, rng) -> torch.Tensor:
    """Joints of ``n`` flange positions within ±0.6 m of a middle pose, all with its
    flange orientation (nominal IK; the first ``n`` reachable of ``5 n`` drawn): spread
    over the workspace as a stationing is, so that the base rotation is not read off a
    small patch (where an error of the model there would tilt the whole set-up)."""
    lo, hi = robot.joint_limits
    q0 = (lo + hi) / 2 + 0.25 * (hi - lo) * torch.as_tensor(rng.uniform(-0.5, 0.5, lo.shape[0]))
    T0 = robot.fk(q0[None])[0]
    targets = T0.expand(5 * n, 4, 4).clone()
    targets[:, :3, 3] += torch.as_tensor(rng.uniform(-0.6, 0.6, (5 * n, 3)))
    res = solve_ik(robot, targets, seeds=4, extra_seeds=q0)
    keep = res.valid[:, 0]
    assert int(keep.sum()) >= n, f"only {int(keep.sum())} stationing poses reachable"
    return res.q[keep, 0][:n]


def test_restationed_on_a_tilted_base(tmp_path, capsys):
    rng = run_rng("restation")
    robot = _robot()
    upright, tilted = parse_mount("floor"), parse_mount(TILT)
    effects, what = _hidden(robot, rng, upright.gravity_root.tolist())
    cal, truth = simulate_campaign(
        robot, N_CALIBRATION, effects, noise_mm=NOISE_MM, position_only=True,
        temperature_range=None, mount=upright, seed=RUN_SEED % 1000,
    )  # fmt: skip
    station_q = _one_orientation(robot, N_STATION, rng)
    judged_q = robot.sample_q(N_JUDGED, torch.Generator().manual_seed(RUN_SEED % 1000 + 1))
    effects_tilted, _ = _hidden(robot, run_rng("restation"), tilted.gravity_root.tolist())
    moved, _ = simulate_campaign(
        robot, None, effects_tilted, poses=torch.cat([station_q, judged_q]), noise_mm=NOISE_MM,
        position_only=True, temperature_range=None, mount=tilted, seed=RUN_SEED % 1000 + 2,
        tool=torch.tensor(truth["tool_frame"], dtype=torch.float64),
    )  # fmt: skip
    n_station = station_q.shape[0]
    files = {
        "cal": write_table(tmp_path / "upright.csv", cal),
        "station": write_table(tmp_path / "station.csv", moved.subset(slice(0, n_station))),
        "judged": write_table(tmp_path / "judged.csv", moved.subset(slice(n_station, None))),
    }
    errors = {}
    for name, spec in (("nominal", "none"), ("extended", "auto")):
        model, refit, out = (tmp_path / f"{name}{s}.pt" for s in ("", "_moved", ""))
        cmds = [
            ["calibrate", files["cal"], "--robot", ROBOT, "--end-link", "tool0", "--effects",
             spec, "--gravity", "level-tracker", "--out", model, "--no-urdf"],
            ["calibrate", files["station"], "--model", model, "--refit", "base", "--out", refit,
             "--no-urdf"],
            ["evaluate", refit, files["judged"], "--json", out.with_suffix(".json")],
        ]  # fmt: skip
        for argv in cmds:
            assert main([str(a) for a in argv]) == 0, (argv, capsys.readouterr().out[-2000:])
        errors[name] = json.loads(out.with_suffix(".json").read_text())["position_mm"]["mean"]
    ratio = errors["extended"] / errors["nominal"]
    print(f"re-stationed at 8 deg: {errors}, ratio {ratio:.3f} ({what}, seed {RUN_SEED})")
    assert np.isfinite(ratio)
    assert ratio <= 0.3, (errors, ratio, what, RUN_SEED)

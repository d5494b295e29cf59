"""Frame components the data cannot determine stay at the end link's origin (issue 28):
a re-stationed campaign whose flange orientation spans < 0.1°, the instrument 10 m from
the robot, position only. The data cannot separate tool and base translation; what
they leave open stays at the end link (or at ``--tool``), in every fit."""

from __future__ import annotations

import math

import pytest
import torch

from hybrid_pk.calibration.fit import fit, model_errors
from hybrid_pk.calibration.frames import FramePriors, FrameSpec
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.effects import ExtendedModel, conditions_from_data
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.io.model_file import load_model
from tests.degenerate import measure, wrist_configs
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
NOISE_MM = 0.5  # a total station's point noise
FRAMES = ["base_frame.translation", "base_frame.rotation", "tool_frame.translation"]


@pytest.fixture(scope="module")
def stationing(rx160):
    """80 fit rows at one flange orientation (span 0.08°), 200 rows of the same set-up
    with the flange turned by up to 60°; the measured point is the end link's origin
    and the instrument stands 10 m from the robot's root at a random azimuth."""
    rng = run_rng("stationing")
    gen = torch.Generator().manual_seed(int(rng.integers(2**31)))
    azimuth = float(rng.uniform(0, 2 * math.pi))
    yaw = float(rng.uniform(-math.pi, math.pi))
    p = torch.tensor([10 * math.cos(azimuth), 10 * math.sin(azimuth), 1.5], dtype=F64)
    base = transform(so3_exp(torch.tensor([0.0, 0.0, yaw], dtype=F64)), -p)
    tool = torch.eye(4, dtype=F64)
    lo = torch.tensor([-0.8, -0.3, 0.8, -1.0, -1.0, -1.0], dtype=F64)
    hi = torch.tensor([0.8, 0.5, 2.0, 1.0, 1.0, 1.0], dtype=F64)
    fit_q = wrist_configs(rx160, 80, lo, hi, 0.08, gen)
    other_q = wrist_configs(rx160, 200, lo, hi, 60.0, gen)
    cal = measure(rx160, fit_q, [], base, tool, NOISE_MM, gen)
    other = measure(rx160, other_q, [], base, tool, 0.0, gen)
    return cal, other


def _fit(robot, data, priors=None):
    model = ExtendedModel(robot)
    cond = conditions_from_data(data)
    initialise_with_priors(model, data, cond, priors)
    res = fit(model, data, free=FRAMES, cond=cond, frames=priors)
    return model, res


@pytest.mark.parametrize("given", [False, True])
def test_the_tool_stays_at_the_end_link_whatever_the_base(rx160, stationing, given):
    cal, other = stationing
    priors = FramePriors(tool=FrameSpec(torch.zeros(3, dtype=F64))) if given else None
    model, res = _fit(rx160, cal, priors)
    tool_mm = 1e3 * float(model.tool.matrix()[0, :3, 3].detach().norm())
    assert tool_mm < 1.0, (tool_mm, res.frame_report.lines())
    err = model_errors(model, other)[0]
    # within the campaign's noise: the rms 3-D error of a row is sqrt(3) x the noise
    assert float(err.pow(2).mean().sqrt()) < math.sqrt(3) * NOISE_MM, float(err.max())


def test_calibrate_keeps_the_tool_at_the_end_link_with_or_without_tool(
    rx160, stationing, tmp_path, capsys
):
    """The CLI: ``calibrate --effects none`` with and without ``--tool 0,0,0``."""
    cal, other = stationing
    write_table(tmp_path / "station.csv", cal)
    models = []
    for extra in ([], ["--tool", "0,0,0"]):
        out = tmp_path / f"m{len(extra)}.pt"
        argv = ["calibrate", tmp_path / "station.csv", "--robot", "rx160", "--effects", "none"]
        rc = main([str(a) for a in [*argv, *extra, "--no-urdf", "--out", out]])
        assert rc == 0, capsys.readouterr().err
        models.append(load_model(out).model)
    for model in models:
        assert 1e3 * float(model.tool.matrix()[0, :3, 3].detach().norm()) < 1.0
        err = model_errors(model, other)[0]
        assert float(err.pow(2).mean().sqrt()) < math.sqrt(3) * NOISE_MM

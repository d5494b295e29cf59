"""Quaternions written in another convention are refused after the frame fit, naming
the reading that fits (hybrid_pk.calibration.conventions).

Before, 400 rows of the shared UR10's Series B with their quaternions inverted (or in
the order x y z w) were diagnosed without a word: orientations off by 30.7° (144.7°)
after the frame fit, no cause named (six causes named); `python
experiments/row_checks.py --out DIR`."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.conventions import READINGS
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.pipelines.calibration import calibrate
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

LABEL = "joint_offset:joint_3"


def _campaign(robot, rng) -> hpk.MeasuredData:
    data, _ = hpk.simulate_campaign(
        robot, 200, f"{LABEL}=4e-4", noise_mm=0.02, noise_deg=0.002,
        seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    return data


def _written(data: hpk.MeasuredData, k: int) -> hpk.MeasuredData:
    """``data`` with its quaternions as a table in reading ``k`` holds them: each reading
    applied to that table gives them back (inverse and reorder are undone by their own
    inverse operations)."""
    q = data.quat
    if k == 0:
        stored = q * q.new_tensor([1.0, -1.0, -1.0, -1.0])
    elif k == 1:
        stored = q[:, [1, 2, 3, 0]]
    else:
        stored = (q * q.new_tensor([1.0, -1.0, -1.0, -1.0]))[:, [1, 2, 3, 0]]
    assert torch.allclose(READINGS[k][1](stored), q)
    return dataclasses.replace(data, quat=stored)


def test_each_other_convention_is_refused_and_named(rx160):
    rng = run_rng("conventions")
    data = _campaign(rx160, rng)
    for k, (reading, _) in enumerate(READINGS):
        with pytest.raises(hpk.DataError) as err:
            hpk.diagnose(rx160, _written(data, k), candidates=[LABEL])
        text = str(err.value)
        assert f"read as {reading} they miss by" in text, text
        assert "convert them, or leave them out" in text
    with pytest.raises(hpk.HybridPKError, match="read as their inverse"):
        calibrate(rx160, _written(data, 0), [LABEL])
    diag = hpk.diagnose(rx160, data, candidates=[LABEL])  # the table's own convention
    assert [c.effect for c in diag.causes] == ["joint_offset"]
    assert diag.nominal["orientation_deg"]["mean"] < 1


def test_orientations_no_reading_explains_are_not_called_a_convention(rx160):
    """Quaternions that fit no reading (a scrambled column) are beyond 5° too, but the
    check does not blame a convention: the diagnosis goes on."""
    rng = run_rng("conventions-scrambled")
    data = _campaign(rx160, rng)
    perm = torch.as_tensor(rng.permutation(data.n))
    scrambled = dataclasses.replace(data, quat=data.quat[perm])
    diag = hpk.diagnose(rx160, scrambled, candidates=[LABEL])
    assert diag.nominal["orientation_deg"]["mean"] > 5


def test_the_cli_says_it_in_one_line(rx160, tmp_path, capsys):
    rng = run_rng("conventions-cli")
    path = tmp_path / "inverse.csv"
    hpk.write_table(path, _written(_campaign(rx160, rng), 0))
    out = tmp_path / "diag.json"
    argv = ["diagnose", str(path), "--robot", "rx160", "--json", str(out), "--no-progress"]
    assert hybrid_pk([*argv, "--candidates", LABEL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("hybrid-pk diagnose: error: the measured orientations miss"), err
    assert not out.exists()


def test_evaluate_with_fit_frames_warns_and_still_reports(rx160, tmp_path, capsys):
    rng = run_rng("conventions-evaluate")
    path = tmp_path / "xyzw.csv"
    hpk.write_table(path, _written(_campaign(rx160, rng), 1))
    argv = ["evaluate", "nominal:rx160", str(path), "--fit-frames", "--no-progress"]
    assert hybrid_pk(argv) == 0
    out = capsys.readouterr().out
    warning = [line for line in out.splitlines() if "the measured orientations miss" in line]
    assert len(warning) == 1, out
    assert "read as the order x y z w under the columns qw qx qy qz" in warning[0]
    assert "orientation error [deg]" in out

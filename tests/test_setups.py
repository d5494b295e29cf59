"""Files of separate set-ups fitted with one frame set are refused, naming the flag
(hybrid_pk.calibration.setups).

Before, `hybrid-pk diagnose A.csv B.csv` of the two shared UR10 series without
`--frames-per-file` fitted one base/tool frame to both: the nominal model missed the rows
by 618 mm (mean), the diagnosis named nothing, listed all 1,495 rows of Series B as
outliers and took 17 s to say so. The tracker had moved between the series."""

from __future__ import annotations

import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.geometry import rpy_to_matrix
from hybrid_pk.pipelines.calibration import calibrate
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

EFFECT = "joint_offset:joint_3=4e-4"


def _base(rng) -> torch.Tensor:
    """A tracker placement: 1-3 m from the robot, turned about the vertical, tilted a
    little."""
    T = torch.eye(4, dtype=torch.float64)
    yaw = float(rng.uniform(-math.pi, math.pi))
    tilt = rng.uniform(-0.02, 0.02, size=2)
    T[:3, :3] = rpy_to_matrix(torch.tensor([tilt[0], tilt[1], yaw], dtype=torch.float64))
    r, az = float(rng.uniform(1.0, 3.0)), float(rng.uniform(-math.pi, math.pi))
    T[:3, 3] = torch.tensor([r * math.cos(az), r * math.sin(az), float(rng.uniform(-0.5, 0.5))])
    return T


def _files(robot, bases, rng) -> hpk.MeasuredData:
    tool = torch.tensor(rng.uniform(-0.05, 0.05, size=3)) + torch.tensor([0.0, 0.0, 0.1])
    parts = []
    for k, base in enumerate(bases):
        d, _ = hpk.simulate_campaign(
            robot, 160, EFFECT, noise_mm=0.02, noise_deg=0.002, base=base, tool=tool,
            seed=int(rng.integers(1 << 30)),
        )  # fmt: skip
        parts.append(hpk.MeasuredData(**{**d.__dict__, "sources": (f"setup_{k}.csv",)}))
    return hpk.MeasuredData.concat(parts)


def _written(data: hpk.MeasuredData, folder) -> list[str]:
    """Each file of ``data`` written as its own table; their paths."""
    paths = []
    for k in range(len(data.sources)):
        path = folder / f"setup_{k}.csv"
        hpk.write_table(path, data.subset(data.file_index == k))
        paths.append(str(path))
    return paths


def test_files_of_separate_setups_with_one_frame_set_are_refused(rx160):
    rng = run_rng("separate-setups")
    data = _files(rx160, [_base(rng), _base(rng)], rng)
    with pytest.raises(hpk.DataError) as err:
        hpk.diagnose(rx160, data, candidates=["joint_offset:joint_3"])
    text = str(err.value)
    assert "separate set-ups" in text, text
    assert "--frames-per-file" in text, text
    assert "frames_per_file=True" in text
    with pytest.raises(hpk.HybridPKError, match="separate set-ups"):
        calibrate(rx160, data, ["joint_offset:joint_3"])
    # each file its own frames: the offset is found and calibrated
    diag = hpk.diagnose(rx160, data, frames_per_file=True, candidates=["joint_offset:joint_3"])
    assert [c.effect for c in diag.causes] == ["joint_offset"]
    assert abs(diag.causes[0].value - 4e-4) < 5 * diag.causes[0].std + 1e-6
    cal = calibrate(rx160, data, ["joint_offset:joint_3"], frames_per_file=True)
    value = float(cal.model.effect("joint_offset:joint_3").value.detach())
    assert value == pytest.approx(4e-4, rel=0.05)


def test_files_of_one_setup_with_one_frame_set_are_diagnosed(rx160):
    """Two files measured from the same tracker placement: one frame set is right, and
    nothing is refused."""
    rng = run_rng("one-setup")
    base = _base(rng)
    data = _files(rx160, [base, base], rng)
    diag = hpk.diagnose(rx160, data, candidates=["joint_offset:joint_3"])
    assert [c.effect for c in diag.causes] == ["joint_offset"]
    assert diag.nominal["position_mm"]["mean"] < 20


def test_the_cli_says_it_in_one_line_and_writes_nothing(rx160, tmp_path, capsys):
    rng = run_rng("separate-setups-cli")
    paths = _written(_files(rx160, [_base(rng), _base(rng)], rng), tmp_path)
    out = tmp_path / "diag.json"
    argv = ["diagnose", *paths, "--robot", "rx160", "--json", str(out), "--no-progress"]
    assert hybrid_pk([*argv, "--candidates", "joint_offset:joint_3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("hybrid-pk diagnose: error: "), err
    assert "the 2 files look like separate set-ups" in err[0]
    assert "--frames-per-file" in err[0]
    assert not out.exists()


def test_evaluate_names_separate_setups_in_its_gross_warning(rx160, tmp_path, capsys):
    """`evaluate --fit-frames` keeps reporting the errors, but its warning names the
    set-ups and the flag (before: "the rows are not this robot's")."""
    rng = run_rng("separate-setups-evaluate")
    paths = _written(_files(rx160, [_base(rng), _base(rng)], rng), tmp_path)
    argv = ["evaluate", "nominal:rx160", *paths, "--fit-frames", "--no-progress"]
    assert hybrid_pk(argv) == 0
    out = capsys.readouterr().out
    warning = next(line for line in out.splitlines() if line.startswith("warning: nominal"))
    assert "the 2 files look like separate set-ups" in warning, warning
    assert "--frames-per-file" in warning
    assert "not this robot's" not in warning
    assert hybrid_pk([*argv, "--frames-per-file"]) == 0
    assert "misses these rows" not in capsys.readouterr().out


def test_train_with_fit_frames_refuses_them_before_training(rx160, tmp_path, capsys):
    rng = run_rng("separate-setups-train")
    paths = _written(_files(rx160, [_base(rng), _base(rng)], rng), tmp_path)
    out, logs = tmp_path / "hybrid.pt", tmp_path / "logs"
    argv = ["train", *paths, "--model", "nominal:rx160", "--fit-frames", "--out", str(out)]
    assert hybrid_pk([*argv, "--logdir", str(logs), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "separate set-ups" in err[0], err
    assert "--frames-per-file" in err[0], err
    assert not out.exists()
    assert not logs.exists()

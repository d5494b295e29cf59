"""A set-up that changed within a file is refused, naming the file and the first row of
the new set-up (hybrid_pk.calibration.setup_change).

Before, 600 rows of the shared UR10's Series B whose last 240 rows were moved by 3° and
55 mm (a tracker bumped mid-file) were diagnosed as "no cause; the URDF may be wrong in
more than one place"."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.geometry import matrix_to_quat, quat_to_matrix, so3_exp
from hybrid_pk.pipelines.calibration import calibrate
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

LABEL = "joint_offset:joint_3"


def _bumped(robot, rng, position_only: bool) -> tuple[hpk.MeasuredData, int, hpk.MeasuredData]:
    """A campaign whose rows from ``k`` on were measured after the tracker moved by a
    random 2-10° and 30-300 mm; returns ``(moved, k, as measured before the move)``."""
    data, _ = hpk.simulate_campaign(
        robot, 300, f"{LABEL}=4e-4", noise_mm=0.02, noise_deg=0.002,
        position_only=position_only, seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    k = int(rng.integers(int(0.2 * data.n), int(0.8 * data.n)))
    axis = torch.as_tensor(rng.normal(size=3))
    turn = so3_exp(axis / axis.norm() * math.radians(float(rng.uniform(2, 10))))
    way = torch.as_tensor(rng.normal(size=3))
    shift = way / way.norm() * float(rng.uniform(0.03, 0.3))  # [m]
    position = data.position.clone()
    position[k:] = position[k:] @ turn.T + shift
    quat = None
    if data.quat is not None:
        quat = data.quat.clone()
        quat[k:] = matrix_to_quat(turn @ quat_to_matrix(data.quat[k:]))
    return dataclasses.replace(data, position=position, quat=quat), k, data


@pytest.mark.parametrize("position_only", [False, True])
def test_a_set_up_changed_within_the_rows_is_refused_at_its_row(rx160, position_only):
    rng = run_rng(f"setup-change-{position_only}")
    moved, k, clean = _bumped(rx160, rng, position_only)
    row = int(moved.rows[k])
    with pytest.raises(hpk.DataError) as err:
        hpk.diagnose(rx160, moved, candidates=[LABEL])
    text = str(err.value)
    assert (err.value.file, err.value.row) == (moved.sources[0], row), (k, text)
    assert f", row {row}: the set-up changed here:" in text, (k, text)
    assert "split the file here" in text
    with pytest.raises(hpk.HybridPKError, match=f"row {row}: the set-up changed here:"):
        calibrate(rx160, moved, [LABEL])
    # the same rows as measured before the move: nothing refused, the offset named
    diag = hpk.diagnose(rx160, clean, candidates=[LABEL])
    assert [c.effect for c in diag.causes] == ["joint_offset"]


def test_the_cli_names_file_and_row_in_one_line(rx160, tmp_path, capsys):
    rng = run_rng("setup-change-cli")
    moved, k, _ = _bumped(rx160, rng, False)
    path = tmp_path / "bumped.csv"
    hpk.write_table(path, moved)
    out = tmp_path / "diag.json"
    argv = ["diagnose", str(path), "--robot", "rx160", "--json", str(out), "--no-progress"]
    assert hybrid_pk([*argv, "--candidates", LABEL]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    # the table's data rows are 1-based: row k + 1 is the first row of the new set-up
    head = f"hybrid-pk diagnose: error: {path}, row {k + 1}: the set-up changed here:"
    assert err[0].startswith(head), err
    assert not out.exists()


def test_evaluate_with_fit_frames_names_the_row_as_the_gross_errors_cause(rx160, tmp_path, capsys):
    rng = run_rng("setup-change-evaluate")
    moved, k, _ = _bumped(rx160, rng, False)
    path = tmp_path / "bumped.csv"
    hpk.write_table(path, moved)
    argv = ["evaluate", "nominal:rx160", str(path), "--fit-frames", "--no-progress"]
    assert hybrid_pk(argv) == 0
    out = capsys.readouterr().out
    gross = next(line for line in out.splitlines() if "misses these rows" in line)
    assert f"row {k + 1}: the set-up changed here:" in gross, gross
    assert "not this robot's" not in gross

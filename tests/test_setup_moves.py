"""A set-up that moved by a little during the rows (a tracker knocked by a millimetre, a
tripod settling) is named after the diagnosis, as a change at one row or a drift
(hybrid_pk.calibration.diagnosis.setup_moves).

Before, such a move, far below the 20 mm of the set-up change refused before any fit,
was explained by causes: 600 rows of the shared UR10's Series B with the rows from 500
on moved by 1 mm were diagnosed with 14 causes instead of 10, and nothing said why."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.setup_moves import (
    _change_row,
    _errors,
    _places,
    mention_moves,
    move_columns,
    setup_move_text,
)
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.geometry import matrix_to_quat, quat_to_matrix, so3_exp
from hybrid_pk.report.diagnosis_report import write_diagnosis_report
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

LABEL = "joint_offset:joint_3"


def _campaign(robot, rng, n: int = 500) -> hpk.MeasuredData:
    data, _ = hpk.simulate_campaign(
        robot, n, f"{LABEL}=4e-4", noise_mm=0.02, noise_deg=0.002,
        seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    return data


def _moved(data: hpk.MeasuredData, weight: torch.Tensor, rotvec: torch.Tensor, shift):
    """``data`` with row i's measurement frame moved by ``weight[i]`` of a rigid move:
    turned by ``rotvec`` [rad] about the frame's origin, then shifted by ``shift`` [m]."""
    turn = so3_exp(rotvec * weight[:, None])
    position = (turn @ data.position[..., None]).squeeze(-1) + shift * weight[:, None]
    quat = None if data.quat is None else matrix_to_quat(turn @ quat_to_matrix(data.quat))
    return dataclasses.replace(data, position=position, quat=quat)


def _rows(q: torch.Tensor, T: torch.Tensor) -> hpk.MeasuredData:
    n = q.shape[0]
    return hpk.MeasuredData(
        q=q, position=T[:, :3, 3], quat=matrix_to_quat(T[:, :3, :3]),
        joint_names=tuple(f"j{i}" for i in range(q.shape[1])),
        file_index=torch.zeros(n, dtype=torch.long), rows=torch.arange(1, n + 1),
        sources=("rows.csv",),
    )  # fmt: skip


def test_the_move_columns_are_the_derivatives_of_a_frame_move(ur10):
    """Oracle: the errors after moving the base by exp(d) and the tool by exp(t), by
    finite differences, against the columns (float64)."""
    rng = run_rng("move-columns")
    q = ur10.sample_q(20, torch.Generator().manual_seed(int(rng.integers(1 << 30))))
    T = ur10.fk(q).detach()
    T[:, :3, 3] += torch.tensor([1.5, -0.4, 0.3], dtype=T.dtype)  # the tracker's frame
    sigmas = (0.02, 3e-5)
    data = _rows(q, T)
    A = move_columns(T, sigmas)
    x = torch.as_tensor(rng.normal(size=12)) * 1e-7
    base = torch.eye(4, dtype=T.dtype)
    base[:3, :3], base[:3, 3] = so3_exp(x[3:6]), x[0:3] * 1e-3
    tool = torch.eye(4, dtype=T.dtype)
    tool[:3, :3], tool[:3, 3] = so3_exp(x[9:12]), x[6:9] * 1e-3
    moved = base @ T @ tool
    # the measured rows are the moved poses: the errors of the unmoved model are A x
    e = _errors(T, _rows(q, moved), sigmas) - _errors(T, data, sigmas)
    assert torch.allclose(e, (A @ x[:, None]).squeeze(-1), rtol=1e-5, atol=1e-9)


def test_a_drift_runs_with_the_time_stamps_where_the_rows_have_them(rx160):
    rng = run_rng("setup-places")
    data = _campaign(rx160, rng, n=40)
    by_row = torch.linspace(0, 1, 40, dtype=torch.float64)
    assert torch.equal(_places(data, torch.float64), by_row)
    t = torch.arange(40, dtype=torch.float64)
    t[20:] += 60.0  # a pause of a minute: half the span
    places = _places(dataclasses.replace(data, t=t), torch.float64)
    assert places[19] == pytest.approx(19 / 99)
    assert places[20] == pytest.approx(80 / 99)
    shuffled = dataclasses.replace(data, t=t.flip(0))  # not in time order: by row
    assert torch.equal(_places(shuffled, torch.float64), by_row)


def test_the_change_row_is_found_where_the_errors_step():
    rng = run_rng("change-row")
    n, p = 400, 12
    k_true = int(rng.integers(100, 300))  # 50 fitted rows on each side, a third held out
    A = torch.as_tensor(rng.normal(size=(n, 6, p)))
    x1, x2 = (torch.as_tensor(rng.normal(size=p)) for _ in range(2))
    x = torch.where(torch.arange(n)[:, None] < k_true, x1, x2)
    e = (A @ x[..., None]).squeeze(-1) + 0.01 * torch.as_tensor(rng.normal(size=(n, 6)))
    assert _change_row(A, e, torch.ones(n, dtype=torch.bool), 50) == k_true
    rows = torch.ones(n, dtype=torch.bool)
    rows[::3] = False  # a region held out: the fitted rows still step there
    assert abs(_change_row(A, e, rows, 50) - k_true) <= 2
    assert _change_row(A, e, torch.arange(n) < 90, 50) is None  # too few for two parts


@pytest.mark.parametrize(
    ("shape", "position_only"), [("change", False), ("drift", False), ("change", True)]
)
def test_a_small_move_of_the_set_up_is_named(rx160, shape, position_only, tmp_path):
    """A random rigid move of 0.2-1 mm and 0.01-0.05° (a change at a random row, or a
    drift over the rows): named with its kind, row and size."""
    rng = run_rng(f"setup-move-{shape}-{position_only}")
    data = _campaign(rx160, rng)
    if position_only:
        data = dataclasses.replace(data, quat=None)
    n = data.n
    k = int(rng.integers(int(0.25 * n), int(0.75 * n)))
    weight = (
        (torch.arange(n) >= k).double()
        if shape == "change"
        else torch.linspace(0, 1, n, dtype=torch.float64)
    )
    axis, way = (torch.as_tensor(rng.normal(size=3)) for _ in range(2))
    rotvec = axis / axis.norm() * math.radians(float(rng.uniform(0.01, 0.05)))
    shift = way / way.norm() * float(rng.uniform(0.2, 1.0)) * 1e-3
    moved = _moved(data, weight, rotvec, shift)
    d = hpk.diagnose(rx160, moved, candidates=[LABEL])
    (entry,) = d.setup_moves
    assert entry["kind"] == shape, entry
    assert entry["gain_mm"] >= entry["min_gain_mm"]
    assert entry == d.to_json()["setup_moves"][0]
    # how far the whole move (weight 1) displaces each row: from the change on, or every
    # row for the drift (its last row against its first)
    whole = _moved(data, torch.ones(n, dtype=torch.float64), rotvec, shift)
    true = (whole.position - data.position).norm(dim=1) * 1e3
    if shape == "change":
        assert abs(entry["row"] - int(moved.rows[k])) <= 0.02 * n, (entry["row"], k)
        expected = float(true[k:].mean())
    else:
        assert entry["row"] is None
        expected = float(true.mean())
    assert entry["shift_mm"]["mean"] == pytest.approx(expected, rel=0.35), (entry, expected)
    line = setup_move_text(entry)
    assert any(w["cause"] == "set-up" and w["why"] == line for w in d.warnings)
    word = "moved near row" if shape == "change" else "drifted during"
    assert f"the set-up {word}" in line
    report = write_diagnosis_report(d, moved, rx160, tmp_path).read_text()
    assert "## The set-up moved during the rows" in report
    assert line in report
    assert (tmp_path / "setup_0.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _random_move(rng, mm: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """A rigid move of 0.01-0.05 deg about a random axis and ``mm`` along another."""
    axis, way = (torch.as_tensor(rng.normal(size=3)) for _ in range(2))
    rotvec = axis / axis.norm() * math.radians(float(rng.uniform(0.01, 0.05)))
    return rotvec, way / way.norm() * float(rng.uniform(*mm)) * 1e-3


def test_a_drift_with_a_knock_on_top_is_named_both(rx160, tmp_path):
    """A random drift of 0.5-1 mm over the rows and a random change of 0.2-1 mm at a
    random row of the middle 40 % (the drift must show on each side of the change on its
    own): before, named a change or a drift, half the story, the other half left in the
    errors (held out 0.08-0.22 mm by the better one against 0.04-0.05 mm for both together)."""
    rng = run_rng("setup-move-both")
    data = _campaign(rx160, rng)
    n = data.n
    k = int(rng.integers(int(0.3 * n), int(0.7 * n)))
    r_drift, s_drift = _random_move(rng, (0.5, 1.0))
    r_knock, s_knock = _random_move(rng, (0.2, 1.0))
    drifted = _moved(data, torch.linspace(0, 1, n, dtype=torch.float64), r_drift, s_drift)
    moved = _moved(drifted, (torch.arange(n) >= k).double(), r_knock, s_knock)
    d = hpk.diagnose(rx160, moved, candidates=[LABEL])
    (entry,) = d.setup_moves
    assert entry["kind"] == "change_and_drift", entry
    assert abs(entry["row"] - int(moved.rows[k])) <= 0.02 * n, (entry["row"], k)
    held = entry["blocked_mean_mm"]
    assert held["both"] + entry["min_gain_mm"] <= min(held["change"], held["drift"])
    ones = torch.ones(n, dtype=torch.float64)
    knock = (_moved(data, ones, r_knock, s_knock).position - data.position).norm(dim=1)
    drift = (_moved(data, ones, r_drift, s_drift).position - data.position).norm(dim=1)
    assert entry["shift_mm"]["mean"] == pytest.approx(1e3 * float(knock[k:].mean()), rel=0.35)
    assert entry["drift"]["shift_mm"]["mean"] == pytest.approx(1e3 * float(drift.mean()), rel=0.35)
    line = setup_move_text(entry)
    assert f"drifted during {entry['file']} and moved near row {entry['row']}" in line
    assert f"--split-at {entry['file']}:{entry['row']}" in line
    report = write_diagnosis_report(d, moved, rx160, tmp_path).read_text()
    assert line in report
    assert "one / change / drift / both" in report


def test_a_set_up_that_stayed_is_not_named(rx160):
    rng = run_rng("setup-stayed")
    d = hpk.diagnose(rx160, _campaign(rx160, rng), candidates=[LABEL])
    assert d.setup_moves == []
    assert not any(w["cause"] == "set-up" for w in d.warnings)


def test_both_commands_print_the_move(rx160, tmp_path, capsys):
    """``hybrid-pk diagnose`` and ``hybrid-pk calibrate --effects auto`` print the move
    as a ``warning: set-up:`` line (the causes they name may carry part of it)."""
    rng = run_rng("setup-move-cli")
    data = _campaign(rx160, rng)
    k = int(rng.integers(int(0.3 * data.n), int(0.7 * data.n)))
    weight = (torch.arange(data.n) >= k).double()
    moved = _moved(data, weight, torch.zeros(3, dtype=torch.float64), torch.tensor([6e-4, 0, 0]))
    table = hpk.write_table(tmp_path / "nudged.csv", moved)
    config = tmp_path / "candidates.yaml"
    config.write_text(f"candidates: [{LABEL}]\n")
    common = [str(table), "--robot", "rx160", "--config", str(config), "--no-progress"]
    # the first fit row of the new set-up (the row itself may be a hold-out row)
    near = re.compile(r"^warning: set-up: the set-up moved near row (\d+) of .*nudged\.csv")
    true_row = int(moved.rows[k])

    def named_row(out: str) -> int:
        rows = [int(m[1]) for line in out.splitlines() if (m := near.match(line))]
        assert len(rows) == 1, out
        return rows[0]

    assert hybrid_pk(["diagnose", *common, "--json", str(tmp_path / "d.json")]) == 0
    assert abs(named_row(capsys.readouterr().out) - true_row) <= 0.02 * data.n
    model = str(tmp_path / "m.pt")
    assert hybrid_pk(["calibrate", *common, "--effects", "auto", "--out", model]) == 0
    assert abs(named_row(capsys.readouterr().out) - true_row) <= 0.02 * data.n


def test_rows_measured_region_by_region_with_an_unmodelled_error_name_no_move(rx160):
    """The false alarm to fear: rows measured region by region (sorted by a random one of
    the first three joints), with errors the candidates cannot explain (a link length
    and a compliance left out of them), so that a frame set fitted per part of the rows
    would absorb a different error in each part. Judged region by region, it does not
    carry over, and no move is named."""
    rng = run_rng("setup-sorted")
    effects = f"{LABEL}=4e-4; link_length:joint_4=0,3e-4,2e-4; joint_compliance:joint_2=1e-6"
    data, _ = hpk.simulate_campaign(
        rx160, 600, effects, noise_mm=0.02, noise_deg=0.002, payload=20.0,
        seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    joint = int(rng.integers(0, 3))
    data = data.subset(data.q[:, joint].argsort())
    data = dataclasses.replace(data, rows=torch.arange(1, data.n + 1))  # the order measured
    d = hpk.diagnose(rx160, data, candidates=[LABEL])
    assert d.setup_moves == [], (joint, d.setup_moves)


def test_the_structural_verdict_names_the_move_it_may_be_speaking_of():
    """On Series B nudged by 1 mm the causes fitted to the move made a structural verdict
    ("not a small correction ... the URDF may be wrong in more than one place"): with a
    move named, the verdict says so; a located structural error and no move leave it."""
    verdict = {"message": "x: not a small correction", "structurally_wrong": False}
    change = {"file": "/data/nudged.csv", "row": 501}
    drift = {"file": "/data/b.csv", "row": None}
    said = mention_moves(verdict, [change, drift])["message"]
    assert said.startswith("x: not a small correction; but the set-up moved during the rows")
    assert "(nudged.csv at row 501, b.csv: see the set-up warning)" in said
    assert "--split-at" in said
    assert verdict["message"] == "x: not a small correction"  # not changed in place
    assert mention_moves(verdict, []) is verdict
    assert mention_moves(None, [change]) is None
    located = {"message": "wrong at joint_2", "structurally_wrong": True}
    assert mention_moves(located, [change]) is located

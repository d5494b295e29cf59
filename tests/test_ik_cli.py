"""``hybrid-pk ik`` end to end on tiny target tables: contract section 6 output, failures
counted, position-only targets, a calibrated model (two stages), and errors."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.geometry import matrix_to_quat, so3_exp, transform
from hybrid_pk.hybrid import HybridFK, InputBox
from hybrid_pk.io.hybrid_file import load_hybrid, save_hybrid
from hybrid_pk.io.model_file import save_model

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64


def _vec(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


def _run(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _write_targets(path: Path, T: torch.Tensor, orientation: bool = True, **extra) -> Path:
    cols = {"x": T[:, 0, 3], "y": T[:, 1, 3], "z": T[:, 2, 3]}
    if orientation:
        quat = matrix_to_quat(T[:, :3, :3])
        cols.update({c: quat[:, k] for k, c in enumerate(("qw", "qx", "qy", "qz"))})
    cols.update(extra)
    pd.DataFrame({k: torch.as_tensor(v).numpy() for k, v in cols.items()}).to_csv(path, index=False)
    return path


def _targets(robot: Robot, n: int, seed: int) -> torch.Tensor:
    q = robot.sample_q(n, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        return robot.fk(q)


def _check_rows(
    frame: pd.DataFrame, robot: Robot, fk, T: torch.Tensor, tol=1e-3, atol=1e-9
) -> None:
    """Every row: joints within limits, reported errors true (recomputed with ``fk``) to
    ``atol`` [mm]."""
    q = torch.tensor(frame[robot.joint_names].to_numpy(), dtype=F64)
    lo, hi = robot.joint_limits
    assert bool(((q >= lo) & (q <= hi)).all())
    with torch.no_grad():
        err = pose_error(T[torch.tensor(frame["target"].to_numpy())], fk(q))
    assert float(err.position_mm.max()) <= tol
    assert float(err.orientation_deg.max()) <= tol
    assert torch.allclose(
        torch.tensor(frame["position_error_mm"].to_numpy()), err.position_mm, atol=atol
    )


def test_ik_nominal_table_with_an_unreachable_target(tmp_path, capsys):
    robot = Robot.from_urdf("rx160")
    T = _targets(robot, 3, seed=0)
    far = T[:1].clone()
    far[:, :3, 3] = torch.tensor([5.0, 5.0, 5.0], dtype=F64)
    T = torch.cat([T[:2], far, T[2:]])  # target 2 is out of reach
    targets = _write_targets(tmp_path / "targets.csv", T)
    out = tmp_path / "solutions.csv"
    rc, stdout, err = _run(capsys, "ik", "nominal:rx160", targets, "--out", out, "--seeds", 32)
    assert rc == 0, err
    frame = pd.read_csv(out)
    assert list(frame.columns) == [
        "target",
        "solution",
        *robot.joint_names,
        "position_error_mm",
        "orientation_error_deg",
    ]
    assert sorted(set(frame["target"])) == [0, 1, 3]  # no row for the failed target
    for _, group in frame.groupby("target"):
        assert list(group["solution"]) == list(range(len(group)))
    _check_rows(frame, robot, robot.fk, T)
    assert "1 of 4 target(s) failed" in stdout
    assert f"wrote {out}" in stdout
    assert "parameter family" not in stdout  # a full pose of six joints: branches


def test_ik_position_only_parquet(tmp_path, capsys):
    robot = Robot.from_urdf("ur10")
    T = _targets(robot, 2, seed=1)
    targets = _write_targets(tmp_path / "points.csv", T, orientation=False)
    out = tmp_path / "solutions.parquet"
    rc, stdout, err = _run(capsys, "ik", "nominal:ur10", targets, "--out", out, "--seeds", 8)
    assert rc == 0, err
    frame = pd.read_parquet(out)
    assert frame["orientation_error_deg"].isna().all()
    q = torch.tensor(frame[robot.joint_names].to_numpy(), dtype=F64)
    with torch.no_grad():
        p = robot.fk(q)[:, :3, 3]
    d = (p - T[torch.tensor(frame["target"].to_numpy()), :3, 3]).norm(dim=-1)
    assert float(d.max()) <= 1e-6  # 1e-3 mm
    assert "position only" in stdout
    assert "0 of 2 target(s) failed" in stdout
    # three coordinates of six joints: a family of solutions, sampled, said so
    assert "a target fixes 3 coordinates of ur10's 6 joints: its solutions form a " in stdout
    assert "3-parameter family" in stdout


def test_ik_on_a_calibrated_model_refines_on_its_effects(tmp_path, capsys):
    robot = Robot.from_urdf("rx160")
    base = transform(
        so3_exp(torch.tensor([0.0, 0.05, 1.2], dtype=F64)), torch.tensor([2.0, 1.0, 0.0])
    )
    tool = transform(
        so3_exp(torch.tensor([0.2, 0.0, 0.0], dtype=F64)), torch.tensor([0.0, 0.0, 0.1])
    )
    effects = [
        make_effect(robot, "joint_offset:joint_3", 3e-3),
        make_effect(robot, "joint_compliance:joint_2", 3e-6),
    ]
    model = ExtendedModel(robot, effects, base=base, tool=tool)
    model.requires_grad_(False)
    path = save_model(tmp_path / "model.pt", model)
    q = robot.sample_q(4, torch.Generator().manual_seed(2))
    payload = torch.tensor([0.0, 5.0, 10.0, 2.0], dtype=F64)
    with torch.no_grad():
        T = model(q, Conditions(payload=payload))
    targets = _write_targets(tmp_path / "targets.csv", T, payload=payload)
    out = tmp_path / "solutions.csv"
    rc, stdout, err = _run(
        capsys, "ik", path, targets, "--out", out, "--seeds", 32, "--robot", "rx160"
    )
    assert rc == 0, err
    assert "two stages" in stdout
    frame = pd.read_csv(out)
    assert sorted(set(frame["target"])) == [0, 1, 2, 3]
    rows = torch.tensor(frame["target"].to_numpy())

    def fk(qq):
        return model(qq, Conditions(payload=payload[rows]))

    _check_rows(frame, robot, fk, T)
    # The nominal kinematics with the same frames would miss by the effects' size.
    nominal = ExtendedModel(robot, [], base=base, tool=tool)
    with torch.no_grad():
        qq = torch.tensor(frame[robot.joint_names].to_numpy(), dtype=F64)
        miss = pose_error(T[rows], nominal(qq)).position_mm
    assert float(miss.min()) > 0.1


def test_ik_on_a_model_with_residual_networks(tmp_path, capsys):
    robot = Robot.from_urdf("ur10")
    torch.manual_seed(0)  # random (not zero) initial weights: a ~0.3 mm residual
    net = HybridFK.build(
        ExtendedModel(robot), InputBox(*robot.joint_limits), "mlp:16x2", "mlp:16x2"
    )
    path = tmp_path / "hybrid.pt"
    save_hybrid(path, net)
    model = load_hybrid(path)
    q = robot.sample_q(3, torch.Generator().manual_seed(4))
    with torch.no_grad():
        T = model(q, None)
        assert float((T[:, :3, 3] - robot.fk(q)[:, :3, 3]).norm(dim=-1).min()) > 1e-5
    targets = _write_targets(tmp_path / "targets.csv", T)
    out = tmp_path / "solutions.csv"
    rc, stdout, err = _run(capsys, "ik", path, targets, "--out", out, "--seeds", 16)
    assert rc == 0, err
    assert "two stages" in stdout
    frame = pd.read_csv(out)
    assert sorted(set(frame["target"])) == [0, 1, 2]
    # float32 networks: their ~0.3 mm output moves by ~1e-8 mm with the batch it is
    # evaluated in (BLAS picks its kernel by the batch size; seen on an AMD EPYC)
    _check_rows(frame, robot, lambda qq: model(qq, None), T, atol=1e-6)


def test_ik_no_progress_shows_no_bar(tmp_path, capsys, monkeypatch):
    """--no-progress (every command) turned off every bar but the IK one (a hybrid model,
    two stages). The bar is the real one, shown from its first line (without the 0.5 s
    delay a quick solve prints nothing either way)."""
    import hybrid_pk.cli.ik_cmd as ik_cmd
    from hybrid_pk.cli.progress import progress

    def at_once(name, total=None, **kw):
        return progress(name, total, **{**kw, "delay": 0.0})

    monkeypatch.setattr(ik_cmd, "progress", at_once)
    robot = Robot.from_urdf("ur10")
    torch.manual_seed(0)
    net = HybridFK.build(
        ExtendedModel(robot), InputBox(*robot.joint_limits), "mlp:16x2", "mlp:16x2"
    )
    path = tmp_path / "hybrid.pt"
    save_hybrid(path, net)
    targets = _write_targets(tmp_path / "t.csv", _targets(robot, 400, seed=5))
    argv = ["ik", path, targets, "--out", tmp_path / "s.csv"]
    rc, out, err = _run(capsys, *argv, "--no-progress")
    assert rc == 0
    assert "on 400 target(s)" in out
    assert "ik [" not in err, err[:200]
    assert "target" not in err, err[:200]
    # without it the bar shows; off a terminal as lines, as every command's, not a bar
    # redrawn by \r
    rc, out, err = _run(capsys, *argv)
    assert rc == 0
    assert "ik [" in err, err[:200]
    assert "\r" not in err


def test_ik_help_states_units(capsys):
    with pytest.raises(SystemExit):
        main(["ik", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for unit in ("[mm]", "[deg]", "[rad", "[m]"):
        assert unit in text
    assert "position_error_mm" in text
    assert "1e-3 rad" in text


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seeds", "0"], "--seeds must be at least 1"),
        (["--tol-mm", "0"], "must be positive"),
        (["--robot", "ur10"], "not 'ur10'"),
        # before: --box -1 / nan solved as if no box were given, without a word
        (["--box", "-1"], "--box must be > 0"),
        (["--box", "nan"], "--box must be > 0"),
        # before: 'IKOptions: tol_mm must be > 0, got IKOptions(tol_mm=nan, ...)'
        (["--tol-mm", "nan"], "--tol-mm and --tol-deg must be positive, got nan mm"),
        (["--max-iterations", "0"], "--max-iterations must be at least 1"),
    ],
)
def test_ik_errors_are_one_line(tmp_path, capsys, argv, message):
    robot = Robot.from_urdf("rx160")
    targets = _write_targets(tmp_path / "t.csv", _targets(robot, 1, seed=3))
    rc, _, err = _run(capsys, "ik", "nominal:rx160", targets, "--out", tmp_path / "o.csv", *argv)
    assert rc == 2
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    assert message in lines[0]


def test_ik_bad_target_table_names_row_and_column(tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_text("x,y,z\n0.5,0.1,1.0\n0.5,nan,1.0\n")
    rc, _, err = _run(capsys, "ik", "nominal:rx160", path, "--out", tmp_path / "o.csv")
    assert rc == 2
    assert "row 2" in err
    assert "'y'" in err


def test_targets_beyond_reach_say_which_frame_targets_are_in(tmp_path, rx160, capsys):
    """Flange poses in the robot base frame given to a model whose base frame (the
    tracker) lies 10 m away: every target fails, and a note says they lie beyond the
    arm's reach and that TARGETS are in the measurement frame (before: only '3 of 3
    target(s) failed'). Targets in the measurement frame solve, with no such note."""
    model = ExtendedModel(rx160, [], base=transform(torch.eye(3, dtype=F64), _vec(10.0, 0, 0)))
    path = save_model(tmp_path / "far.pt", model)
    T = _targets(rx160, 3, seed=4)
    flange = _write_targets(tmp_path / "flange.csv", T)
    rc, out, _ = _run(capsys, "ik", path, flange, "--out", tmp_path / "s.csv", "--no-progress")
    assert rc == 0
    assert "3 of 3 target(s) failed" in out
    assert "beyond the" in out, out
    assert "measurement frame" in out, out
    with torch.no_grad():
        measured = _write_targets(tmp_path / "measured.csv", model(rx160.sample_q(3)))
    rc, out, _ = _run(capsys, "ik", path, measured, "--out", tmp_path / "m.csv", "--no-progress")
    assert rc == 0
    assert "beyond the" not in out, out
    # measured poses given to nominal:ROBOT (identity frames) say the converse
    rc, out, _ = _run(capsys, "ik", "nominal:rx160", measured, "--out", tmp_path / "n.csv")
    assert rc == 0
    assert "nominal:ROBOT takes flange poses in the robot base frame" in out, out


def _beyond_stretched(robot: Robot, beyond: list[float]) -> torch.Tensor:
    """Poses of the UR10 with its elbow stretched and the upper arm horizontal (the
    farthest the wrist gets), each moved ``beyond`` [m] farther along the arm."""
    q = _vec(0.3, 0.0, 0.0, 0.0, 0.7, 0.2)[None]
    with torch.no_grad():
        frames, T = robot.link_frames(q)[0], robot.fk(q)
    along = frames[3, :3, 3] - frames[1, :3, 3]
    T = T.repeat(len(beyond), 1, 1)
    T[:, :3, 3] += _vec(*beyond)[:, None] * along / along.norm()
    return T


def test_targets_just_beyond_reach_say_by_how_much(tmp_path, capsys):
    """A measured pose of a stretched arm lies micrometres beyond the nominal reach: the
    API's closest_mm and the command say how near the solver came (before: a bare '2 of 3
    target(s) failed', and nothing in IKResult)."""
    from hybrid_pk.ik import solve_ik

    robot = Robot.from_urdf("ur10")
    T = _beyond_stretched(robot, [0.0, 5e-6, 1e-4])
    res = solve_ik(robot, T)
    assert res.failed.tolist() == [False, True, True]
    # the best start misses by at most the distance beyond the reach, and not by nothing
    assert 1e-3 < float(res.closest_mm[1]) <= 5e-3 + 1e-6
    assert 1e-2 < float(res.closest_mm[2]) <= 0.1 + 1e-6
    assert float(res.closest_mm[0]) <= res.tol_mm  # a solved target: its best solution
    assert bool(torch.isfinite(res.closest_deg).all())
    targets = _write_targets(tmp_path / "t.csv", T)
    rc, out, _ = _run(capsys, "ik", "nominal:ur10", targets, "--out", tmp_path / "s.csv")
    assert rc == 0
    assert "2 of 3 target(s) failed" in out
    line = next(ln for ln in out.splitlines() if ln.startswith("note: closest"))
    assert f"1: {float(res.closest_mm[1]):.3g} mm" in line, line
    assert f"2: {float(res.closest_mm[2]):.3g} mm" in line, line


def test_two_stage_ik_says_how_near_it_came(tmp_path, capsys):
    """On a calibrated model (two stages, direct fall-back for failures) a target beyond
    the reach gets closest_mm from the direct solve; solved targets their best solution."""
    from hybrid_pk.ik import solve_ik_two_stage

    robot = Robot.from_urdf("ur10")
    model = ExtendedModel(robot, [make_effect(robot, "joint_offset:elbow_joint", 2e-3)])
    model.requires_grad_(False)
    T = _beyond_stretched(robot, [-0.05, 1e-4])
    res = solve_ik_two_stage(robot, model, T)
    assert res.failed.tolist() == [False, True]
    assert float(res.closest_mm[0]) <= res.tol_mm
    assert 1e-2 < float(res.closest_mm[1]) <= 0.1 + 1e-6
    path = save_model(tmp_path / "m.pt", model)
    targets = _write_targets(tmp_path / "t.csv", T)
    rc, out, _ = _run(capsys, "ik", path, targets, "--out", tmp_path / "s.csv", "--no-progress")
    assert rc == 0
    assert f"1: {float(res.closest_mm[1]):.3g} mm" in out, out


@pytest.mark.parametrize("box", [0.0, -0.1, float("nan")])
def test_two_stage_ik_refuses_a_box_that_is_not_positive(box):
    """solve_ik_two_stage(box=-0.1) gave lower > upper boxes and fell back to the direct
    solve without a word; now a one-line error before any work."""
    from hybrid_pk.errors import ShapeError
    from hybrid_pk.ik import solve_ik_two_stage

    robot = Robot.from_urdf("ur10")
    model = ExtendedModel(robot, [make_effect(robot, "joint_offset:elbow_joint", 2e-3)])
    with pytest.raises(ShapeError, match="box half-width must be > 0"):
        solve_ik_two_stage(robot, model, _targets(robot, 1, seed=1), box=box)


def test_targets_at_singular_configurations_are_named(tmp_path, capsys):
    """The UR10 home pose (-pi, -pi/2, 0, -pi/2, 0, 0: elbow stretched, wrist_2 = 0) and a
    pose with wrist_2 = 1e-4 have solutions that the tolerance does not pin down to the
    1e-3 rad that tells solutions apart (before: 1 and 7-10 rows listed as if distinct
    branches, without a word); a regular pose (wrist_2 = 0.7) gets no such note."""
    robot = Robot.from_urdf("ur10")
    q = torch.tensor(
        [
            [-torch.pi, -torch.pi / 2, 0.0, -torch.pi / 2, 0.0, 0.0],
            [0.3, -1.0, 1.0, 0.5, 1e-4, 0.2],
            [0.3, -1.0, 1.0, 0.5, 0.7, 0.2],
        ],
        dtype=F64,
    )
    with torch.no_grad():
        T = robot.fk(q)
    both = _write_targets(tmp_path / "t.csv", T)
    rc, out, _ = _run(capsys, "ik", "nominal:ur10", both, "--out", tmp_path / "s.csv")
    assert rc == 0
    line = next(ln for ln in out.splitlines() if "singular configuration" in ln)
    assert "2 target(s) (rows 0, 1, 0-based)" in line, line
    regular = _write_targets(tmp_path / "r.csv", T[2:])
    rc, out, _ = _run(capsys, "ik", "nominal:ur10", regular, "--out", tmp_path / "r_s.csv")
    assert rc == 0
    assert "singular configuration" not in out.replace(str(tmp_path), "")

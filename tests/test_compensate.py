"""Program compensation (issue 15): joints that put the real robot at the nominal pose,
on the same branch, within limits; unreachable rows reported; the ``compensate`` CLI."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

from hybrid_pk.cli.main import main
from hybrid_pk.data.joint_table import write_joint_table
from hybrid_pk.effects import Conditions, ExtendedModel, approach_direction, make_effect
from hybrid_pk.evaluation.metrics import pose_error
from hybrid_pk.geometry import matrix_to_quat
from hybrid_pk.hybrid import HybridFK, InputBox
from hybrid_pk.ik import compensate
from hybrid_pk.io.hybrid_file import save_hybrid
from hybrid_pk.io.model_file import save_model
from hybrid_pk.simulate import random_frames

F64 = torch.float64
N = 60


pytestmark = pytest.mark.usefixtures("one_thread")


def _real(robot, *extra: str) -> ExtendedModel:
    """A 'calibrated' robot: offset, compliance, backlash, plus ``extra`` effects."""
    base, tool = random_frames(torch.Generator().manual_seed(4))
    effects = [
        make_effect(robot, "joint_offset:joint_2", torch.tensor(8e-4, dtype=F64)),
        make_effect(robot, "joint_compliance:joint_3", torch.tensor(3e-6, dtype=F64)),
        make_effect(robot, "backlash:joint_5", torch.tensor(6e-4, dtype=F64)),
    ]
    for label in extra:
        kind, _, value = label.partition("=")
        values = [float(v) for v in value.split(",")]
        effects.append(make_effect(robot, kind, torch.tensor(values, dtype=F64).squeeze()))
    model = ExtendedModel(robot, effects, base=base, tool=tool)
    model.requires_grad_(False)
    return model


def _program(robot, n: int = N, seed: int = 0) -> torch.Tensor:
    lo, hi = robot.joint_limits
    u = torch.rand(n, robot.dof, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return lo + (0.05 + 0.9 * u) * (hi - lo)


def _cond(q: torch.Tensor) -> Conditions:
    return Conditions(payload=torch.zeros(q.shape[0], dtype=F64))


def _frames(model: ExtendedModel):
    with torch.no_grad():
        return model.base.matrix()[0], model.tool.matrix()[0]


def test_compensated_joints_reach_the_nominal_pose(rx160):
    real = _real(rx160)
    q_nom = _program(rx160)
    base, tool = _frames(real)
    payload = torch.full((N,), 15.0, dtype=F64)
    comp = compensate(real, rx160, base=base, tool=tool, q_nominal=q_nom,
                      cond=Conditions(payload=payload))  # fmt: skip
    assert comp.status == ("ok",) * N
    # independent check: the real model at the corrected joints, under the program's
    # approach directions, vs the nominal flange pose placed by the model's frames
    cond = Conditions(payload=payload, direction=approach_direction(q_nom))
    with torch.no_grad():
        err = pose_error(base @ rx160.fk(q_nom) @ tool, real(comp.q, cond))
        before = pose_error(base @ rx160.fk(q_nom) @ tool, real(q_nom, cond))
    assert float(err.position_mm.max()) < 1e-3
    assert float(err.orientation_deg.max()) < 1e-3
    assert float(before.position_mm.mean()) > 0.3  # the program was off before
    assert torch.allclose(comp.nominal_mm, before.position_mm, atol=1e-9)
    # same branch: small corrections; within the limits
    assert float((comp.q - q_nom).abs().max()) < 0.01
    lo, hi = rx160.joint_limits
    assert bool(((comp.q >= lo) & (comp.q <= hi)).all())
    assert any("program order" in a for a in comp.assumed)


def test_a_row_needing_a_joint_beyond_its_limit_is_reported_not_bent(rx160):
    real = _real(rx160, "joint_offset:joint_4=2e-3")  # true joint 4 = commanded + 2 mrad
    q_nom = _program(rx160, 5)
    lo, hi = rx160.joint_limits
    q_nom[2, 3] = hi[3] - 1e-4  # the correction must go below, fine
    q_nom[3, 3] = lo[3] + 1e-4  # needs ~2 mrad below the lower limit of joint 4
    base, tool = _frames(real)
    comp = compensate(
        real, rx160, base=base, tool=tool, q_nominal=q_nom, approach="mid", cond=_cond(q_nom)
    )
    assert comp.status[2] == "ok"
    assert comp.status[3] == "joint_limit"
    assert "joint_4" in comp.note[3]
    assert "lower limit" in comp.note[3]
    assert torch.equal(comp.q[3], q_nom[3])  # nominal joints kept
    assert float(comp.residual_mm[3]) == pytest.approx(float(comp.nominal_mm[3]))
    assert comp.status.count("ok") == 4


def test_a_pose_beyond_the_real_reach_is_unreachable(rx160):
    # stretch the arm straight ahead: the elbow angle of largest reach
    q3 = torch.linspace(-2.5, 2.5, 2001, dtype=F64)
    q = torch.zeros(q3.shape[0], rx160.dof, dtype=F64)
    q[:, 1], q[:, 2] = 0.3, q3
    with torch.no_grad():
        reach = rx160.fk(q)[:, :3, 3].norm(dim=-1)
    q_nom = q[reach.argmax()][None].clone()
    real = _real(rx160, "link_length:joint_3=0,0,-0.01")
    base, tool = _frames(real)
    comp = compensate(
        real, rx160, base=base, tool=tool, q_nominal=q_nom, approach="mid", cond=_cond(q_nom)
    )
    assert comp.status == ("unreachable",)
    assert "no solution within" in comp.note[0]
    # the stretched elbow is singular: the reason is said
    assert "near a singular configuration" in comp.note[0]


def test_a_box_too_small_for_any_direction_is_not_called_singular(rx160):
    """A 2 mrad joint offset with a 0.5 mrad box, in a well-conditioned program: the
    rows are unreachable within the box, and nothing is said about singularity."""
    real = _real(rx160, "joint_offset:joint_2=2e-3")
    q_nom = _program(rx160, 5)
    base, tool = _frames(real)
    comp = compensate(real, rx160, base=base, tool=tool, q_nominal=q_nom, approach="mid",
                      cond=_cond(q_nom), box=5e-4)  # fmt: skip
    assert set(comp.status) == {"unreachable"}, comp.status
    assert not any("singular" in n for n in comp.note), comp.note


def test_pose_program_takes_the_branch_nearest_the_previous_row(rx160):
    real = _real(rx160)
    a, b = _program(rx160, 2, seed=3)
    q_nom = a + torch.linspace(0, 0.3, 30, dtype=F64)[:, None] * (b - a)  # a smooth path
    base, tool = _frames(real)
    with torch.no_grad():
        targets = rx160.fk(q_nom)
    by_joints = compensate(
        real, rx160, base=base, tool=tool, q_nominal=q_nom, approach="mid", cond=_cond(q_nom)
    )
    by_poses = compensate(real, rx160, base=base, tool=tool, targets=targets,
                          reference=q_nom[0], approach="mid", cond=_cond(q_nom))  # fmt: skip
    assert torch.allclose(by_poses.q_nominal, q_nom, atol=1e-6)
    assert torch.allclose(by_poses.q, by_joints.q, atol=1e-6)


def test_hybrid_model_is_compensated_through_its_networks(rx160):
    base_model = _real(rx160)
    q_box = rx160.sample_q(64, torch.Generator().manual_seed(1))
    torch.manual_seed(0)
    hybrid = HybridFK.build(
        base_model, InputBox.from_data(q_box, None, fade=0.2), "mlp:8x2", "mlp:8x2",
        torch.full((3,), 1e-3, dtype=F64), torch.full((3,), 2e-3, dtype=F64),
    ).eval()  # fmt: skip
    hybrid.requires_grad_(False)
    q_nom = _program(rx160, 20, seed=5)
    base, tool = _frames(base_model)
    comp = compensate(
        hybrid, rx160, base=base, tool=tool, q_nominal=q_nom, approach="mid", cond=_cond(q_nom)
    )
    assert comp.status == ("ok",) * 20
    with torch.no_grad():
        err = pose_error(base @ rx160.fk(q_nom) @ tool, hybrid(comp.q, Conditions(
            direction=torch.zeros(20, rx160.dof, dtype=F64))))  # fmt: skip
    assert float(err.position_mm.max()) < 1e-3


# ----------------------------------------------------------------------------- CLI


def test_cli_joint_and_pose_programs(tmp_path, capsys, rx160):
    model_file = save_model(tmp_path / "model.pt", _real(rx160))
    q_nom = _program(rx160, 8, seed=2)
    program = write_joint_table(tmp_path / "program.csv", q_nom, rx160.joint_names)
    out = tmp_path / "corrected.csv"
    assert main(["compensate", str(model_file), str(program), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "8 ok" in text
    assert "program order" in text
    table = pd.read_csv(out)
    assert list(table.columns) == [
        *rx160.joint_names, "residual_mm", "residual_deg", "status", "nominal_mm",
        "nominal_deg", "note",
    ]  # fmt: skip
    assert len(table) == 8
    assert (table["status"] == "ok").all()
    assert table["residual_mm"].max() < 1e-3
    assert table["nominal_mm"].min() > 0.05
    # the same program as flange poses
    with torch.no_grad():
        T = rx160.fk(q_nom)
    quat = matrix_to_quat(T[:, :3, :3])
    poses = pd.DataFrame({"x": T[:, 0, 3], "y": T[:, 1, 3], "z": T[:, 2, 3]})
    for k, c in enumerate(("qw", "qx", "qy", "qz")):
        poses[c] = quat[:, k].numpy()
    poses.to_csv(tmp_path / "poses.csv", index=False)
    argv = ["compensate", str(model_file), str(tmp_path / "poses.csv"), "--out", str(out)]
    assert main([*argv, "--approach", "mid"]) == 0
    assert "flange poses" in capsys.readouterr().out
    assert len(pd.read_csv(out)) == 8
    # a pose 10 m away: no nominal joints, so none are said to be kept
    poses.loc[2, "x"] = 10.0
    poses.to_csv(tmp_path / "poses.csv", index=False)
    assert main([*argv, "--approach", "mid"]) == 0
    text = capsys.readouterr().out
    assert "1 row(s) no_nominal_solution, joints left empty: row 3" in text
    assert pd.read_csv(out).loc[2, rx160.joint_names].isna().all()


def test_cli_tells_how_to_state_an_assumed_payload_in_the_program(tmp_path, capsys, rx160):
    """A compliant model on a program without a payload column: the note names the
    PROGRAM column that states it, not a Python argument the user cannot pass."""
    model_file = save_model(tmp_path / "model.pt", _real(rx160))
    q_nom = _program(rx160, 4, seed=3)
    program = write_joint_table(tmp_path / "program.csv", q_nom, rx160.joint_names)
    argv = ["compensate", str(model_file), str(program), "--out", str(tmp_path / "c.csv")]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "solved at 0 kg; a payload column [kg] in PROGRAM states it" in text
    assert "Conditions(" not in text
    # with the column, nothing is assumed
    table = pd.read_csv(program)
    table["payload"] = 5.0
    table.to_csv(program, index=False)
    assert main(argv) == 0
    assert "0 kg" not in capsys.readouterr().out


def test_cli_hybrid_model_file(tmp_path, capsys, rx160):
    torch.manual_seed(0)
    q_box = rx160.sample_q(64, torch.Generator().manual_seed(1))
    hybrid = HybridFK.build(
        _real(rx160), InputBox.from_data(q_box, None, fade=0.2), "mlp:8x2", None,
        torch.full((3,), 1e-3, dtype=F64),
    ).eval()  # fmt: skip
    model_file = save_hybrid(tmp_path / "hybrid.pt", hybrid)
    program = write_joint_table(tmp_path / "p.csv", _program(rx160, 4), rx160.joint_names)
    out = tmp_path / "c.csv"
    assert main(["compensate", str(model_file), str(program), "--out", str(out)]) == 0
    assert "4 ok" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("x,y,z\n1,0,1\n", "needs the flange orientation"),
        ("joint_1,joint_2,joint_3,joint_4,joint_5,joint_6\n0,0,0,0,3,0\n", "joint limits"),
        # 9 on joint_5 (limits -1.83, 2.09 rad) is 9 degrees: named as a pose table does
        ("joint_1,joint_2,joint_3,joint_4,joint_5,joint_6\n0,0,0,0,9,0\n", "looks like degrees"),
        # a UR joint program for the RX160 model: its joints are named, not x, y, z
        (
            "shoulder_pan_joint,shoulder_lift_joint,elbow_joint\n0,0,0\n",
            "missing joint column(s) 'joint_1', 'joint_2'",
        ),
    ],
)
def test_cli_bad_programs_are_one_line_errors(tmp_path, capsys, rx160, content, message):
    model_file = save_model(tmp_path / "model.pt", _real(rx160))
    (tmp_path / "p.csv").write_text(content)
    argv = ["compensate", str(model_file), str(tmp_path / "p.csv"), "--out", "c.csv"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err
    assert err.count("\n") == 1


def test_backlash_sides_are_those_of_the_corrected_program(rx160):
    """The approach side of a backlash joint is the sign of the *corrected* move: rows are
    re-solved until the sides agree; a joint that turns around by less than the play
    cannot be compensated from the program order and is reported."""
    real = _real(rx160)  # backlash 0.6 mrad on joint_5
    j5 = rx160.joint_names.index("joint_5")
    q0 = _program(rx160, 1, seed=7)[0]
    steps = torch.zeros(5, rx160.dof, dtype=F64)
    steps[:, 0] = 0.05  # joint 1 moves every row
    steps[1, j5], steps[2, j5], steps[3, j5], steps[4, j5] = -0.05, 2e-5, 2e-5, -0.05
    q_nom = q0 + steps.cumsum(0)
    base, tool = _frames(real)
    comp = compensate(real, rx160, base=base, tool=tool, q_nominal=q_nom, cond=_cond(q_nom))
    # row 2 turns joint 5 around by 0.02 mrad (< play): no consistent side
    assert comp.status[2] == "approach_conflict"
    assert "turns around" in comp.note[2]
    ok = comp.ok
    side = approach_direction(torch.where(ok[:, None], comp.q, q_nom))
    cond = Conditions(payload=torch.zeros(5, dtype=F64), direction=side)
    with torch.no_grad():
        err = pose_error(base @ rx160.fk(q_nom) @ tool, real(comp.q, cond)).position_mm
    assert float(err[ok].max()) < 1e-3, err


def test_cli_keeps_the_program_columns_and_warns_on_a_corrected_program(tmp_path, capsys, rx160):
    """A joint program's other columns (line numbers, speeds, payload) are copied to
    CORRECTED as they are (before: dropped, only the joints came back); a CORRECTED file
    given as PROGRAM again is warned about (its joints would be corrected twice)."""
    model = save_model(tmp_path / "m.pt", _real(rx160))
    q = _program(rx160, n=5)
    extra = pd.DataFrame({"line": [10, 20, 30, 40, 50], "speed": ["0.25", "0.5", "1", "v200", ""]})
    write_joint_table(tmp_path / "p.csv", q, rx160.joint_names, extra)
    argv = ["compensate", str(model), str(tmp_path / "p.csv"), "--no-progress", "--out"]
    assert main([*argv, str(tmp_path / "c.csv")]) == 0
    out = capsys.readouterr().out
    assert "copied to the output" in out, out
    corrected = pd.read_csv(tmp_path / "c.csv", dtype=str, keep_default_na=False)
    assert corrected["line"].tolist() == ["10", "20", "30", "40", "50"]
    assert corrected["speed"].tolist() == ["0.25", "0.5", "1", "v200", ""]
    assert list(corrected.columns).index("speed") < list(corrected.columns).index("status")
    assert "warning" not in out
    assert (
        main(
            [
                "compensate",
                str(model),
                str(tmp_path / "c.csv"),
                "--no-progress",
                "--out",
                str(tmp_path / "c2.csv"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "is a compensate output" in out, out
    again = pd.read_csv(tmp_path / "c2.csv")
    assert list(again.columns).count("status") == 1
    # CSV in, Parquet out: a column of numbers stays numbers, text stays text
    assert main([*argv, str(tmp_path / "c.parquet")]) == 0
    typed = pd.read_parquet(tmp_path / "c.parquet")
    assert typed["line"].dtype == "float64"
    assert typed["speed"].tolist() == ["0.25", "0.5", "1", "v200", ""]


def test_cli_controller_running_the_exported_geometry(tmp_path, capsys, rx160):
    """A controller that runs the exported calibrated geometry (DH YAML): a program
    computed with that table, compensated with --controller TABLE, puts the model at the
    table's poses (B · table FK · X); without --controller the geometry is corrected a
    second time and the model misses them by about the geometric correction."""
    from hybrid_pk import Robot
    from hybrid_pk.ik.compensation import nearest_branch

    real = _real(rx160, "link_length:joint_3=4e-4,0,-3e-4", "axis_misalignment:joint_4=5e-4,0")
    model = save_model(tmp_path / "m.pt", real)
    table = tmp_path / "geometry.yaml"
    assert main(["export", str(model), "--format", "dh", "--out", str(table)]) == 0
    controller = Robot.from_dh(table)
    start = torch.tensor([0.0, 0.3, 1.2, 0.0, 0.9, 0.0], dtype=F64)
    with torch.no_grad():
        line = controller.fk(start).repeat(8, 1, 1)
    line[:, 0, 3] += torch.linspace(0.0, 0.1, 8, dtype=F64)
    q = nearest_branch(controller, line, reference=start)
    write_joint_table(tmp_path / "p.csv", q, rx160.joint_names)
    B, X = _frames(real)
    with torch.no_grad():
        intended = B @ controller.fk(q) @ X
    argv = ["compensate", str(model), str(tmp_path / "p.csv"), "--no-progress", "--out"]
    missed = {}
    for name, flags in (("controller", ["--controller", str(table)]), ("nominal", [])):
        assert main([*argv, str(tmp_path / f"{name}.csv"), *flags]) == 0
        corrected = torch.tensor(pd.read_csv(tmp_path / f"{name}.csv")[rx160.joint_names].values)
        with torch.no_grad():
            cond = Conditions(
                payload=_cond(corrected).payload, direction=approach_direction(corrected)
            )
            reached = real(corrected, cond)
        missed[name] = float(pose_error(intended, reached).position_mm.max())
    assert "program joints mean" in capsys.readouterr().out  # the controller's, not nominal
    assert missed["controller"] < 1e-3, missed  # the ok tolerance
    assert missed["nominal"] > 0.1, missed  # the geometry corrected twice
    table.with_suffix(".csv").write_text("name,a,alpha,d,theta,type,lower,upper\n")
    assert main([*argv, str(tmp_path / "x.csv"), "--controller", str(table.with_suffix(".csv"))])
    assert "a CSV DH table does not state its convention" in capsys.readouterr().err


def test_cli_controller_file_that_holds_no_kinematics(tmp_path, capsys, rx160):
    """--controller names a URDF or a DH YAML table: a JSON file is one line saying so
    (before: yourdfpy's parser noise, then 'cannot parse URDF: Invalid input object:
    NoneType'); a cut-off URDF is one line naming its line and column."""
    model = save_model(tmp_path / "m.pt", _real(rx160))
    write_joint_table(tmp_path / "p.csv", _program(rx160, 4), rx160.joint_names)
    argv = ["compensate", str(model), str(tmp_path / "p.csv"), "--out", str(tmp_path / "o.csv")]
    (tmp_path / "c.json").write_text('{"format": "x"\n')
    cut = tmp_path / "c.urdf"
    cut.write_text('<robot name="r">\n  <link name="a"/>\n  <joint name="j">')
    for controller, text in (
        ("c.json", "--controller: {}: expected the controller's kinematics, a URDF (.urdf"),
        ("c.urdf", "{}, line 3, column 19: not well-formed XML (premature end of data"),
    ):
        path = tmp_path / controller
        assert main([*argv, "--controller", str(path)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert text.format(path) in err, err
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize(
    ("cell", "message"),
    [("abc", "row 2, column 'payload': text 'abc'"), ("", "row 2, column 'payload': empty"),
     ("-1", "a payload is a mass >= 0 kg"), ("5000", "looks like grams")],
)  # fmt: skip
def test_cli_bad_payload_cells_of_a_program(tmp_path, capsys, rx160, cell, message):
    """A program's payload column is checked as a measured table's is: one line with
    file, row and column (before: pandas' 'Unable to parse string' without a place, an
    empty cell made its row 'unreachable ... nan the correction needs', and -1 or 5000 kg
    were used as they stood)."""
    model = save_model(tmp_path / "m.pt", _real(rx160))
    payload = pd.DataFrame({"payload": ["2", cell, "2"]})
    write_joint_table(tmp_path / "p.csv", _program(rx160, n=3), rx160.joint_names, payload)
    argv = ["compensate", str(model), str(tmp_path / "p.csv"), "--no-progress", "--out"]
    assert main([*argv, str(tmp_path / "c.csv")]) != 0
    err = capsys.readouterr().err
    assert message in err, err
    assert err.count("\n") == 1


def test_a_pose_program_row_beyond_any_reach_says_in_which_frame(rx160):
    """A flange pose 10 m from the robot's root (a tracker-frame or mm row in a pose
    program): no_nominal_solution, and the note gives its distance beside the arm's reach
    and the frame flange poses are in (before: only 'the nominal model has no solution');
    a reachable row has no such note."""
    real = _real(rx160)
    base, tool = _frames(real)
    with torch.no_grad():
        targets = rx160.fk(_program(rx160, n=2, seed=3))
    targets[1, :3, 3] += torch.tensor([10.0, 0.0, 0.0], dtype=F64)
    comp = compensate(real, rx160, base=base, tool=tool, targets=targets, cond=_cond(targets[:, 0]))
    assert comp.status[1] == "no_nominal_solution"
    assert "beyond the" in comp.note[1], comp.note[1]
    assert "robot base frame" in comp.note[1]
    assert "beyond the" not in comp.note[0]


def test_help_states_the_approach_default_compensate_uses(capsys):
    # compensate takes backlash sides from the program's order; its --approach help said
    # "default: the mid-play model", which is ik's default (shared help text)
    with pytest.raises(SystemExit):
        main(["compensate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "default: the sides of the corrected program's own moves" in text
    assert "default: the mid-play model" not in text
    with pytest.raises(SystemExit):
        main(["ik", "--help"])
    assert "default: the mid-play model" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("flag", ["--box", "--tol-mm", "--tol-deg"])
def test_cli_refuses_nan_box_and_tolerances(tmp_path, capsys, rx160, flag):
    """NaN passes 'box <= 0': before, --box nan reached the solver and --tol-mm nan gave
    'IKOptions: tol_mm must be > 0, got IKOptions(tol_mm=nan, ...)'; now the flags' own
    one-line error that 0 and negative values already had."""
    model_file = save_model(tmp_path / "model.pt", _real(rx160))
    program = write_joint_table(tmp_path / "p.csv", _program(rx160, 2), rx160.joint_names)
    argv = ["compensate", str(model_file), str(program), "--out", str(tmp_path / "c.csv")]
    assert main([*argv, flag, "nan"]) == 2
    err = capsys.readouterr().err
    assert "--box, --tol-mm and --tol-deg must be positive, got" in err
    assert len([ln for ln in err.splitlines() if "error:" in ln]) == 1

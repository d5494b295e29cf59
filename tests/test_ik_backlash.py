"""IK on a model with backlash, without row order: under a stated approach direction
(API ``approach=``, CLI ``--approach``) or, by default, the mid-play model, said so."""

from __future__ import annotations

import re
import warnings

import pandas as pd
import pytest
import torch

from hybrid_pk.cli.main import main
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.errors import HybridPKError
from hybrid_pk.geometry import matrix_to_quat
from hybrid_pk.ik import IKAssumption, solve_ik, solve_ik_two_stage
from hybrid_pk.io.model_file import save_model

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
PLAY = 3e-3  # [rad] full play of joint_3: +-1.5 mrad, about 1 mm at the flange
TOL = 1e-3  # [mm] and [deg]


@pytest.fixture(scope="module")
def model(rx160):
    m = ExtendedModel(
        rx160,
        [
            make_effect(rx160, "backlash:joint_3", PLAY),
            make_effect(rx160, "joint_offset:joint_2", 1e-3),
        ],
        base=torch.eye(4, dtype=F64),
        tool=torch.eye(4, dtype=F64),
    )
    return m.requires_grad_(False)


def _direction(robot, n: int, side: float) -> torch.Tensor:
    d = torch.zeros(n, robot.dof, dtype=F64)
    d[:, robot.joint_names.index("joint_3")] = side
    return d


def _targets(model, side: float, n: int = 4):
    robot = model.robot
    q = robot.sample_q(n, torch.Generator().manual_seed(11)) * 0.7
    with torch.no_grad():
        return model(q, Conditions(direction=_direction(robot, n, side)))


def _errors(model, q: torch.Tensor, T: torch.Tensor, side: float) -> tuple[float, float]:
    """Largest position [mm] and orientation [deg] error of ``q`` under ``side``,
    recomputed here from the model's forward kinematics."""
    with torch.no_grad():
        T_q = model(q, Conditions(direction=_direction(model.robot, len(q), side)))
    pos = (T_q[:, :3, 3] - T[:, :3, 3]).norm(dim=-1) * 1e3
    R = T_q[:, :3, :3].transpose(-1, -2) @ T[:, :3, :3]
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return float(pos.max()), float(torch.rad2deg(torch.arccos(cos)).max())


def _solutions(result, T):
    target, slot = result.valid.nonzero(as_tuple=True)
    return result.q[target, slot], T[target]


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_two_stage_solves_under_the_stated_direction(model, side):
    T = _targets(model, side)
    cheap = ExtendedModel(model.robot, base=torch.eye(4, dtype=F64), tool=torch.eye(4, dtype=F64))
    with warnings.catch_warnings():
        warnings.simplefilter("error", IKAssumption)  # a stated direction assumes nothing
        result = solve_ik_two_stage(cheap, model, T, seeds=32, approach={"joint_3": int(side)})
    assert result.n_failed == 0
    q, T_sol = _solutions(result, T)
    pos, ori = _errors(model, q, T_sol, side)
    assert pos <= TOL, pos
    assert ori <= TOL, ori
    # The direction is really used: the same joints miss the target on the other side.
    assert _errors(model, q, T_sol, -side)[0] > 0.1
    assert result.info["assumed"] == [
        f"backlash approach as stated: joint_3 {'positive' if side > 0 else 'negative'}"
    ]


def test_without_a_direction_the_mid_play_model_is_solved_and_said(model):
    T = _targets(model, 0.0)
    with pytest.warns(IKAssumption, match="backlash on joint_3 .* mid-play model"):
        result = solve_ik_two_stage(ExtendedModel(model.robot), model, T, seeds=32)
    q, T_sol = _solutions(result, T)
    assert result.n_failed == 0
    pos, ori = _errors(model, q, T_sol, 0.0)
    assert pos <= TOL, pos
    assert ori <= TOL, ori
    assert "mid-play" in result.info["assumed"][0]


def test_solve_ik_takes_the_direction_too(model):
    T = _targets(model, -1.0, n=2)
    result = solve_ik(model, T, seeds=32, approach="-")
    q, T_sol = _solutions(result, T)
    assert len(q) >= 2
    assert _errors(model, q, T_sol, -1.0)[0] <= TOL


@pytest.mark.parametrize(
    ("approach", "message"),
    [
        ({"joint_5": 1}, "'joint_5' has no backlash in this model (backlash joints: joint_3)"),
        ({"joint_3": 2}, "expected +1, -1 or 0"),
        ("sideways", "expected '+', '-' or 'mid'"),
        (torch.ones(3), "expected a (6,) or (1, 6) tensor"),
    ],
)
def test_a_wrong_direction_is_a_clear_error(model, approach, message):
    T = _targets(model, 1.0, n=1)
    with pytest.raises(HybridPKError, match=re.escape(message)):
        solve_ik(model, T, seeds=4, approach=approach)


def test_the_model_without_a_direction_says_what_to_pass(model):
    q = torch.zeros(1, model.robot.dof, dtype=F64)
    with pytest.raises(HybridPKError, match="backlash on joint_3 needs the approach direction"):
        model(q, Conditions())


def _write_targets(path, T):
    quat = matrix_to_quat(T[:, :3, :3])
    cols = {"x": T[:, 0, 3], "y": T[:, 1, 3], "z": T[:, 2, 3]}
    cols.update({c: quat[:, k] for k, c in enumerate(("qw", "qx", "qy", "qz"))})
    pd.DataFrame({k: v.numpy() for k, v in cols.items()}).to_csv(path, index=False)


@pytest.mark.parametrize(("flag", "side"), [("joint_3=+", 1.0), ("-", -1.0), (None, 0.0)])
def test_cli_solves_under_the_stated_direction(model, tmp_path, capsys, flag, side):
    T = _targets(model, side, n=3)
    save_model(tmp_path / "model.pt", model)
    _write_targets(tmp_path / "targets.csv", T)
    argv = ["ik", tmp_path / "model.pt", tmp_path / "targets.csv", "--out", tmp_path / "s.csv"]
    argv += ["--seeds", "32"] + ([] if flag is None else ["--approach", flag])
    assert main([str(a) for a in argv]) == 0
    out = capsys.readouterr().out
    frame = pd.read_csv(tmp_path / "s.csv")
    assert sorted(set(frame["target"])) == [0, 1, 2]
    q = torch.tensor(frame[list(model.robot.joint_names)].to_numpy(), dtype=F64)
    pos, ori = _errors(model, q, T[torch.tensor(frame["target"].to_numpy())], side)
    assert pos <= TOL, pos
    assert ori <= TOL, ori
    if flag is None:
        assert "note: backlash on joint_3 without an approach direction" in out
        assert "--approach" in out
    else:
        assert "note: backlash approach as stated: joint_3 " in out


def test_cli_direction_for_a_model_without_backlash_is_one_line_error(rx160, tmp_path, capsys):
    save_model(
        tmp_path / "m.pt", ExtendedModel(rx160, [make_effect(rx160, "joint_offset:joint_2")])
    )
    _write_targets(tmp_path / "t.csv", torch.eye(4, dtype=F64)[None])
    argv = ["ik", tmp_path / "m.pt", tmp_path / "t.csv", "--out", tmp_path / "s.csv"]
    assert main([str(a) for a in [*argv, "--approach", "+"]]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "no backlash effect" in err

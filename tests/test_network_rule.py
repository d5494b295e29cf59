"""A hybrid moved to a new set-up keeps its networks only where they carry over (issue
27): hybrid_pk.pipelines.network_rule, reached through calibrate --refit and evaluate."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.cli.main import main
from hybrid_pk.data import write_table
from hybrid_pk.effects import ExtendedModel, conditions_from_data
from hybrid_pk.evaluation.metrics import row_errors
from hybrid_pk.geometry import rpy_to_matrix, so3_exp, transform
from hybrid_pk.io.hybrid_file import networks_used, predict_poses, save_hybrid
from hybrid_pk.io.model_file import load_model
from hybrid_pk.pipelines.flange_frames import (
    BLOCKS,
    MAX_FOLDS,
    FlangeRows,
    fit_flange_frames,
    fold_of_rows,
    frames_at,
)
from hybrid_pk.pipelines.refit import refit
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.training import train_hybrid
from tests.helpers import RUN_SEED, middle_q, run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64
NETS = {"position_net": "mlp:16x2", "orientation_net": "mlp:16x2", "refine_net": "mlp:8x2"}
REFIT_ROWS = 50  # the re-fit rows
NOISE_MM = 0.01


def _campaign(robot, n: int, seed: int, effect: str, base=None, tool=None):
    """``n`` rows from the middle half of each joint's range (inside the training rows'
    coverage), measured with ``effect`` ('' none), in frames ``base``/``tool`` (None:
    the robot's root frame at the flange)."""
    q = middle_q(robot, n, seed, 0.5)
    data, _ = simulate_campaign(
        robot, None, effect, poses=q, noise_mm=NOISE_MM, known_frames=base is None,
        temperature_range=None, seed=seed, base=base, tool=tool,
    )  # fmt: skip
    return data


@pytest.fixture(scope="module")
def setups(ur10, tmp_path_factory):
    """A hybrid trained on a first set-up whose rows carry an unmodelled elbow
    compliance (0.3-0.6 mm at the flange), and a re-stationed set-up (tracker moved,
    target re-mounted) measured with and without that error."""
    rng = run_rng("network-rule")
    stiffness = float(rng.uniform(2e-5, 4e-5))  # [rad/Nm]
    effect = f"joint_compliance:elbow_joint={stiffness}"
    first = _campaign(ur10, 500, 1, effect)
    physics = ExtendedModel(ur10)  # frames known, the compliance not modelled
    result = train_hybrid(first, physics, model=NETS, max_epochs=80, progress=False, seed=0)
    path = tmp_path_factory.mktemp("rule") / "hybrid.pt"
    save_hybrid(path, result.hybrid)
    rpy = torch.as_tensor(rng.uniform(-0.3, 0.3, 3), dtype=F64)
    base = transform(rpy_to_matrix(rpy), torch.as_tensor(rng.uniform(-2, 2, 3), dtype=F64))
    tool = transform(torch.eye(3, dtype=F64), torch.tensor([0.01, -0.02, 0.08], dtype=F64))
    moved = {
        name: _campaign(ur10, REFIT_ROWS + 300, 2, e, base, tool)
        for name, e in (("robot's own", effect), ("first set-up's", ""))
    }
    return path, moved


def _split(data):
    pick = torch.zeros(data.n, dtype=torch.bool)
    pick[:REFIT_ROWS] = True
    return data.subset(pick), data.subset(~pick)


def _physics(path, fit_rows):
    """The model file's extended model alone, its frames re-fitted on ``fit_rows``."""
    alone = replace(load_model(path), networks=None)
    return replace(alone, model=refit(alone, fit_rows, "frames").model)


def _mean_mm(loaded, data) -> float:
    T = predict_poses(loaded, data, conditions_from_data(data))
    return float(row_errors(T, data)[0].mean())


def test_networks_that_learned_the_robots_own_error_are_kept_on_a_new_setup(setups):
    """The compliance is the robot's: it moves with it, and the networks that learned it
    beat the physics on the re-fit rows held out, and on the judged rows."""
    path, moved = setups
    fit_rows, judged = _split(moved["robot's own"])
    res = refit(load_model(path), fit_rows, "frames")
    assert res.verdict is not None
    assert res.verdict.used, res.verdict
    assert res.verdict.gain_mm > 2 * res.verdict.se_mm > 0
    assert res.verdict.reached == REFIT_ROWS  # inside the training rows' joints
    kept = replace(load_model(path), model=res.model, networks=res.networks)
    hybrid, physics = _mean_mm(kept, judged), _mean_mm(_physics(path, fit_rows), judged)
    assert hybrid < 0.9 * physics, (hybrid, physics, res.verdict)


def test_networks_that_learned_an_error_of_the_old_setup_fall_back_to_the_physics(
    setups, tmp_path, capsys
):
    """The error belonged to the first set-up (absent after re-stationing): the networks
    would add it back, so the re-fit marks them unused, evaluate uses the extended model
    (the same errors as a re-fit of the physics alone) and says so, in its output and
    its JSON."""
    path, moved = setups
    fit_rows, judged = _split(moved["first set-up's"])
    refit_file, judge_file = (
        write_table(tmp_path / "refit.csv", fit_rows),
        write_table(tmp_path / "judge.csv", judged),
    )
    out = tmp_path / "moved.pt"
    args = ["calibrate", str(refit_file), "--model", str(path), "--refit", "frames"]
    assert main([*args, "--out", str(out), "--no-urdf"]) == 0
    assert "residual networks NOT used" in capsys.readouterr().out
    loaded = load_model(out)
    assert loaded.has_networks
    assert not networks_used(loaded)
    assert main(["evaluate", str(out), str(judge_file), "--json", str(tmp_path / "e.json")]) == 0
    printed = capsys.readouterr().out
    assert "residual networks NOT used" in printed
    assert "(not used)" in printed
    summary = json.loads((tmp_path / "e.json").read_text())
    rule = summary["networks"]
    assert rule["used"] is False
    assert rule["rows"] == REFIT_ROWS
    assert rule["gain_mm"] < 0
    assert "standard errors" in rule["rule"]
    physics = _mean_mm(_physics(path, fit_rows), judged)
    assert summary["position_mm"]["mean"] == pytest.approx(physics, rel=1e-6)


def test_rows_where_no_network_acts_say_the_rows_cannot_show_it(setups, ur10):
    """Re-fit rows with joint 1 beyond the range the networks were trained on (the middle
    half): no stage acts there, so the verdict says the rows cannot show whether the
    networks carry, not that they lost to the physics by nothing."""
    from hybrid_pk.pipelines.network_rule import verdict_line

    path, _ = setups
    rng = run_rng("network-rule-unreached")
    q = middle_q(ur10, REFIT_ROWS, int(rng.integers(1 << 20)), 0.5)
    lo, hi = ur10.joint_limits
    side = float(rng.choice([-1.0, 1.0]))  # an end quarter of joint 1, either side
    mid, half = float(lo[0] + hi[0]) / 2, float(hi[0] - lo[0]) / 2
    q[:, 0] = mid + side * half * torch.empty(REFIT_ROWS, dtype=F64).uniform_(0.6, 0.95)
    data, _ = simulate_campaign(
        ur10, None, "", poses=q, noise_mm=NOISE_MM, known_frames=True,
        temperature_range=None, seed=3,
    )  # fmt: skip
    res = refit(load_model(path), data, "frames")
    assert res.verdict.reached == 0, res.verdict
    assert not res.verdict.used
    assert "act on none of the 50 re-fit rows" in verdict_line(res.verdict.to_json())


@pytest.mark.parametrize("error", ["robot's own", "first set-up's"])
def test_evaluate_fit_frames_judges_the_networks_on_the_rows_it_fits_the_frames_to(
    setups, error, tmp_path, capsys
):
    """``evaluate --fit-frames`` on a new set-up fits the frames there as ``calibrate
    --refit frames`` does, so the same rule decides on those rows whether the networks
    are used: kept for the robot's own error (the hybrid beats the physics), dropped
    for the old set-up's (the errors are the physics' with its frames fitted there)."""
    path, moved = setups
    data = moved[error]
    file, out = write_table(tmp_path / "new.csv", data), tmp_path / "e.json"
    assert main(["evaluate", str(path), str(file), "--fit-frames", "--json", str(out)]) == 0
    printed, summary = capsys.readouterr().out, json.loads(out.read_text())
    rule = summary["networks"]
    assert rule["rows"] == data.n
    physics = _mean_mm(_physics(path, data), data)
    if error == "robot's own":
        assert rule["used"] is True, rule
        assert "residual networks used" in printed
        assert summary["position_mm"]["mean"] < 0.9 * physics
    else:
        assert rule["used"] is False, rule
        assert "residual networks NOT used" in printed
        assert summary["position_mm"]["mean"] == pytest.approx(physics, rel=1e-6)


def test_the_folds_leave_one_row_out_up_to_their_cap():
    fold, folds = fold_of_rows(REFIT_ROWS)
    assert folds == REFIT_ROWS
    assert torch.equal(fold, torch.arange(REFIT_ROWS))
    fold, folds = fold_of_rows(10 * MAX_FOLDS + 3)
    assert folds == MAX_FOLDS
    assert int(torch.bincount(fold).min()) == 10


@pytest.mark.parametrize("orientation", [True, False])
@pytest.mark.parametrize("weighted", [True, False])
def test_the_frames_jacobian_in_closed_form_is_forward_modes(orientation, weighted):
    """``FlangeRows.jacobian`` against forward mode through ``FlangeRows.residual``
    (float64, random frames, offsets of tens of mm and mrad, a subset of the rows, robust
    weights or none, position only or full poses): the same to round-off."""
    g = torch.Generator().manual_seed(7 + 2 * orientation + weighted)

    def frames(k: int) -> torch.Tensor:
        w, p = torch.randn(k, 3, generator=g, dtype=F64), torch.randn(k, 3, generator=g, dtype=F64)
        return transform(so3_exp(w), p)

    E, T, (B0, X0) = frames(24), frames(24), frames(2)
    weights = torch.rand(24, generator=g, dtype=F64) + 0.5 if weighted else None
    rows = FlangeRows(E, T[:, :3, 3], T[:, :3, :3] if orientation else None, 0.02, 1e-4, weights)
    theta = 40 * torch.randn(12, generator=g, dtype=F64)
    picked = torch.arange(1, 24, 3)
    r, J = rows.jacobian(theta, B0, X0, picked)
    r_fwd, J_fwd = jacobian(lambda t: rows.residual(t, B0, X0, picked), theta)
    assert J.shape == (picked.numel() * (6 if orientation else 3), 12)
    assert torch.equal(r, r_fwd)
    assert torch.allclose(J, J_fwd, rtol=1e-12, atol=1e-12 * float(J_fwd.abs().max()))


def test_the_frames_fit_recovers_the_frames_of_exact_rows(ur10):
    """Noise-free rows of known frames: the fit from frames a few mm and mrad off returns
    them; a block left out of ``free`` stays where it starts."""
    rng = run_rng("flange-frames")
    E = ur10.fk(middle_q(ur10, 30, 3, 0.5))
    B = transform(rpy_to_matrix(torch.as_tensor(rng.uniform(-1, 1, 3))), torch.ones(3, dtype=F64))
    X = transform(rpy_to_matrix(torch.tensor([0.0, 0.1, 0.2], dtype=F64)), torch.ones(3) * 0.05)
    T = B @ E @ X
    rows = FlangeRows(E, T[:, :3, 3], T[:, :3, :3], 0.01, 1e-5)
    off = torch.as_tensor(rng.uniform(-3, 3, 12))
    B0, X0 = frames_at(off, B, X)
    B1, X1 = fit_flange_frames(rows, B0, X0, BLOCKS)
    assert torch.allclose(B1, B, atol=1e-9)
    assert torch.allclose(X1, X, atol=1e-9)
    B2, X2 = fit_flange_frames(rows, B0, X0, BLOCKS[:2])
    assert torch.equal(X2, X0)
    assert not torch.allclose(B2, B0, atol=1e-6)


@pytest.mark.slow
def test_networks_gated_beyond_joint_1_are_carried_where_the_new_rows_show_they_hold(
    ur10, tmp_path
):
    """A gravity-driven compliance (it turns with the arm): networks trained on joint 1's
    lower half are gated beyond it, and a new set-up measured only on its upper half
    (frames moved) gives them no row as stored. The second look lifts their joint gates:
    the re-fit rows held out show the correction carries, so it is kept (carried) and
    the judged rows gain on the physics; a compliance the robot does not have there
    (the first set-up's error, absent after moving) leaves the networks unused."""
    rng = run_rng("network-rule-carried")
    joint, lo = (("shoulder_lift_joint", 5e-6), ("elbow_joint", 2e-5))[int(rng.integers(2))]
    effect = f"joint_compliance:{joint}={lo * float(rng.uniform(1.5, 3.0)):.3g}"
    data, _ = simulate_campaign(
        ur10, 1200, effect, noise_mm=0.002, known_frames=True, temperature_range=None,
        seed=int(rng.integers(1 << 20)),
    )  # fmt: skip
    low = data.q[:, 0] < data.q[:, 0].median()
    nets = {"position_net": "mlp:64x2", "orientation_net": "mlp:64x2", "refine_net": "mlp:64x2"}
    result = train_hybrid(
        data.subset(torch.nonzero(low)[:, 0]), ExtendedModel(ur10), model=nets,
        max_epochs=80, progress=False, seed=0,
    )  # fmt: skip
    path = tmp_path / "hybrid.pt"
    save_hybrid(path, result.hybrid)
    rpy = torch.as_tensor(rng.uniform(-0.3, 0.3, 3), dtype=F64)
    base = transform(rpy_to_matrix(rpy), torch.as_tensor(rng.uniform(-2, 2, 3), dtype=F64))
    tool = transform(torch.eye(3, dtype=F64), torch.tensor([0.01, -0.02, 0.08], dtype=F64))
    q_new = data.q[~low][: REFIT_ROWS + 300]
    where = f"seed {RUN_SEED}: {effect}"
    for error, kept in ((effect, True), ("", False)):
        moved, _ = simulate_campaign(
            ur10, None, error, poses=q_new, noise_mm=0.002, known_frames=False,
            temperature_range=None, seed=5, base=base, tool=tool,
        )  # fmt: skip
        fit_rows, judged = _split(moved)
        res = refit(load_model(path), fit_rows, "frames")
        assert res.verdict.used is kept, (where, error, res.verdict)
        assert res.verdict.carried is kept, (where, error, res.verdict)
        if not kept:  # the second look's numbers stay beside the verdict
            assert res.verdict.lifted["reached"] == REFIT_ROWS, res.verdict
            assert "with their joint gates lifted" in res.verdict.line()
        if kept:
            assert res.verdict.z > 2.0  # the second look's stricter z
            moved_model = replace(load_model(path), model=res.model, networks=res.networks)
            hybrid = _mean_mm(moved_model, judged)
            physics = _mean_mm(_physics(path, fit_rows), judged)
            assert hybrid < 0.9 * physics, (where, hybrid, physics, res.verdict)

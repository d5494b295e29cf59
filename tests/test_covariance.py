"""The covariance of a fit from the SVD of its Jacobian: correlations stay in [-1, 1]
when parameters are over-determined, and the warning names the groups of parameters the
data cannot separate."""

from __future__ import annotations

import math

import pytest
import torch

from hybrid_pk.calibration.covariance import svd_covariance, undetermined_groups
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.calibration.frames import FramePriors
from hybrid_pk.cli.calibrate_output import MAX_CONDITION, condition_warning
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64


def _jacobian(seed: int, m: int = 300, n: int = 8) -> torch.Tensor:
    """Random columns whose sizes span 8 decades (as mm, mrad and µrad/Nm do)."""
    g = torch.Generator().manual_seed(seed)
    scales = 10 ** (torch.rand(n, generator=g, dtype=F64) * 8 - 4)
    return torch.randn(m, n, generator=g, dtype=F64) * scales


@pytest.mark.parametrize("seed", range(12))
def test_a_parameter_twice_keeps_correlations_in_range(seed):
    """Column 1 is column 0 at another scale (the same direction): the pseudo-inverse of
    J^T J gave |r| up to 1e295 on these; the SVD gives r = +-1 for the pair and leaves
    the other parameters' covariance as in the fit without the duplicate."""
    J = _jacobian(seed)
    J[:, 1] = J[:, 0] * 37.5
    svd = svd_covariance(J, J.shape[0], 1.0)
    cov, corr = svd["cov"], svd["corr"]
    assert float(corr.abs().max()) <= 1.0
    assert abs(float(corr[0, 1])) == pytest.approx(1.0, abs=1e-9)
    alone = svd_covariance(J[:, [0, *range(2, 8)]], J.shape[0], 1.0)["cov"]
    torch.testing.assert_close(cov[2:, 2:], alone[1:, 1:], rtol=1e-8, atol=0)
    assert torch.linalg.eigvalsh(cov).min() >= -1e-12 * cov.diagonal().max()


def _unit_svd(J: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    svd = svd_covariance(J, J.shape[0], 1.0)
    return svd["singular_values"], svd["singular_vectors"]


def test_groups_of_a_three_way_and_a_two_way_trade_off():
    """Parameters 0 + 1 + 2 (a sum, no pair correlated at 0.999) and 4 ~ 6 are not
    determined; two exact trade-offs come back apart whatever basis the SVD picks."""
    J = _jacobian(3)
    unit = J / J.norm(dim=0)
    J[:, 2] = -(unit[:, 0] + unit[:, 1]) * 1e3  # each member an even part of the sum
    J[:, 6] = J[:, 4] * 1e-3
    s, vh = _unit_svd(J)
    assert undetermined_groups(s, vh, MAX_CONDITION) == [[0, 1, 2], [4, 6]]
    turn = torch.randn(2, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    mixed = torch.linalg.qr(turn).Q @ vh[-2:]  # another basis of the same two trade-offs
    assert undetermined_groups(s, torch.cat([vh[:-2], mixed]), MAX_CONDITION) == [
        [0, 1, 2],
        [4, 6],
    ]
    assert undetermined_groups(*_unit_svd(_jacobian(3)), MAX_CONDITION) == []


def test_the_warning_names_the_group_of_an_over_parameterised_fit(rx160):
    """A joint-1 offset beside a free base rotation is the base's turn about z: the
    fit's warning names exactly those two, with correlations in [-1, 1]."""
    data, _ = simulate_campaign(rx160, 60, "none", noise_mm=0.05, noise_deg=0.01, seed=1)
    model = ExtendedModel(rx160, [make_effect(rx160, "joint_offset:joint_1", 0.0)])
    no_prior = FramePriors(tool_std_m=math.inf, base_std_m=math.inf, rotation_std_rad=math.inf)
    res = fit(model, data, cond=conditions_from_data(data), frames=no_prior)
    assert res.condition > MAX_CONDITION
    assert float(res.corr.abs().max()) <= 1.0
    assert res.undetermined(MAX_CONDITION) == [["base_frame.rotation[2]", "joint_offset:joint_1"]]
    warning = condition_warning(res)
    assert "cannot separate: {base_frame.rotation[2], joint_offset:joint_1}" in warning


def test_link_lengths_along_parallel_axes_are_named_as_an_exact_trade_off(ur10):
    """The UR10's elbow and wrist-1 axes are parallel to the shoulder lift's: moving
    along that common axis at the elbow or at wrist 1 moves the flange alike, so only the
    sum of those two components is determined. The diagnosis' ambiguity entry says so
    (not 'the data barely separates them')."""
    from hybrid_pk.calibration.diagnosis.ambiguity import correlated_groups

    g = torch.Generator().manual_seed(7)
    values = (torch.rand(2, 3, generator=g, dtype=F64) - 0.5) * 1e-3
    effects = f"link_length:elbow_joint={','.join(f'{v:.6g}' for v in values[0].tolist())}"
    effects += f"; link_length:wrist_1_joint={','.join(f'{v:.6g}' for v in values[1].tolist())}"
    data, _ = simulate_campaign(ur10, 300, effects, noise_mm=0.01, noise_deg=0.001, seed=2)
    labels = ["link_length:elbow_joint", "link_length:wrist_1_joint"]
    model = ExtendedModel(ur10, [make_effect(ur10, lbl) for lbl in labels])
    res = fit(model, data, cond=conditions_from_data(data))
    entries = [e for e in correlated_groups(res) if e["effects"] == labels]
    assert len(entries) == 1, correlated_groups(res)
    assert "only the combination is determined" in entries[0]["why"]
    assert "link_length:elbow_joint[" in entries[0]["why"]
    # each cause marks that component: its printed std is not a measurement
    from hybrid_pk.calibration.diagnosis.gains import _undetermined
    from hybrid_pk.cli.diagnose_cmd import _value

    exact = [g for g in res.undetermined(MAX_CONDITION) if len(g) > 1]
    marks = {e.label: _undetermined(e, exact, e.report_value()) for e in model.effects}
    (k,) = {u["component"] for m in marks.values() for u in m}
    assert marks[labels[0]] == [{"component": k, "with": [f"{labels[1]}[{k}]"]}], marks
    assert marks[labels[1]] == [{"component": k, "with": [f"{labels[0]}[{k}]"]}], marks
    line = _value([1e-4] * 3, [2e-6] * 3, "m", marks[labels[0]])
    assert line.count("*") == 2, line
    assert f"* [{k}]: only its combination with" in line, line


def test_exact_orientations_do_not_shrink_what_positions_measure(rx160):
    """Orientations simulated without noise sit at the rotation noise floor; their
    weighted residuals are ~0 and, pooled into the covariance's variance, scaled every
    std by sqrt(1/2): a Panda's link length erred 1.3-1.6x its std over 30 campaigns
    (sweep seed 696969 of tests/test_stand_ins.py). Over fresh noise draws, a link
    length's errors are the size of its std (z rms ~1; the old scale gave ~1.45)."""
    from tests.helpers import run_rng

    rng = run_rng("exact-orientation covariance")
    length = rng.uniform(-1e-4, 1e-4, 3)  # [m]
    spec = "link_length:joint_4=" + ",".join(f"{v:.6g}" for v in length)
    z = []
    for seed in rng.integers(1 << 20, size=20):
        data, _ = simulate_campaign(rx160, 300, spec, noise_mm=0.02, seed=int(seed))
        model = ExtendedModel(rx160, [make_effect(rx160, "link_length:joint_4")])
        cond = conditions_from_data(data)
        # from the closed-form frames, as every fit of the tool starts: from the identity
        # one draw in 20 (sweep seeds 838383, 151515) ended in another minimum, 80 mm off
        initialise_frames(model, data, cond)
        res = fit(model, data, cond=cond)
        err = model.effect("link_length:joint_4").value.detach() - torch.as_tensor(length)
        z.append(err / res.std[res.block_slice("link_length:joint_4")])
    rms = float(torch.cat(z).pow(2).mean().sqrt())
    # 60 draws: a z rms's sampling sd is ~1/sqrt(120) = 0.09; 1.25 is 2.8 of them from 1
    # (0.80-1.10 at run seeds 1-5 and 696969); below, only a gross overstatement fails
    # (the directions the exact orientations fix keep the floor's larger variance)
    assert 0.6 < rms < 1.25, (rms, length)

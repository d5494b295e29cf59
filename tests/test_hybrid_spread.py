"""The posture stage's shrink where its refine stage is off (hybrid_pk.hybrid.spread)."""

from __future__ import annotations

import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.effects import Conditions, ExtendedModel
from hybrid_pk.hybrid.builder import DEFAULT_INPUTS, build_hybrid, fit_coverages
from hybrid_pk.hybrid.spread import TargetSpread, shrink
from hybrid_pk.hybrid.stage import check_stages, refine_trust
from hybrid_pk.io.hybrid_file import load_hybrid, save_hybrid
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.training import train_hybrid
from tests.helpers import SMALL_STAGES, middle_q

F64 = torch.float64


def test_shrink_keeps_what_the_spread_dwarfs_and_halves_what_it_matches():
    s2 = torch.tensor([1e-8, 1e-8, 0.0], dtype=F64)  # (0.1 mm)² on x and y, none on z
    c = torch.tensor([[1e-3, 1e-4, 1e-5], [0.0, -1e-4, 0.0]], dtype=F64)
    off, on = torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64)
    torch.testing.assert_close(shrink(c, s2, on), c)  # the refine stage is trusted
    out = shrink(c, s2, off)
    torch.testing.assert_close(out[0, 0], c[0, 0] * 1e-6 / (1e-6 + 1e-8))  # 99 % kept
    torch.testing.assert_close(out[:, 1], c[:, 1] / 2)  # the size of the spread: half
    torch.testing.assert_close(out[:, 2], c[:, 2])  # no spread: all of it
    half = shrink(c, s2, torch.full((2,), 0.5, dtype=F64))
    torch.testing.assert_close(half, (c + out) / 2)  # linear in the refine trust


def test_the_spread_is_what_rows_of_equal_inputs_disagree_by():
    gen = torch.Generator().manual_seed(3)
    u = torch.rand(2000, 2, generator=gen, dtype=F64)
    smooth = torch.stack([u[:, 0], u[:, 1], u[:, 0] * u[:, 1]], -1) * 1e-4
    hidden = torch.randn(2000, 3, generator=gen, dtype=F64) * torch.tensor([0, 2e-5, 0])
    spread = TargetSpread.from_targets(u, smooth + hidden, None)
    # independent hidden parts: E[(a - b)²] = 2 var; the smooth part barely differs
    torch.testing.assert_close(
        spread.position[1], torch.tensor(2 * 4e-10, dtype=F64), rtol=0.1, atol=0
    )
    assert float(spread.position[0]) < 0.02 * float(spread.position[1])
    assert torch.equal(spread.orientation, torch.zeros(3, dtype=F64))
    # a row measured twice pairs with its repeat, never with itself
    twice = TargetSpread.from_targets(
        torch.cat([u[:10], u[:10]]),
        torch.cat([smooth[:10], smooth[:10] + 1e-5]),
        None,
        neighbours=1,
    )
    torch.testing.assert_close(twice.position, torch.full((3,), 1e-10, dtype=F64))


def _with_spread(robot: Robot, q: torch.Tensor):
    torch.manual_seed(0)
    hybrid = build_hybrid(ExtendedModel(robot), DEFAULT_INPUTS, SMALL_STAGES, q).double().eval()
    fit_coverages(hybrid, hybrid.encode_all(q), hybrid.encode_all(q[:50]), SMALL_STAGES)
    hybrid.stages[0].spread = TargetSpread(
        torch.full((3,), 1e-8, dtype=F64), torch.full((3,), 1e-8, dtype=F64)
    )
    return hybrid


def test_the_shrink_acts_only_where_the_refine_stage_is_off(ur10):
    q = middle_q(ur10, 300, 1, 0.3)
    hybrid = _with_spread(ur10, q)
    with torch.no_grad():
        trusted = refine_trust(hybrid.weights(q), 0) == 1
    inside = q[trusted][:40]
    assert len(inside) >= 20
    outside = inside.clone()
    outside[:, 0] += 4.0  # joint 1 beyond the refine stage's joint box, posture the same
    with torch.no_grad():
        full = {}
        for key, rows in (("inside", inside), ("outside", outside)):
            shrunk = hybrid.corrections(rows)
            spread, hybrid.stages[0].spread = hybrid.stages[0].spread, None
            full[key] = hybrid.corrections(rows)
            hybrid.stages[0].spread = spread
            full[key + " shrunk"] = shrunk
        w_in, w_out = hybrid.weights(inside), hybrid.weights(outside)
    for a, b in zip(full["inside"], full["inside shrunk"], strict=True):
        torch.testing.assert_close(a, b)  # the refine stage trusted: nothing shrinks
    assert float(w_out[1].abs().max()) == 0.0
    torch.testing.assert_close(w_out[0], w_in[0])  # the posture stage turns with joint 1
    assert float(w_out[0].mean()) > 0.5
    with torch.no_grad():  # outside: the posture stage's own correction, shrunk
        u, geo = hybrid.stages[0].encode(ur10, outside)
        c0 = hybrid.stages[0].predict(u, geo, w_out[0])
    for a, b, c, s2 in zip(
        full["outside"],
        full["outside shrunk"],
        c0,
        hybrid.stages[0].spread.apply(*c0, 0 * w_out[0]),
        strict=True,
    ):
        torch.testing.assert_close(b - a, s2 - c)
        assert float((s2 - c).abs().max()) > 0


def test_a_model_with_a_spread_round_trips_and_passes_gradients_tomiddle_q(ur10, tmp_path):
    q = middle_q(ur10, 300, 2, 0.3)
    hybrid = _with_spread(ur10, q)
    restored = load_hybrid(save_hybrid(tmp_path / "spread.pt", hybrid))
    assert restored.state()["version"] == 3  # a spread without a gate: format 3 still
    assert restored.stages[0].spread is not None
    probe = q[:20].clone()
    probe[:10, 0] += 4.0  # half of them where the shrink acts
    with torch.no_grad():
        assert torch.equal(restored(probe, Conditions()), hybrid(probe, Conditions()))
    x = probe[:3].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q_: hybrid.end_pose(q_)[..., :3, :], (x,))


def test_a_spread_needs_a_refine_stage_after_it(ur10):
    q = middle_q(ur10, 200, 3, 0.3)
    hybrid = build_hybrid(ExtendedModel(ur10), "frame1+q2-4+torque", SMALL_STAGES, q)
    hybrid.stages[0].spread = TargetSpread(torch.zeros(3), torch.zeros(3))
    with pytest.raises(ValueError, match="refine stage"):
        check_stages(list(hybrid.stages))


def test_training_the_default_stages_measures_the_spread_unless_told_not_to(ur10):
    data, _ = simulate_campaign(
        ur10, 240, "joint_compliance:elbow_joint=2e-5", noise_mm=0.01, known_frames=True,
        temperature_range=None, seed=7,
    )  # fmt: skip
    spreads, records = {}, {}
    for spread, blocked in ((True, False), (False, False), (True, True)):
        result = train_hybrid(
            data,
            ExtendedModel(ur10),
            model={"inputs": DEFAULT_INPUTS, "position_net": "mlp:8x2",
                   "orientation_net": "mlp:8x2", "refine_net": "mlp:8x2", "spread": spread,
                   "blocked": blocked},
            max_epochs=2,
            progress=False,
            seed=0,
        )  # fmt: skip
        spreads[spread, blocked] = result.hybrid.stages[0].spread
        records[spread, blocked] = result.hybrid.stages[0].blocked
    assert spreads[False, False] is None
    assert records[True, False] is None  # no blocked test: the spread as measured
    # the blocked test keeps the shrink only where it freed the stage and the shrink won
    assert (spreads[True, True] is not None) == (records[True, True]["mode"] == "shrunk")
    measured = spreads[True, False]
    assert measured is not None
    # an elbow sag of up to ~0.6 mm that differs between rows of nearly equal inputs
    assert 0 < float(measured.position.max()) < (1e-3) ** 2

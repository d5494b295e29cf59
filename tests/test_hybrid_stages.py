"""Stages of residual networks (cascade of fall-backs, refinements) and a hybrid that
holds where joint 1 was never trained (issue 13)."""

from __future__ import annotations

import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.effects import Conditions, ExtendedModel, conditions_from_data
from hybrid_pk.errors import HybridPKError
from hybrid_pk.evaluation.metrics import row_errors
from hybrid_pk.hybrid import HybridFK
from hybrid_pk.hybrid.builder import (
    DEFAULT_INPUTS,
    build_hybrid,
    fit_coverages,
    parse_stages,
)
from hybrid_pk.hybrid.stage import combine_stages
from hybrid_pk.io.hybrid_file import load_hybrid, save_hybrid
from hybrid_pk.simulate import simulate_campaign
from hybrid_pk.training import train_hybrid
from tests.helpers import RUN_SEED, SMALL_STAGES, middle_q

F64 = torch.float64


def _fitted(robot: Robot, inputs: str, q: torch.Tensor) -> HybridFK:
    """Random networks for ``inputs`` and coverages of the rows ``q`` (first 3/4 the
    training rows, the rest the validation rows)."""
    torch.manual_seed(0)
    n = 3 * len(q) // 4
    hybrid = build_hybrid(ExtendedModel(robot), inputs, SMALL_STAGES, q[:n]).double().eval()
    fit_coverages(hybrid, hybrid.encode_all(q[:n]), hybrid.encode_all(q[n:]), SMALL_STAGES)
    return hybrid


def test_inputs_strings_name_the_stages_and_bad_ones_say_how():
    assert parse_stages(DEFAULT_INPUTS) == [
        ("frame1+qarm+torque", "cascade"),
        ("joints", "refine"),
        ("local+q1", "cascade"),
    ]
    assert parse_stages("joints") == [("joints", "cascade")]
    for bad, why in (
        ("local,frame1", "local networks must be the last stage"),
        ("frame1/local", "local networks must be the last stage"),
        ("frame1,,joints", "an empty stage"),
        ("frame1+heat", "unknown or clashing"),
    ):
        with pytest.raises(HybridPKError, match=why):
            parse_stages(bad)


def test_cascade_weights_hand_the_rest_to_the_next_stage_and_refinements_ride_along(ur10):
    hybrid = _fitted(ur10, DEFAULT_INPUTS, middle_q(ur10, 200, 1))
    first = torch.tensor([1.0, 0.0, 0.25], dtype=F64)
    refine = torch.tensor([0.5, 1.0, 1.0], dtype=F64)
    local = torch.full((3, ur10.dof), 0.8, dtype=F64)
    w = combine_stages(list(hybrid.stages), [first, refine, local])
    torch.testing.assert_close(w[0], first)
    torch.testing.assert_close(w[1], first * refine)  # only where the first stage applies
    torch.testing.assert_close(w[2], (1 - first)[:, None] * local)


def test_rows_no_stage_covers_are_the_base_model_exactly(ur10):
    q_train = middle_q(ur10, 200, 2, share=0.1)  # a narrow band of every joint
    hybrid = _fitted(ur10, DEFAULT_INPUTS, q_train)
    far = q_train[:50] + torch.pi  # every joint on the far side of its circle
    with torch.no_grad():
        weights = hybrid.weights(far)
        T, T_base = hybrid(far), hybrid.base(far)
        near = hybrid.weights(q_train[:50])
    assert all(bool((w == 0).all()) for w in weights)
    assert torch.equal(T, T_base)
    assert float(near[0].mean()) > 0.9  # the training rows themselves are covered


def test_a_model_file_of_three_stages_round_trips_bit_for_bit(ur10, tmp_path):
    hybrid = _fitted(ur10, DEFAULT_INPUTS, middle_q(ur10, 200, 4))
    restored = load_hybrid(save_hybrid(tmp_path / "stages.pt", hybrid))
    # qarm resolved on the training rows: the UR10's joints 2-5 (wrist 3 turns the tool)
    assert restored.input_label == DEFAULT_INPUTS.replace("qarm", "q2-5")
    assert [s.role for s in restored.stages] == ["cascade", "refine", "cascade"]
    q = ur10.sample_q(500, torch.Generator().manual_seed(5))
    with torch.no_grad():
        assert torch.equal(restored(q, Conditions()), hybrid(q, Conditions()))


@pytest.mark.slow
def test_the_default_hybrid_is_the_physics_where_joint_1_was_never_trained(ur10):
    """A hidden gravity-driven effect (compliance of a random joint behind joint 1, random
    size): trained on rows with q1 below its median, the default stages learn it (the
    validation rows gain) but do not carry it to the rows above it, as the paper's
    joint-box networks do not: blocked hold-out inside joint 1's trained range cannot
    tell an error that turns with joint 1 from one that does not (issue 27,
    tests/test_hybrid_blocked.py), so even a freed stage keeps joint 1's range. Before
    issue 27 the default stages corrected these rows (< 0.8 x the base model)."""
    gen = torch.Generator().manual_seed(RUN_SEED)
    # shoulder lift carries ~100 Nm, the elbow ~30 Nm: sizes for 0.2 .. 1 mm of sag
    joint, lo = (("shoulder_lift_joint", 5e-6), ("elbow_joint", 2e-5))[
        int(torch.randint(2, (1,), generator=gen))
    ]
    size = float(lo * (1 + 3 * torch.rand((), generator=gen)))
    data, _ = simulate_campaign(
        ur10,
        1200,
        f"joint_compliance:{joint}={size:.3g}",
        noise_mm=0.002,
        known_frames=True,
        temperature_range=None,
        seed=RUN_SEED,
    )
    low = data.q[:, 0] < data.q[:, 0].median()
    train, test = data.subset(torch.nonzero(low)[:, 0]), data.subset(torch.nonzero(~low)[:, 0])
    base = ExtendedModel(ur10)
    errors, gains = {}, {}
    for inputs in ("joints", DEFAULT_INPUTS):
        result = train_hybrid(
            train,
            base,
            model={
                "inputs": inputs,
                "position_net": "mlp:64x2",
                "orientation_net": "mlp:64x2",
                "refine_net": "mlp:64x2",
            },
            # 40 epochs left an elbow sag under-learned (validation gain 0.68-0.81 at
            # seeds 1-8 and sweep seed 313131, against the < 0.8 below); 80 take it to ~0.5
            max_epochs=80,
            progress=False,
            seed=RUN_SEED,
        )
        gains[inputs] = result.best["position_mm"] / result.base["position_mm"]
        with torch.no_grad():
            errors[inputs] = row_errors(result.hybrid(test.q, conditions_from_data(test)), test)[0]
    with torch.no_grad():
        errors["base"] = row_errors(base(test.q, conditions_from_data(test)), test)[0]
    where = f"seed {RUN_SEED}: {joint} = {size:.3g} rad/Nm"
    assert float(errors["base"].mean()) > 0.1, where  # the effect is there
    assert gains[DEFAULT_INPUTS] < 0.8, where  # learned where trained
    torch.testing.assert_close(errors["joints"], errors["base"])  # outside the box
    torch.testing.assert_close(errors[DEFAULT_INPUTS], errors["base"])  # beyond joint 1

"""The joint-space effects' Jacobian effect by effect (``calibration/joint_jacobian.py``)
equals forward mode through the whole sequence, and declines effects that couple joints."""

from __future__ import annotations

import torch

from hybrid_pk.calibration.joint_jacobian import joint_effect_jacobian
from hybrid_pk.calibration.problem import param_blocks
from hybrid_pk.effects import Conditions, Effect, ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign

# Several effects on one joint act in sequence (the chain rule runs through each).
LABELS = [
    "joint_offset:elbow_joint", "gear_ratio:elbow_joint", "backlash:elbow_joint",
    "joint_eccentricity:elbow_joint", "cyclic_error_3:elbow_joint", "gear_ratio:wrist_1_joint",
    "cyclic_error_17:shoulder_lift_joint", "joint_compliance:shoulder_lift_joint",
    "backlash:wrist_3_joint", "link_length:wrist_1_joint", "joint_offset:wrist_3_joint",
]  # fmt: skip


def _model(robot, labels, seed):
    gen = torch.Generator().manual_seed(seed)
    effects = [make_effect(robot, c) for c in labels]
    with torch.no_grad():
        for e in effects:  # away from zero: the chain factors are not one
            e.value.copy_(
                torch.randn(e.value.shape, generator=gen, dtype=e.value.dtype) * 30 * e.scale
            )
    return ExtendedModel(robot, effects)


class _KinematicValues(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, q, cond):
        return self.model.kinematic_joint_values(q, cond)


def _forward_mode(model, q, cond, blocks):
    """Every direction through the whole sequence (the general path)."""
    wrapper, params = _KinematicValues(model), dict(model.named_parameters())

    def q_kin(theta):
        vals, k = {}, 0
        for b in blocks:
            x = params[b.name].detach()
            vals[f"model.{b.name}"] = (x.reshape(-1) + theta[k : k + b.size] * b.scale).reshape(
                x.shape
            )
            k += b.size
        return torch.func.functional_call(wrapper, vals, (q, cond))

    size = sum(b.size for b in blocks)
    return torch.func.jacfwd(q_kin)(torch.zeros(size, dtype=q.dtype))


def test_effect_by_effect_equals_forward_mode_through_all(ur10):
    data, _ = simulate_campaign(ur10, 300, "none", noise_mm=0.0, seed=4)
    cond = conditions_from_data(data)
    for seed in (1, 2):
        model = _model(ur10, LABELS, seed)
        blocks = param_blocks(model, None, False)
        joint = [b for b in blocks if b.name.startswith("effects.")]
        joint = [b for b in joint if dict(model.named_modules())[b.name[:-6]].stage == "joint"]
        got = joint_effect_jacobian(model, data.q, cond, joint)
        ref = _forward_mode(model, data.q, cond, joint)
        assert got is not None
        torch.testing.assert_close(got, ref, atol=1e-15, rtol=1e-12)
        assert float(got.abs().max()) > 0


class _Coupled(Effect):
    """Joint j turns with the next joint too: not a map of its own joint alone."""

    kind, unit, stage, scale = "coupled_test_effect", "1", "joint", 1e-3

    def apply_q(self, q: torch.Tensor, cond: Conditions) -> torch.Tensor:
        onehot = torch.zeros(q.shape[-1], dtype=q.dtype)
        onehot[self.joint_index] = 1
        return q + (self.value.to(q.dtype) * q[..., self.joint_index + 1])[..., None] * onehot


def test_an_effect_that_couples_joints_is_declined(ur10):
    q = ur10.sample_q(20, torch.Generator().manual_seed(5))
    coupled = _Coupled(ur10, "elbow_joint")
    with torch.no_grad():
        coupled.value.fill_(1e-3)
    model = ExtendedModel(ur10, [make_effect(ur10, "joint_offset:elbow_joint"), coupled])
    blocks = [b for b in param_blocks(model, None, False) if b.name.startswith("effects.")]
    assert joint_effect_jacobian(model, q, Conditions(), blocks) is None
    plain = ExtendedModel(ur10, [make_effect(ur10, "joint_offset:elbow_joint")])
    blocks = [b for b in param_blocks(plain, None, False) if b.name.startswith("effects.")]
    assert joint_effect_jacobian(plain, q, Conditions(), blocks) is not None


def test_closed_form_derivatives_equal_forward_mode_bit_for_bit(ur10, monkeypatch):
    """The built-in joint effects' ``joint_derivatives`` give the very numbers forward
    mode through ``apply_q`` gives (the diagnosis finds the same, only faster)."""
    from hybrid_pk.calibration import joint_jacobian as jj

    data, _ = simulate_campaign(ur10, 200, "none", noise_mm=0.0, seed=6)
    cond = conditions_from_data(data)
    model = _model(ur10, LABELS, 3)
    blocks = {b.name: b for b in param_blocks(model, None, False)}
    checked = 0
    for i, e in enumerate(model.effects):
        if getattr(e, "joint_derivatives", None) is None:
            continue
        block = blocks[f"effects.{i}.value"]
        got = jj._effect_derivatives(e, data.q, cond, e.joint_index, block)
        monkeypatch.setattr(type(e), "joint_derivatives", None)  # the forward-mode path
        ref = jj._effect_derivatives(e, data.q, cond, e.joint_index, block)
        monkeypatch.undo()
        for a, b in zip(got, ref, strict=True):
            assert torch.equal(a, b), e.label
        checked += 1
    assert checked == 9  # every joint-stage effect of LABELS

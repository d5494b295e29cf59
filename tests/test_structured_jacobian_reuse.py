"""What the structured Jacobian computes once and hands on: the gravity torques that come
with their derivative, and the frame twists spread over several frame sets."""

import torch

from hybrid_pk.calibration.gravity_jacobian import gravity_jacobian
from hybrid_pk.calibration.least_squares import jacobian
from hybrid_pk.calibration.twists import frame_twists
from hybrid_pk.effects import ExtendedModel


def test_gravity_derivative_hands_on_its_torques_bit_for_bit(ur10):
    q = ur10.sample_q(50, torch.Generator().manual_seed(6))
    payload = torch.full((50,), 4.0, dtype=torch.float64)
    gravity = torch.tensor([0.0, 0.0, -9.80665], dtype=torch.float64)
    params = ur10.kinematic_params()
    data_q = q.clone()  # the rows' data set, the key's owner
    key = (data_q, 0, 50)
    with torch.no_grad():
        tau, G = gravity_jacobian(ur10, q, payload, params, key, gravity)
        assert torch.equal(tau, ur10.gravity_torques(q, payload, gravity, params))
        assert G.shape == (50, 6, 6)
        again, G_kept = gravity_jacobian(ur10, q + 1e-6, payload, params, key, gravity)
    assert again is None  # dg/dq reused (q* moved < GRAVITY_REUSE_RAD): no torques with it
    assert torch.equal(G_kept, G)


def test_frame_twists_of_several_sets_are_each_rows_own_set(ur10):
    g = torch.Generator().manual_seed(7)
    n = 12
    one, two = ExtendedModel(ur10), ExtendedModel(ur10, frame_sets=2)
    with torch.no_grad():
        for frame in ("base", "tool"):
            rotvec = 0.1 * torch.randn(1, 3, generator=g, dtype=torch.float64)
            getattr(one, frame).rotvec.copy_(rotvec)
            getattr(two, frame).rotvec.copy_(rotvec.repeat(2, 1))  # both sets the same
        group = torch.tensor([0, 1] * (n // 2))
        T_BE = ur10.fk(ur10.sample_q(n, g))
        T = T_BE @ one.tool.matrix()[0]
        single = frame_twists(one.base, one.tool, None, T_BE, T)
        for key, v in frame_twists(two.base, two.tool, group, T_BE, T).items():
            spread = v.reshape(n, 6, 2, 3)
            rows = torch.arange(n)
            assert torch.equal(spread[rows, :, group], single[key])  # its own set's columns
            assert not spread[rows, :, 1 - group].any()  # the other set moves nothing


def test_gravity_derivative_in_closed_form_while_the_axes_require_grad(ur10):
    """Inside a fit the joint axes require grad; dg/dq is a constant of the Jacobian, so
    the closed form is taken all the same (its torques come with it; before, forward
    mode through the statics, ~10x slower, handed none on) and agrees with forward mode."""
    q = ur10.sample_q(20, torch.Generator().manual_seed(8))
    gravity = torch.tensor([0.0, 0.0, -9.80665], dtype=torch.float64)
    plain = ur10.kinematic_params()
    free = plain._replace(axis=plain.axis.clone().requires_grad_(True))
    tau, G = gravity_jacobian(ur10, q, 3.0, free, None, gravity)
    assert tau is not None
    assert torch.equal(tau, ur10.gravity_torques(q, 3.0, gravity, plain))

    def torques(d: torch.Tensor) -> torch.Tensor:
        return ur10.gravity_torques(q + d, payload=3.0, gravity=gravity, params=plain).reshape(-1)

    _, G_fwd = jacobian(torques, torch.zeros(6, dtype=torch.float64))
    assert torch.allclose(G, G_fwd.reshape(20, 6, 6), rtol=1e-10, atol=1e-10)

"""What the structured Jacobian computes once and hands on: the gravity torques that come
with their derivative."""

import torch

from hybrid_pk.calibration.structured_jacobian import _gravity_jacobian


def test_gravity_derivative_hands_on_its_torques_bit_for_bit(ur10):
    q = ur10.sample_q(50, torch.Generator().manual_seed(6))
    payload = torch.full((50,), 4.0, dtype=torch.float64)
    gravity = torch.tensor([0.0, 0.0, -9.80665], dtype=torch.float64)
    params = ur10.kinematic_params()
    data_q = q.clone()  # the rows' data set, the key's owner
    key = (data_q, 0, 50)
    with torch.no_grad():
        tau, G = _gravity_jacobian(ur10, q, payload, params, key, gravity)
        assert torch.equal(tau, ur10.gravity_torques(q, payload, gravity, params))
        assert G.shape == (50, 6, 6)
        again, G_kept = _gravity_jacobian(ur10, q + 1e-6, payload, params, key, gravity)
    assert again is None  # dg/dq reused (q* moved < GRAVITY_REUSE_RAD): no torques with it
    assert torch.equal(G_kept, G)

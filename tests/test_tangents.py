"""``geometry.tangents.carried``: constants keep their values and get a zero tangent
under forward mode, so effect code gives the same derivatives with or without it."""

from __future__ import annotations

import torch

from hybrid_pk.geometry import so3_exp
from hybrid_pk.geometry.tangents import carried


def test_carried_is_the_constant_with_a_zero_tangent():
    x = torch.randn(4, 3, dtype=torch.float64)
    c = torch.randn(4, 3, dtype=torch.float64)

    def f(y):
        return carried(c, y), carried(2.5, y) * y

    (c_out, scaled), (c_dot, scaled_dot) = torch.func.jvp(f, (x,), (torch.ones_like(x),))
    assert torch.equal(c_out, c)
    assert torch.equal(c_dot, torch.zeros_like(c))
    assert torch.equal(scaled, 2.5 * x)
    assert torch.equal(scaled_dot, torch.full_like(x, 2.5))
    assert carried(c, x) is c  # outside torch.func: the constant itself


def test_so3_exp_forward_mode_matches_finite_differences():
    w = torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.0, 0.0], [1e-6, 0.0, 0.0]], dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    jac = torch.func.vmap(lambda v: torch.func.jvp(so3_exp, (w,), (v.expand(3, 3),))[1])(eye)
    h = 1e-6
    for k in range(3):
        fd = (so3_exp(w + h * eye[k]) - so3_exp(w - h * eye[k])) / (2 * h)
        torch.testing.assert_close(jac[k], fd, atol=1e-8, rtol=0)

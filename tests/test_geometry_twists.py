"""geometry_twists: directions equal in every row take the shared path, same columns."""

import torch

from hybrid_pk.calibration.twists import _origin_twists, geometry_twists


def test_shared_and_per_row_directions_give_the_per_row_columns():
    g = torch.Generator().manual_seed(0)
    n, k = 40, 5
    maps = torch.randn(n, 6, 42, dtype=torch.float64, generator=g)
    rot = torch.linalg.qr(torch.randn(7, 3, 3, dtype=torch.float64, generator=g))[0]
    rot = rot.expand(n, 7, 3, 3)
    d_xyz = torch.randn(k, 1, 7, 3, dtype=torch.float64, generator=g).repeat(1, n, 1, 1)
    d_rot = torch.randn(k, 1, 7, 3, 3, dtype=torch.float64, generator=g).repeat(1, n, 1, 1, 1)
    d_xyz[2] = torch.randn(n, 7, 3, dtype=torch.float64, generator=g)  # one per-row direction
    d_rot[4, 3] += 1e-3  # and one that differs in a single row
    got = geometry_twists(maps, rot, d_xyz, d_rot)
    want = _origin_twists(maps, rot, d_xyz, d_rot)
    assert got.shape == (n, 6, k)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_shared_rotations_with_per_row_directions_take_the_shared_path_too():
    """Shared origin rotations (a thermal expansion at exactly zero keeps the parameters
    shared) with per-row directions: the same columns as with the rotations per row."""
    g = torch.Generator().manual_seed(1)
    n, k = 30, 4
    maps = torch.randn(n, 6, 42, dtype=torch.float64, generator=g)
    rot = torch.linalg.qr(torch.randn(7, 3, 3, dtype=torch.float64, generator=g))[0]
    d_xyz = torch.randn(k, 1, 7, 3, dtype=torch.float64, generator=g).repeat(1, n, 1, 1)
    d_rot = torch.randn(k, 1, 7, 3, 3, dtype=torch.float64, generator=g).repeat(1, n, 1, 1, 1)
    d_xyz[1] = torch.randn(n, 7, 3, dtype=torch.float64, generator=g)
    got = geometry_twists(maps, rot, d_xyz, d_rot)
    want = geometry_twists(maps, rot.expand(n, 7, 3, 3), d_xyz, d_rot)
    assert torch.equal(got, want)


def test_zero_thermal_expansion_keeps_shared_parameters(ur10):
    from hybrid_pk.effects import Conditions, make_effect

    e = make_effect(ur10, "thermal_expansion")
    cond = Conditions(temperature=torch.linspace(18.0, 26.0, 9, dtype=torch.float64))
    with torch.no_grad():  # values alone (a Jacobian takes derivatives by forward mode)
        params = ur10.kinematic_params()
        assert e.apply_params(params, cond) is params  # zero: every factor exactly 1
        e.value.fill_(1e-5)
        grown = e.apply_params(params, cond)
    assert grown.origin_xyz.shape == (9, *params.origin_xyz.shape)
    assert not torch.equal(grown.origin_xyz[0], params.origin_xyz)

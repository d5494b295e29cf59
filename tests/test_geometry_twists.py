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

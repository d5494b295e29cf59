"""Python API misuse gives a one-line error naming what is wrong (third tour, API user)."""

import pytest

import hybrid_pk as hpk
from hybrid_pk.errors import HybridPKError


@pytest.fixture(scope="module")
def ur10():
    return hpk.Robot.from_urdf("ur10")


@pytest.mark.parametrize(
    ("spec", "value", "said"),
    [
        ("link_length:elbow_joint", 5e-4, r"must be \(3,\) \[m\], got shape \(\)"),
        ("joint_offset:elbow_joint", [1e-3, 2e-3], r"must be a number \[rad\], got shape \(2,\)"),
        ("joint_offset:elbow_joint", "abc", r"must be a number \[rad\], got 'abc'"),
        ("joint_offset:elbow_joint", float("nan"), r"finite, got nan"),
    ],
)
def test_make_effect_value_checked(ur10, spec, value, said):
    with pytest.raises(HybridPKError, match=said):
        hpk.make_effect(ur10, spec, value)


def test_make_effect_value_kept(ur10):
    e = hpk.make_effect(ur10, "link_length:elbow_joint", [0.0, 0.0, 5e-4])
    assert e.value.tolist() == [0.0, 0.0, 5e-4]

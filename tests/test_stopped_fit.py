"""A fit stops where its caller's test of the model holds (``fit(stop=...)``,
:class:`hybrid_pk.calibration.least_squares.StoppedFit`), and the diagnosis' swap
refits stop where an effect passes the size of a small correction
(:func:`hybrid_pk.calibration.diagnosis.plausibility.oversized`).

On the shared UR10 series a group swap's refit walked 11 LM iterations (about 3 s)
to a 2455 mm elbow link length before the swap rule refused it; stopped at the first
step past 50 mm, the diagnosis names the same causes with the same values.
"""

from __future__ import annotations

import copy

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.plausibility import oversized
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.calibration.least_squares import StoppedFit, levenberg_marquardt
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")


def test_lm_raises_at_the_first_accepted_point_its_test_holds_at():
    rng = run_rng("stopped-lm")
    target = torch.tensor(rng.uniform(2.0, 5.0, 3), dtype=torch.float64)
    fun = lambda x: x - target  # noqa: E731  (one Gauss-Newton step solves it)
    x0 = torch.zeros(3, dtype=torch.float64)
    free = levenberg_marquardt(fun, x0)
    assert torch.allclose(free.x, target, atol=1e-6)
    seen = []

    def beyond_one(x):
        seen.append(x.clone())
        return bool(x.abs().max() > 1.0)

    with pytest.raises(StoppedFit) as stopped:
        levenberg_marquardt(fun, x0, stop=beyond_one)
    assert len(seen) == 1  # the first accepted step already passed 1
    assert torch.equal(stopped.value.x, seen[0])
    assert float(stopped.value.x.abs().max()) > 1.0


def test_a_fit_stops_where_the_test_holds_and_the_model_keeps_its_start(ur10):
    rng = run_rng("stopped-fit")
    true_m = float(rng.uniform(2e-3, 6e-3))  # a 2-6 mm link-length error
    label = "link_length:elbow_joint"
    seed = int(rng.integers(1000))
    data, _ = simulate_campaign(
        ur10, 150, f"{label}=0,{true_m},0", noise_mm=0.02, noise_deg=0.002, seed=seed
    )  # fmt: skip
    cond = conditions_from_data(data)
    model = ExtendedModel(ur10, [make_effect(ur10, label)])
    initialise_frames(model, data, cond)
    twin = copy.deepcopy(model)
    start = [p.detach().clone() for p in model.parameters()]
    limit = true_m / 4  # the walk to the true value passes it

    def past_limit(m: ExtendedModel) -> bool:
        return float(m.effect(label).value.detach().norm()) > limit

    with pytest.raises(StoppedFit):
        fit(model, data, cond=cond, stop=past_limit)
    for p, p0 in zip(model.parameters(), start, strict=True):
        assert torch.equal(p.detach(), p0)  # the test's writes undone, nothing kept
    res = fit(twin, data, cond=cond, stop=oversized)  # 2-6 mm: a small correction
    assert res.converged
    assert abs(float(twin.effect(label).value[1]) - true_m) < 1e-4


def test_oversized_is_the_size_limit_without_the_sign(ur10):
    rng = run_rng("oversized")
    far = float(rng.uniform(0.06, 3.0))  # [m]: beyond a URDF correction's 50 mm
    near = float(rng.uniform(1e-4, 0.04))

    def model(length, play):
        return ExtendedModel(
            ur10,
            [
                hpk.make_effect(ur10, "link_length:elbow_joint", torch.tensor([0.0, length, 0.0])),
                hpk.make_effect(ur10, "backlash:wrist_3_joint", torch.tensor(play)),
            ],
        )

    assert oversized(model(far, 1e-4))
    assert oversized(model(-far, 1e-4))
    assert not oversized(model(near, 1e-4))
    assert not oversized(model(near, -1e-4))  # a negative play is refused at the end, not here

"""A refit whose frame report nobody reads (the diagnosis' trial refits) skips it, and
everything else it returns is bit for bit the fit's with the report, the work counted
for the diagnosis' budget included."""

from __future__ import annotations

import copy

import pytest
import torch

from hybrid_pk.calibration import work
from hybrid_pk.calibration.fit import fit, initialise_frames
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.simulate import simulate_campaign

pytestmark = pytest.mark.usefixtures("one_thread")


def test_a_fit_without_its_frame_report_is_otherwise_the_same(rx160):
    data, _ = simulate_campaign(
        rx160, 120, "joint_compliance:joint_2=1.5e-6", noise_mm=0.02, noise_deg=0.002,
        payload=20.0, seed=3,
    )  # fmt: skip
    cond = conditions_from_data(data)
    model = ExtendedModel(rx160, [make_effect(rx160, "joint_compliance:joint_2")])
    initialise_frames(model, data, cond)
    twin = copy.deepcopy(model)
    # rows of their own each: what is kept per rows (the compliance's last fixed point,
    # dg/dq, poses) starts the same for both fits. Both copies live throughout: a copy
    # freed after the first fit could leave its address, and equal values, to the
    # second, whose compliance would then start where the first settled (kept by the
    # rows' address, checked by value: the same to the fixed point's tolerance, not bit
    # for bit). The likely cause of one failure in a full run (x apart at round-off);
    # not reproduced alone
    rows_full, rows_bare = copy.deepcopy(data), copy.deepcopy(data)
    before = work.done()
    full = fit(model, rows_full, cond=cond)
    between = work.done()
    bare = fit(twin, rows_bare, cond=cond, report_frames=False)
    # the report's rows are counted as done: a diagnosis' work budget cuts where it did
    assert between - before > 0  # the fit counts its work at all
    assert work.done() - between == between - before
    assert full.frame_report is not None
    assert bare.frame_report is None
    for name in ("x", "std", "corr", "singular_values", "position_mm", "normal_matrix"):
        assert torch.equal(getattr(full, name), getattr(bare, name)), name
    for name in ("cost", "condition", "sigma_pos_mm", "sigma_rot_rad", "iterations"):
        assert getattr(full, name) == getattr(bare, name), name
    for a, b in zip(model.parameters(), twin.parameters(), strict=True):
        assert torch.equal(a, b)

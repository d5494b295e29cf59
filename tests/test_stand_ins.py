"""A candidate that named causes together stand in for is listed as ambiguous.

A Panda (its modified-DH table) with a hidden joint-4 offset: the search names the
joint-5 axis misalignment and link length, which together move the point exactly as
the offset does, and no one of them alone. The diagnosis must say so and keep its causes.
"""

from __future__ import annotations

import math

import torch

import hybrid_pk as hpk
from hybrid_pk.calibration.diagnosis.result import Cause
from hybrid_pk.calibration.diagnosis.search import diagnose
from hybrid_pk.calibration.diagnosis.selection import Scores
from hybrid_pk.calibration.diagnosis.stand_ins import group_stand_ins, kept_stand_ins
from hybrid_pk.calibration.problem import ParamBlock
from hybrid_pk.cli.diagnose_cmd import ambiguous_lines
from hybrid_pk.simulate import simulate_campaign

HALF_PI = math.pi / 2
# Franka Emika Panda, Craig's modified DH (a, alpha, d) and the joint limits [rad].
PANDA = [
    (0.0, 0.0, 0.333, -2.8973, 2.8973),
    (0.0, -HALF_PI, 0.0, -1.7628, 1.7628),
    (0.0, HALF_PI, 0.316, -2.8973, 2.8973),
    (0.0825, HALF_PI, 0.0, -3.0718, -0.0698),
    (-0.0825, -HALF_PI, 0.384, -2.8973, 2.8973),
    (0.0, HALF_PI, 0.0, -0.0175, 3.7525),
    (0.088, HALF_PI, 0.0, -2.8973, 2.8973),
]
HIDDEN = "joint_offset:joint_4=5e-4; link_length:joint_5=1e-4,0,0; joint_offset:joint_2=3e-4"
SEED = 0


def _panda() -> hpk.Robot:
    rows = [
        {"name": f"joint_{i}", "a": a, "alpha": al, "d": d, "theta": 0.0,
         "type": "revolute", "lower": lo, "upper": up}
        for i, (a, al, d, lo, up) in enumerate(PANDA, 1)
    ]  # fmt: skip
    flange = {"xyz": [0.0, 0.0, 0.107], "rpy": [0.0, 0.0, 0.0]}
    robot = hpk.Robot.from_dh(rows, "mdh", name="panda", flange=flange)
    robot.requires_grad_(False)
    return robot


def test_joint_offset_stood_in_for_by_two_named_causes_is_ambiguous():
    robot = _panda()
    data, _ = simulate_campaign(robot, 300, HIDDEN, noise_mm=0.02, seed=SEED)
    diag = diagnose(robot, data, seed=SEED)
    named = {c.effect if c.joint is None else f"{c.effect}:{c.joint}" for c in diag.causes}
    # the search's choice is unchanged: the offset is not named, the pair is
    assert "joint_offset:joint_4" not in named, named
    assert {"axis_misalignment:joint_5", "link_length:joint_5"} <= named, named
    groups = [a for a in diag.ambiguous if a.get("stood_in_by")]
    offset = [a for a in groups if a["effects"][0] == "joint_offset:joint_4"]
    assert offset, diag.ambiguous
    assert offset[0]["stood_in_by"] == ["axis_misalignment:joint_5", "link_length:joint_5"]
    assert offset[0]["effects"][1:] == offset[0]["stood_in_by"]
    assert all(set(a["stood_in_by"]) <= named and len(a["stood_in_by"]) > 1 for a in groups)
    line = "  joint_offset:joint_4 ~ axis_misalignment:joint_5 + link_length:joint_5 (together)"
    assert line in ambiguous_lines(diag.ambiguous)


def _scores(columns: dict[str, torch.Tensor], n_current: int) -> Scores:
    """A scoring whose factor holds ``columns`` (one column each) and a residual."""
    blocks = tuple(ParamBlock(f"p.{k}", k, 1, 1.0, "m") for k in columns)
    J = torch.stack(list(columns.values()), 1)
    R = torch.cat([J, torch.ones(J.shape[0], 1)], 1)
    return Scores(scored=[], m=J.shape[0], n_current=n_current, R=R, blocks=blocks)


def test_group_needs_each_member_and_a_single_holder_is_left_to_the_pairs():
    g = torch.Generator().manual_seed(SEED)
    frame, a, b, c = torch.randn(4, 40, generator=g, dtype=torch.float64)
    columns = {
        "base_frame.rotation": frame,
        "cause_a": a,
        "cause_b": b,
        "cause_c": c,
        "group": a + b + 3.0 * frame,  # a and b together, beside the frame
        "alone": a + 1e-3 * b,  # a alone holds it: the pairwise checks' business
        "outside": torch.randn(40, generator=g, dtype=torch.float64),
    }
    entries = group_stand_ins(_scores(columns, 4), ["cause_a", "cause_b", "cause_c"])
    assert [e["effects"] for e in entries] == [["group", "cause_a", "cause_b"]]
    causes = [Cause("cause_a", None, 0.0, "m", 0.0, 0.1, None, "test")]
    assert kept_stand_ins(entries, causes) == []  # cause_b is no longer a cause

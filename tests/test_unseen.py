"""Components no data can see (issue 28): the part of an effect the fitted frames absorb
is found, named in words, and marked in the tables that compare values."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest
import torch

from hybrid_pk.calibration.diagnosis.unseen import mark_unseen, seeable_split, seen_error
from hybrid_pk.calibration.fit import fit, initialise_frames, model_errors
from hybrid_pk.cli.main import main
from hybrid_pk.effects import ExtendedModel, conditions_from_data, make_effect
from hybrid_pk.pipelines.demo_report import found_table
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64


@pytest.fixture(scope="module")
def campaign(rx160):
    data, _ = simulate_campaign(rx160, 150, "none", noise_mm=0.0, seed=3)
    cond = conditions_from_data(data)
    model = ExtendedModel(rx160)
    initialise_frames(model, data, cond)
    fit(model, data, cond=cond, covariance=False)
    return model, data, cond


def test_the_last_link_length_along_its_axis_is_absorbed_by_the_tool(rx160, campaign):
    nominal, data, cond = campaign
    rng = run_rng("unseen-link")
    value = torch.tensor(rng.uniform(-0.5e-3, 0.5e-3, 3), dtype=F64)
    split = seeable_split(nominal, data, cond, make_effect(rx160, "link_length:joint_6", value))
    assert split is not None
    assert split["words"] == "along joint_6's axis: absorbed by the tool frame"
    absorbed = torch.tensor(split["absorbed"], dtype=F64)
    seen = torch.tensor(split["seen"], dtype=F64)
    torch.testing.assert_close(seen + absorbed, value)
    assert abs(float(seen @ absorbed)) < 1e-12  # orthogonal parts
    # oracle: points made with the absorbed part alone are fitted exactly by the frames
    only = ExtendedModel(rx160, [make_effect(rx160, "link_length:joint_6", absorbed)])
    only.base.reset_to(nominal.base.matrix().detach())
    only.tool.reset_to(nominal.tool.matrix().detach())
    with torch.no_grad():
        T = only(data.q, cond)
    moved = dataclasses.replace(data, position=T[:, :3, 3])
    refit = ExtendedModel(rx160)
    initialise_frames(refit, moved, cond)
    fit(refit, moved, cond=cond, covariance=False, sigma_pos_mm=1e-3, sigma_rot_rad=1e-5)
    assert float(model_errors(refit, moved, cond)[0].max()) < 1e-6  # [mm]


def test_an_inner_link_length_is_seen_whole(rx160, campaign):
    nominal, data, cond = campaign
    value = [1e-4, -2e-4, 3e-4]
    assert (
        seeable_split(nominal, data, cond, make_effect(rx160, "link_length:joint_3", value)) is None
    )


def test_the_demo_table_marks_the_unseen_part(rx160, campaign):
    nominal, data, cond = campaign
    truth = {
        "effects": [
            {"effect": "link_length", "joint": "joint_6", "value": [4.5e-4, 3.6e-4, -5e-4]}
        ],
        "unmodelled": [],
    }
    truth["effects"] = mark_unseen(nominal, data, cond, truth["effects"])
    entry = truth["effects"][0]
    seen = entry["unseen"]["seen"]

    # what a diagnosis names: the seen part (1 % off), ~0 along the axis
    cause = SimpleNamespace(effect="link_length", joint="joint_6", value=[1.01 * x for x in seen])
    (row,) = found_table(truth, SimpleNamespace(causes=[cause]))
    assert "(along joint_6's axis: absorbed by the tool frame)" in row[4]
    assert "within 1 %" in row[4]
    assert row[1] == "m"  # the unit column
    assert seen_error(entry, cause.value) == pytest.approx(0.01, rel=1e-6)


def test_simulate_notes_the_part_no_data_can_see(tmp_path, capsys):
    rc = main(
        ["simulate", "rx160", "--n", "60", "--effects", "link_length:joint_6=4.5e-4,3.6e-4,-5e-4",
         "--noise-mm", "0.02", "--out", str(tmp_path / "c.csv")]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0
    assert "note: link_length:joint_6 (along joint_6's axis: absorbed by the tool frame)" in out, (
        out
    )

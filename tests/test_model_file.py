"""MODEL file round trip, robot checks, error messages; corrected-URDF export."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
import torch

import hybrid_pk.io.model_file as mf
from hybrid_pk import ModelFileError, Robot
from hybrid_pk.effects import EFFECTS, Conditions, ExtendedModel, make_effect
from hybrid_pk.effects.geometric import REFERENCE_TEMPERATURE
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.io.model_file import load_model, model_robot, save_model
from hybrid_pk.io.urdf_export import corrected_urdf, export_urdf
from hybrid_pk.robot.urdf_copy import urdf_copy
from tests.helpers import assert_transforms_close

HERE = Path(__file__).resolve().parent
ARM7 = HERE / "data" / "arm7_generic.urdf"
F64 = torch.float64


def _random_pose(gen: torch.Generator, scale: float) -> torch.Tensor:
    w = torch.randn(3, generator=gen, dtype=F64)
    p = scale * torch.randn(3, generator=gen, dtype=F64)
    return transform(so3_exp(w), p)


def _every_effect(robot: Robot, gen: torch.Generator) -> list:
    """One effect of every kind of the vocabulary that the robot's joints take (a
    column's bending needs a prismatic joint), with non-zero values."""
    effects = []
    for i, (kind, cls) in enumerate(sorted(EFFECTS.items())):
        if kind == "column_bending" and "prismatic" not in robot.joint_types:
            continue
        joint = robot.joint_names[1 + i % (robot.dof - 1)]  # geometric ones not on joint 1
        if kind == "column_bending":
            joint = robot.joint_names[robot.joint_types.index("prismatic")]
        label = f"{kind}:{joint}" if cls.per_joint else kind
        e = make_effect(robot, label)
        with torch.no_grad():
            e.value.copy_(cls.scale * (1 + torch.rand(e.value.shape, generator=gen, dtype=F64)))
        effects.append(e)
    return effects


def _model(robot: Robot, sets: int, seed: int = 0) -> ExtendedModel:
    gen = torch.Generator().manual_seed(seed)
    model = ExtendedModel(robot, _every_effect(robot, gen), frame_sets=sets)
    with torch.no_grad():
        for frame, scale in ((model.base, 2.0), (model.tool, 0.1)):
            for g in range(sets):
                frame.reset_to(_random_pose(gen, scale), g)
            frame.dp.copy_(1e-3 * torch.randn(sets, 3, generator=gen, dtype=F64))
            frame.rotvec.copy_(1e-3 * torch.randn(sets, 3, generator=gen, dtype=F64))
    return model


def _conditions(robot: Robot, n: int, sets: int, gen: torch.Generator) -> Conditions:
    return Conditions(
        payload=10 * torch.rand(n, generator=gen, dtype=F64),
        temperature=20 + 8 * torch.rand(n, generator=gen, dtype=F64),
        direction=torch.randint(-1, 2, (n, robot.dof), generator=gen).to(F64),
        group=torch.randint(0, sets, (n,), generator=gen) if sets > 1 else None,
    )


# ----------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("sets", [1, 3])
def test_round_trip_reproduces_forward_bit_for_bit(rx160, tmp_path, sets):
    model = _model(rx160, sets)
    assert {e.kind for e in model.effects} == set(EFFECTS) - {"column_bending"}  # no prismatic
    gen = torch.Generator().manual_seed(1)
    q = rx160.sample_q(40, gen)
    cond = _conditions(rx160, 40, sets, gen)
    networks = {"position": {"w": torch.randn(4, 3, generator=gen), "arch": "mlp:64x2"}}
    path = save_model(
        tmp_path / "m.pt", model, networks=networks, metadata={"note": "test", "n": 40}
    )

    loaded = load_model(path)

    with torch.no_grad():
        expected, got = model(q, cond), loaded.model(q, cond)
    assert torch.equal(got, expected), f"max difference {(got - expected).abs().max():.3e}"
    assert [e.label for e in loaded.model.effects] == [e.label for e in model.effects]
    assert loaded.model.base.sets == sets
    assert torch.equal(loaded.networks["position"]["w"], networks["position"]["w"])
    assert loaded.networks["position"]["arch"] == "mlp:64x2"
    assert loaded.metadata["note"] == "test"
    assert loaded.metadata["created"]["hybrid_pk"]
    assert loaded.robot_name == "rx160"
    assert loaded.frames_fitted
    assert loaded.has_networks
    assert model_robot(loaded).joint_names == rx160.joint_names
    assert loaded.source == str(path)


def test_round_trip_without_the_original_urdf(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    urdf = tmp_path / "my_arm.urdf"
    shutil.copy(ARM7, urdf)
    robot = Robot.from_urdf(urdf, end_link="tool0")
    model = ExtendedModel(robot, [make_effect(robot, "link_length:j3", [1e-3, 0, -2e-3])])
    path = save_model(tmp_path / "m.pt", model, frames_fitted=False)
    urdf.unlink()  # the file must be self-contained

    loaded = load_model(path)

    q = robot.sample_q(10, torch.Generator().manual_seed(2))
    with torch.no_grad():
        assert torch.equal(loaded.model(q), model(q))
    assert loaded.model.robot.end_link == "tool0"
    copy = Path(loaded.model.robot.spec.urdf_path)
    assert copy.parent == tmp_path / "cache" / "hybrid_pk" / "urdf"
    assert not loaded.frames_fitted


def test_urdf_copies_are_one_file_per_content_and_leave_no_partial(tmp_path, monkeypatch):
    """A model file's URDF and a DH table's share one cache: the same text is the same
    file (written once), another text another file, and no half-written copy remains."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    text = ARM7.read_text(encoding="utf-8")
    first = urdf_copy(text, "arm7.urdf")
    stamp = first.stat().st_mtime_ns
    assert urdf_copy(text, "arm7.urdf") == first
    assert first.stat().st_mtime_ns == stamp  # not written again
    other = urdf_copy(text.replace("arm7", "arm7b", 1), "arm7.urdf")
    assert other != first
    assert first.read_text(encoding="utf-8") == text
    folder = tmp_path / "cache" / "hybrid_pk" / "urdf"
    assert sorted(p.name for p in folder.iterdir()) == sorted([first.name, other.name])


def test_nominal_spec_is_the_urdf_with_identity_frames(rx160):
    loaded = load_model("nominal:rx160")
    q = rx160.sample_q(5, torch.Generator().manual_seed(3))
    with torch.no_grad():
        assert torch.equal(loaded.model(q), rx160.fk(q))
    assert len(loaded.model.effects) == 0
    assert not loaded.frames_fitted
    assert loaded.networks is None
    assert loaded.source == "nominal:rx160"


# ----------------------------------------------------------------------------- robot check


def test_refuses_a_model_made_for_another_robot(rx160, tmp_path):
    path = save_model(tmp_path / "m.pt", ExtendedModel(rx160))
    with pytest.raises(
        ModelFileError, match=r"made for robot 'rx160' \(joints joint_1.*not 'ur10'"
    ):
        load_model(path, robot_check="ur10")
    with pytest.raises(ModelFileError, match="not joints a, b"):
        load_model(path, robot_check=["a", "b"])
    with pytest.raises(ModelFileError, match="not 'ur10'"):
        load_model("nominal:rx160", robot_check="ur10")
    assert load_model(path, robot_check="rx160").robot_name == "rx160"
    assert load_model(path, robot_check=rx160.joint_names).robot_name == "rx160"


# ----------------------------------------------------------------------------- bad files


def test_missing_file_is_a_model_file_error(tmp_path):
    with pytest.raises(ModelFileError, match="model file not found"):
        load_model(tmp_path / "nope.pt")


def test_text_file_is_not_a_model_file(tmp_path):
    bad = tmp_path / "data.csv"
    bad.write_text("joint_1,x\n0.1,0.2\n")
    with pytest.raises(ModelFileError, match="is not a hybrid_pk model file"):
        load_model(bad)


@pytest.mark.parametrize(
    ("name", "text", "why"),
    [
        ("empty.pt", "", "it is empty"),
        ("diag.json", '{"robot": "ur5"}', "it is not a torch archive"),
        ("notes.pt", "hello", "it is not a torch archive"),
    ],
)
def test_empty_or_text_file_says_why_it_is_not_a_model_file(tmp_path, name, text, why):
    """An empty file gave 'cannot be read as one: )' and a JSON file 'it holds Python
    objects besides tensors': the reason names what the file is."""
    bad = tmp_path / name
    bad.write_text(text)
    with pytest.raises(ModelFileError, match=re.escape(f"model file ({why}); model files")):
        load_model(bad)


def test_torch_file_without_the_format_tag_is_not_a_model_file(tmp_path):
    other = tmp_path / "weights.pt"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, other)
    with pytest.raises(ModelFileError, match=r"no 'hybrid_pk\.model' format tag"):
        load_model(other)


def test_truncated_model_file_is_refused(rx160, tmp_path):
    path = save_model(tmp_path / "m.pt", ExtendedModel(rx160))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match="not a hybrid_pk model file"):
        load_model(path)


def test_newer_format_version_asks_for_an_upgrade(rx160, tmp_path):
    path = save_model(tmp_path / "m.pt", ExtendedModel(rx160))
    payload = torch.load(path, weights_only=True)
    payload["version"] = mf.FORMAT_VERSION + 1
    torch.save(payload, path)
    newer = mf.FORMAT_VERSION + 1
    with pytest.raises(ModelFileError, match=rf"format version {newer}.*upgrade hybrid_pk"):
        load_model(path)


def test_urdf_given_as_model_suggests_nominal(tmp_path):
    with pytest.raises(ModelFileError, match="nominal:"):
        load_model(ARM7)


def test_save_refuses_what_cannot_be_loaded_safely(rx160, tmp_path):
    with pytest.raises(ModelFileError, match=r"networks\['net'\]: cannot store a object"):
        save_model(tmp_path / "m.pt", ExtendedModel(rx160), networks={"net": object()})
    assert not (tmp_path / "m.pt").exists()


# ----------------------------------------------------------------------------- URDF export


def _geometric_model(robot: Robot, labels_values: list, offsets: list = ()) -> ExtendedModel:
    effects = [make_effect(robot, label, value) for label, value in labels_values]
    effects += [make_effect(robot, label, value) for label, value in offsets]
    return ExtendedModel(robot, effects)


GEOMETRIC_CASES = {
    # fixed joint inside the chain (mount before j3), prismatic j4, tilted j3 axis
    "arm7": (
        str(ARM7),
        [
            ("link_length:j3", [1e-3, -2e-3, 5e-4]),
            ("axis_misalignment:j3", [0.0, 8e-4, -6e-4]),
            ("link_length:j4", [1e-3, 0.0, 0.0]),
            ("axis_misalignment:j5", [0.0, 1e-3, 1e-3]),
            ("thermal_expansion", 1.2e-5),
        ],
        [("joint_offset:j4", 3e-3), ("joint_offset:j2", 1e-3)],
    ),
    # fixed flange joint after the last actuated joint, pitch-90-degree origins
    "ur10": (
        "ur10",
        [
            ("link_length:elbow_joint", [1e-3, 2e-3, 3e-3]),
            ("axis_misalignment:wrist_1_joint", [1e-3, 0.0, 2e-3]),
            ("thermal_expansion", -2e-5),
        ],
        [("joint_offset:wrist_3_joint", 2e-3)],
    ),
}


def _reference_cond(n: int) -> Conditions:
    return Conditions(temperature=torch.full((n,), REFERENCE_TEMPERATURE, dtype=F64))


@pytest.mark.parametrize("case", list(GEOMETRIC_CASES))
def test_exported_urdf_reproduces_the_geometric_model(case, tmp_path):
    urdf, geometric, _ = GEOMETRIC_CASES[case]
    robot = Robot.from_urdf(urdf, end_link="tool0")
    model = _geometric_model(robot, geometric)
    path = export_urdf(model, tmp_path / "cal.urdf")

    exported = Robot.from_urdf(path, end_link="tool0")

    q = robot.sample_q(50, torch.Generator().manual_seed(5))
    with torch.no_grad():
        expected = model.end_pose(q, _reference_cond(50))
        assert_transforms_close(exported.fk(q), expected, atol_pos=1e-9, atol_rot=1e-9)
        # the correction is real: the nominal URDF is millimetres off
        assert float((robot.fk(q) - expected)[:, :3, 3].norm(dim=-1).max()) > 1e-4
    assert exported.joint_names == robot.joint_names
    assert torch.equal(exported.segment_mass, robot.segment_mass)  # inertials kept


@pytest.mark.parametrize("case", list(GEOMETRIC_CASES))
def test_exported_urdf_folds_joint_offsets_when_asked(case, tmp_path):
    urdf, geometric, offsets = GEOMETRIC_CASES[case]
    robot = Robot.from_urdf(urdf, end_link="tool0")
    model = _geometric_model(robot, geometric, offsets)
    q = robot.sample_q(30, torch.Generator().manual_seed(6))
    with torch.no_grad():
        expected = model.end_pose(q, _reference_cond(30))
        without_offsets = _geometric_model(robot, geometric).end_pose(q, _reference_cond(30))

    folded = Robot.from_urdf(
        export_urdf(model, tmp_path / "f.urdf", fold_joint_offsets=True), end_link="tool0"
    )
    listed = Robot.from_urdf(export_urdf(model, tmp_path / "l.urdf"), end_link="tool0")

    with torch.no_grad():
        assert_transforms_close(folded.fk(q), expected, atol_pos=1e-9, atol_rot=1e-9)
        assert_transforms_close(listed.fk(q), without_offsets, atol_pos=1e-9, atol_rot=1e-9)
    text = (tmp_path / "l.urdf").read_text()
    for label, _ in offsets:
        assert f"hybrid_pk calibration: {label} = " in text


def test_exported_urdf_with_frames_gives_the_measured_pose(rx160, tmp_path):
    model = _model(rx160, sets=1)
    model.effects = torch.nn.ModuleList(
        [make_effect(rx160, "link_length:joint_3", [2e-3, 0, 1e-3])]
    )
    path = export_urdf(model, tmp_path / "frames.urdf", include_base=True, include_tool=True)

    exported = Robot.from_urdf(path)

    assert exported.root_link == "measurement_frame"
    assert exported.end_link == "measured_point"
    q = rx160.sample_q(20, torch.Generator().manual_seed(7))
    with torch.no_grad():
        assert_transforms_close(exported.fk(q), model(q), atol_pos=1e-9, atol_rot=1e-9)


def test_export_header_lists_every_effect_with_its_unit(rx160):
    model = _model(rx160, sets=1)
    text = corrected_urdf(model)
    header = text[text.index("<!-- hybrid_pk calibration") :].split("-->")[0]
    for e in model.effects:
        assert f"{e.label} = " in header, e.label
        line = next(ln for ln in header.splitlines() if f"{e.label} = " in ln)
        assert line.rstrip().endswith(e.unit), line
    assert "not representable in URDF" in header
    assert "base frame T_measurement_base_link" in header

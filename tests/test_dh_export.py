"""``hybrid-pk export``: a calibrated model as DH, MDH, UR kinematics YAML and URDF.

Each file is read back by ``tests/dh_reader.py`` (written from the formats'
definitions, not from the exporter) and must reproduce the model's geometric FK (its
geometric effects and joint offsets) to 1e-9 m on 1,000 random configurations; the
effects a geometric file cannot carry are listed in the summary with their size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.data.ipa import convert_ipa
from hybrid_pk.effects import Conditions, ExtendedModel, make_effect
from hybrid_pk.effects.joint import JointOffset
from hybrid_pk.io.dh_export import model_dh_table, write_dh_yaml
from hybrid_pk.io.export_summary import left_out
from hybrid_pk.io.model_file import load_model, save_model
from hybrid_pk.io.ur_calibration import write_ur_calibration
from tests.dh_reader import chain_pose, read_table_yaml, ur_pose
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

REPO = Path(__file__).resolve().parents[1]
SERIES_B = REPO.parent / "shared" / "data" / "ipa-ur10" / "Series_B"
SERIES_B_FILE = SERIES_B / "measurements_joint_configurations.csv"
TOL = 1e-9  # [m] the acceptance: the files carry the geometry to well below a nanometre


def _geometric_pose(model: ExtendedModel, q: torch.Tensor) -> np.ndarray:
    """The model's geometric FK, built here: its robot with the link-length and axis
    effects (the geometry stage) and joint offsets added to the commanded joints."""
    geometric = [e for e in model.effects if e.stage == "geometry"]
    offsets = torch.zeros(model.robot.dof, dtype=torch.float64)
    for e in model.effects:
        if isinstance(e, JointOffset):
            offsets[e.joint_index] += e.value.detach()
    with torch.no_grad():
        return model.with_effects(geometric).end_pose(q + offsets).numpy()


def _check_files(model: ExtendedModel, tmp_path: Path) -> dict[str, float]:
    """Write DH, MDH and UR YAML, read each back independently; the largest position
    and rotation-element error against the geometric FK per format."""
    q = model.robot.sample_q(1000, torch.Generator().manual_seed(7))
    want = _geometric_pose(model, q)
    errors = {}
    for convention in ("dh", "mdh"):
        path = write_dh_yaml(model_dh_table(model, convention), tmp_path / f"{convention}.yaml")
        table = read_table_yaml(path)
        got = chain_pose(table["rows"], convention, q.numpy(), *table["frames"])
        errors[convention] = float(np.abs(got - want)[:, :3, :].max())
    if model.robot.dof == 6:
        path, _ = write_ur_calibration(model, tmp_path / "ur.yaml")
        errors["ur"] = float(np.abs(ur_pose(path, q.numpy()) - want)[:, :3, :].max())
    return errors


@pytest.fixture(scope="module")
def calibrated_ur10(tmp_path_factory) -> Path:
    """A UR10 model calibrated on every 12th row of the shared Series B (125 of 1,495
    configurations): joint offsets, axis misalignments, a link length and a joint
    compliance, base and tool frames fitted as ``hybrid-pk calibrate`` does."""
    if not SERIES_B_FILE.is_file():
        pytest.skip(f"shared data not found: {SERIES_B_FILE}")
    tmp = tmp_path_factory.mktemp("ur10_export")
    convert_ipa(SERIES_B_FILE, tmp / "all.csv")
    pd.read_csv(tmp / "all.csv").iloc[::12].to_csv(tmp / "rows.csv", index=False)
    effects = [
        "joint_offset:shoulder_lift_joint",
        "joint_offset:elbow_joint",
        "axis_misalignment:elbow_joint",
        "axis_misalignment:wrist_1_joint",
        "link_length:wrist_1_joint",
        "joint_compliance:shoulder_lift_joint",
    ]
    out = tmp / "model.pt"
    argv = ["calibrate", str(tmp / "rows.csv"), "--robot", "ur10", "--no-urdf"]
    assert main([*argv, "--effects", ",".join(effects), "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_calibrated_ur10_exports_reproduce_geometry(calibrated_ur10, tmp_path, capsys):
    """Acceptance: DH, MDH and UR YAML of a UR10 calibrated on real data rebuild its
    geometric FK to 1e-9 m; the compliance is listed with its size, not dropped."""
    model = load_model(calibrated_ur10).model
    assert any(e.stage == "geometry" for e in model.effects)
    errors = _check_files(model, tmp_path)
    print(f"largest element error per format [m, 1]: {errors}")
    assert max(errors.values()) < TOL, errors
    for fmt, suffix in (
        ("dh", "yaml"),
        ("mdh", "yaml"),
        ("ur-calibration", "yaml"),
        ("urdf", "urdf"),
    ):
        out = tmp_path / f"cli_{fmt}.{suffix}"
        argv = ["export", str(calibrated_ur10), "--format", fmt, "--out", str(out)]
        assert main(argv) == 0
        printed = capsys.readouterr().out
        assert "joint_compliance:shoulder_lift_joint" in printed
        assert "mm rms" in printed
        assert "125 measured points" in printed  # the model's own calibration rows
        # a DH table holds the UR10's link masses, and says so (tests/test_dh_export_mass.py)
        assert ("link masses written" in printed) == (fmt in ("dh", "mdh")), printed
        if suffix == "yaml":
            assert "joint_compliance:shoulder_lift_joint" in out.read_text(encoding="utf-8")
    with torch.no_grad():
        urdf = Robot.from_urdf(tmp_path / "cli_urdf.urdf").fk(
            torch.zeros(1, 6, dtype=torch.float64)
        )
    assert (
        np.abs(urdf.numpy() - _geometric_pose(model, torch.zeros(1, 6, dtype=torch.float64))).max()
        < TOL
    )


def _random_model(robot: Robot, rng: np.random.Generator) -> ExtendedModel:
    """Geometric effects and offsets of random size on random joints, plus effects no
    geometric file carries."""
    joints = robot.joint_names
    picks = rng.choice(len(joints), size=3, replace=False)
    effects = [make_effect(robot, f"joint_offset:{joints[i]}", rng.normal(0, 2e-3)) for i in picks]
    for i in rng.choice(len(joints), size=3, replace=False):
        effects.append(make_effect(robot, f"axis_misalignment:{joints[i]}", rng.normal(0, 2e-3, 2)))
        effects.append(make_effect(robot, f"link_length:{joints[i]}", rng.normal(0, 2e-3, 3)))
    # a compliance where gravity loads the joint (the last joint's axis carries none: a
    # compliance there moves nothing, the summary rightly sizes it 0)
    q = robot.sample_q(64, torch.Generator().manual_seed(0))
    loaded = [
        j for j, t in zip(joints, robot.gravity_torques(q).abs().amax(0), strict=True) if t > 1.0
    ]
    soft = str(rng.choice(loaded))
    effects.append(make_effect(robot, f"joint_compliance:{soft}", abs(rng.normal(2e-5, 5e-6))))
    effects.append(make_effect(robot, f"backlash:{joints[-1]}", abs(rng.normal(1e-3, 2e-4))))
    return ExtendedModel(robot, effects)


@pytest.mark.parametrize("name", ["ur10", "rx160"])
def test_random_geometry_exports_and_summary(name, tmp_path):
    """Random geometric effects on random joints: every format rebuilds the geometry to
    1e-9 m; the left-out effects are exactly the non-geometric ones, each with the size
    the full model moves without it."""
    robot = Robot.from_urdf(name)
    robot.requires_grad_(False)
    rng = run_rng(f"dh-export-{name}")
    model = _random_model(robot, rng)
    model.requires_grad_(False)
    errors = _check_files(model, tmp_path)
    assert max(errors.values()) < TOL, errors
    save_model(tmp_path / "m.pt", model)
    q = robot.sample_q(200, torch.Generator().manual_seed(3))
    cond = Conditions(direction=torch.ones_like(q))
    items = left_out(load_model(tmp_path / "m.pt"), q, cond)
    named = [i.what for i in items]
    carried_not = [
        e.label for e in model.effects if e.stage != "geometry" and not isinstance(e, JointOffset)
    ]
    assert named == [*carried_not, "total"]
    with torch.no_grad():
        full = model(q, cond)
        for item, label in zip(items, carried_not, strict=False):
            others = [e for e in model.effects if e.label != label]
            moved = (full - model.with_effects(others)(q, cond))[:, :3, 3].norm(dim=-1) * 1000
            # abs: the compliance fixed point's tolerance (1e-12 rad) over a 10 m lever,
            # reached from another warm start in each evaluation (seed 606: 2e-8 mm for a
            # wrist backlash that moves the flange 1.5e-9 mm): 1e-7 mm, 0.1 nm
            assert item.size_mm[1] == pytest.approx(float(moved.max()), rel=1e-9, abs=1e-7)
            assert max(item.size_mm[1], item.turn_mrad) > 0


def test_ur_yaml_of_the_ur10(tmp_path, ur10):
    """UR's own DH table gives the kinematics ur_description derives from it (shoulder
    up d1; upper_arm roll pi/2; forearm x a2; wrist_1 x a3, z d4; wrist_2 y -d5, roll
    pi/2; wrist_3 y d6, roll pi/2, pitch pi, yaw pi), compared as transforms; the
    shipped ur10 (root base_link) with --ur-root base_link rebuilds its own FK after
    base_link_inertia = base_link Rz(pi)."""
    from tests.dh_reader import pose
    from tests.test_dh import UR10_DH, _table

    robot = Robot.from_dh(_table(UR10_DH, "dh"), "dh")
    path, note = write_ur_calibration(ExtendedModel(robot), tmp_path / "dh.yaml")
    assert note is None
    d1, a2, a3, d4, d5, d6 = 0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922
    pi = np.pi
    want = [
        pose((0, 0, d1), (0, 0, 0)),
        pose((0, 0, 0), (pi / 2, 0, 0)),
        pose((a2, 0, 0), (0, 0, 0)),
        pose((a3, 0, d4), (0, 0, 0)),
        pose((0, -d5, 0), (pi / 2, 0, 0)),
        pose((0, d6, 0), (pi / 2, pi, pi)),
    ]
    qq = robot.sample_q(50, torch.Generator().manual_seed(4)).numpy()
    got = ur_pose(path, qq)
    expect = np.broadcast_to(np.eye(4), (50, 4, 4)).copy()
    for i, E in enumerate(want):
        expect = expect @ E @ _rz(qq[:, i])
    assert np.abs(got - expect).max() < 1e-12
    shipped, note = write_ur_calibration(ExtendedModel(ur10), tmp_path / "s.yaml", root="base_link")
    q = ur10.sample_q(200, torch.Generator().manual_seed(5))
    with torch.no_grad():
        fk = ur10.fk(q).numpy()
    inertia_in_base = pose((0, 0, 0), (0, 0, pi))  # base_link -> base_link_inertia
    assert np.abs(inertia_in_base @ ur_pose(shipped, q.numpy()) - fk).max() < 1e-9
    assert note is None  # its 12-digit pi/2 tilts tool0 by 5e-12 rad: rounding, not said


def test_ur_root_is_taken_from_the_geometry(tmp_path, ur10, capsys):
    """export --format ur-calibration without --ur-root: the shipped ur10 (arm along +x
    at zero) is written as base_link, UR's DH table (along -x) as base_link_inertia, each
    said; a --ur-root that contradicts the geometry is warned about."""
    from tests.test_dh import UR10_DH, _table

    from_dh = Robot.from_dh(_table(UR10_DH, "dh"), "dh")
    for robot, root in ((ur10, "base_link"), (from_dh, "base_link_inertia")):
        model = save_model(tmp_path / f"{root}.pt", ExtendedModel(robot))
        argv = ["export", str(model), "--format", "ur-calibration", "--out"]
        assert main([*argv, str(tmp_path / "auto.yaml")]) == 0
        assert f"root link taken as {root}:" in capsys.readouterr().out
        assert main([*argv, str(tmp_path / "given.yaml"), "--ur-root", root]) == 0
        assert "warning" not in capsys.readouterr().out
        body = [
            (tmp_path / f).read_text().split("kinematics:")[1] for f in ("auto.yaml", "given.yaml")
        ]
        assert body[0] == body[1]
        other = "base_link" if root == "base_link_inertia" else "base_link_inertia"
        assert main([*argv, str(tmp_path / "other.yaml"), "--ur-root", other]) == 0
        assert f"warning: --ur-root {other}, but" in capsys.readouterr().out


def _rz(angle: np.ndarray) -> np.ndarray:
    T = np.zeros((len(angle), 4, 4))
    c, s = np.cos(angle), np.sin(angle)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1
    return T


def test_networks_listed_with_their_size(tmp_path, rx160, capsys):
    """A model file with residual networks: the export lists them with the size of
    their correction at the points (never silently dropped)."""
    from hybrid_pk.hybrid import HybridFK, InputBox
    from hybrid_pk.io import save_hybrid

    base = ExtendedModel(rx160, [make_effect(rx160, "joint_offset:joint_2", 1e-3)])
    q = rx160.sample_q(64, torch.Generator().manual_seed(1))
    torch.manual_seed(0)
    scale = torch.full((3,), 1e-3, dtype=torch.float64)
    hybrid = HybridFK.build(base, InputBox.from_data(q, None, fade=0.2), "mlp:8x2", None, scale)
    path = save_hybrid(tmp_path / "hybrid.pt", hybrid.eval())
    items = left_out(load_model(path), q, Conditions())
    assert [i.what for i in items] == ["residual networks", "total"]
    with torch.no_grad():
        moved = (hybrid(q) - base(q))[:, :3, 3].norm(dim=-1).max() * 1000
    assert items[0].size_mm[1] == pytest.approx(float(moved), rel=1e-9)
    out = tmp_path / "t.yaml"
    argv = ["export", str(path), "--format", "mdh", "--data", str(_table_of(rx160, q, tmp_path))]
    assert main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "  residual networks: " in printed  # not 'residual networks = -:'
    assert "the 64 measured points" in printed


def _table_of(robot: Robot, q: torch.Tensor, tmp_path: Path) -> Path:
    """A pose table at joint values ``q`` (the nominal flange: only ``q`` is read)."""
    with torch.no_grad():
        p = robot.fk(q)[:, :3, 3].numpy()
    frame = pd.DataFrame(q.numpy(), columns=robot.joint_names)
    frame[["x", "y", "z"]] = p
    path = tmp_path / "points.csv"
    frame.to_csv(path, index=False)
    return path


def test_mimic_chain_is_refused_naming_its_mimic_joints():
    # the message listed every chain joint (dsr_joint1..6 too) as "mimic joints"
    robot = Robot.from_urdf("column_arm", end_link="tool0")
    with pytest.raises(Exception, match="mimic joints") as err:
        model_dh_table(ExtendedModel(robot), "dh")
    text = str(err.value)
    assert "(column_middle_joint, column_top_joint)" in text
    assert "dsr_joint1" not in text

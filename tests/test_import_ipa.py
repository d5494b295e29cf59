"""``hybrid-pk import ipa``: conversion of the published UR10 laser-tracker files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from scipy.spatial.transform import Rotation

from hybrid_pk.cli.main import main
from hybrid_pk.data import read_table
from hybrid_pk.data.ipa import (
    GOAL_CONVENTION,
    MEASUREMENT_ANGLES,
    MEASUREMENT_CONVENTION,
    UR_JOINT_NAMES,
    detect_euler_convention,
    detect_ipa_conventions,
)

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
IPA = SHARED / "data" / "ipa-ur10"
SERIES_A = IPA / "Series_A" / "measurements_grid.csv"
SERIES_B = IPA / "Series_B" / "measurements_joint_configurations.csv"
HANDEYE = IPA / "Series_B" / "calibration_handeye.csv"
TWO_PI = 2 * math.pi
UR10_LIMITS = {
    "joint_names": UR_JOINT_NAMES,
    "lower": [-TWO_PI, -TWO_PI, -math.pi, -TWO_PI, -TWO_PI, -TWO_PI],
    "upper": [TWO_PI, TWO_PI, math.pi, TWO_PI, TWO_PI, TWO_PI],
}

needs_shared = pytest.mark.skipif(not IPA.is_dir(), reason=f"shared data not found at {IPA}")


def _rx(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _matrix(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """Rotation matrix of a unit quaternion, written out (not the library's function)."""
    return np.array(
        [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
            [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
            [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)],
        ]
    )


def _one_error_line(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    return err


@pytest.fixture(scope="module")
def converted(tmp_path_factory) -> dict[str, Path]:
    """Both shared series converted by the CLI (A to CSV, B to Parquet)."""
    if not IPA.is_dir():
        pytest.skip(f"shared data not found at {IPA}")
    out = tmp_path_factory.mktemp("ipa")
    paths = {"A": out / "series_a.csv", "B": out / "series_b.parquet"}
    assert main(["import", "ipa", str(SERIES_A), "--out", str(paths["A"])]) == 0
    assert main(["import", "ipa", str(SERIES_B), "--out", str(paths["B"])]) == 0
    return paths


@needs_shared
def test_rows_match_hand_computation(converted):
    a = pd.read_csv(converted["A"])
    b = pd.read_parquet(converted["B"])
    # Source rows copied from the files: joints [rad]; rx, ry, rz [deg]; x, y, z written
    # in m by hand from the file's mm (2361,9831 mm -> 2.3619831 m).
    cases = [
        (a, 0, [-1.5708, -1.5708, 0.0, -1.5708, 0.0, 0.0], [2.3619831, -1.3685474, 0.11939713],
         [-90.409151, -59.885105, -90.887438], 23.6800003051758),
        (a, 1, [-2.14055, -2.08493, -0.837441, -0.218756, 0.393594, -0.00187856],
         [1.6852797, -1.6653456, -0.41581103], [-90.282663, -49.675357, -90.926009],
         23.6800003051758),
        (b, 0, [-3.14159, -1.5708, 0.0, -1.5708, 0.0, 0.0], [0.38376294, -3.2408734, 0.20193157],
         [-90.179302, -20.118749, -90.169308], 21.86750031),
    ]  # fmt: skip
    for table, k, joints, metres, (rx, ry, rz), temperature in cases:
        row = table.iloc[k]
        assert row[list(UR_JOINT_NAMES)].tolist() == joints
        assert row[["x", "y", "z"]].tolist() == metres
        assert row["temperature"] == temperature
        expected = _rx(rx) @ _ry(ry) @ _rz(rz)  # intrinsic x-y'-z''
        quat = row[["qw", "qx", "qy", "qz"]].to_numpy(float)
        assert quat[0] >= 0
        np.testing.assert_allclose(_matrix(*quat), expected, atol=1e-14)
    # Row 1 of Series A by hand: q = qx(rx/2) * qy(ry/2) * qz(rz/2), Hamilton product.
    np.testing.assert_allclose(
        a.loc[0, ["qw", "qx", "qy", "qz"]].to_numpy(float),
        [0.680744444672422, -0.1808356610527434, -0.6849013823797772, -0.18653568332499665],
        rtol=0,
        atol=1e-14,
    )
    assert list(b.columns[-6:]) == [
        "std_x_mm", "std_y_mm", "std_z_mm", "std_rx_deg", "std_ry_deg", "std_rz_deg"
    ]  # fmt: skip
    assert b.loc[0, "std_x_mm"] == 0.031674


@needs_shared
def test_converted_tables_reread_cleanly_with_unit_quaternions(converted):
    for key, n in (("A", 11911), ("B", 1495)):
        if key == "B":
            with pytest.warns(UserWarning, match="ignored extra column"):
                data = read_table(converted[key], **UR10_LIMITS, n_params=42)
            assert data.ignored_columns[0] == "std_x_mm"
        else:
            data = read_table(converted[key], **UR10_LIMITS, n_params=42)
        assert data.n == n
        assert data.t is None
        assert data.skipped == ()
        norm = data.quat.norm(dim=1)
        assert torch.all((norm - 1).abs() < 1e-12)
        assert torch.all(data.quat[:, 0] >= 0)


@needs_shared
def test_cli_prints_a_short_summary(capsys, tmp_path):
    assert main(["import", "ipa", str(SERIES_B), "--out", str(tmp_path / "b.csv")]) == 0
    out = capsys.readouterr().out
    assert "1495 rows" in out
    assert "temperature 21.62 .. 22.24 °C" in out
    assert "intrinsic 'XYZ'" in out
    assert "detected" not in out
    argv = ["import", "ipa", str(SERIES_B), "--out", str(tmp_path / "b.csv")]
    assert main([*argv, "--convention", "auto"]) == 0
    assert (
        "intrinsic 'XYZ' (R = Rx(a) Ry(b) Rz(c)), detected on the file" in capsys.readouterr().out
    )


@needs_shared
def test_several_sources_go_to_a_directory(capsys, tmp_path):
    out = tmp_path / "converted"
    assert main(["import", "ipa", str(SERIES_A), str(SERIES_B), "--out", str(out / "a.csv")]) == 2
    assert "is a table but 2 sources were given" in capsys.readouterr().err
    assert main(["import", "ipa", str(SERIES_A), str(SERIES_B), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "measurements_grid.csv",
        "measurements_joint_configurations.csv",
    ]


@needs_shared
@pytest.mark.parametrize("series", [SERIES_A, SERIES_B], ids=["A", "B"])
def test_detected_conventions_are_the_defaults(series):
    goal, measurement = detect_ipa_conventions(series)
    assert goal.convention == GOAL_CONVENTION == "xyz"
    assert goal.runner_up.fit_deg > 50 * goal.best.fit_deg
    assert measurement.convention == MEASUREMENT_CONVENTION == "XYZ"
    assert measurement.best.fit_deg < 0.2
    assert measurement.runner_up.fit_deg > measurement.best.fit_deg


@needs_shared
def test_handeye_poses_separate_xyz_from_its_transposed_twin():
    raw = pd.read_csv(HANDEYE, sep=";", decimal=",")
    flange = Rotation.from_quat(raw[["flange_qx", "flange_qy", "flange_qz", "flange_qw"]])
    found = detect_euler_convention(raw[list(MEASUREMENT_ANGLES)].to_numpy(), flange.as_matrix())
    assert found.convention == MEASUREMENT_CONVENTION
    assert found.best.fit_deg < 0.1
    twin = next(s for s in found.scores if s.sequence == "zyx")
    assert twin.pair_deg == pytest.approx(found.best.pair_deg, rel=1e-9)  # pairwise is blind
    assert twin.fit_deg > 10
    assert found.runner_up.fit_deg > 5


@pytest.mark.parametrize("truth", ["ZYX", "xzy", "ZXZ"])
def test_detect_euler_convention_recovers_a_synthetic_sequence(truth):
    rng = np.random.default_rng(7)
    reference = Rotation.random(300, random_state=rng)
    base, tool = Rotation.random(2, random_state=rng)
    measured = base * reference * tool
    angles = measured.as_euler(truth, degrees=True)
    found = detect_euler_convention(angles, reference.as_matrix())
    assert truth in found.equivalent
    assert found.best.fit_deg < 1e-9
    known = detect_euler_convention(angles, reference.as_matrix(), left=base.as_matrix())
    assert known.convention == truth
    assert known.equivalent == (truth,)


# ----------------------------------------------------------------------------- bad input


def _ipa_file(tmp_path, text: str) -> Path:
    path = tmp_path / "ipa.csv"
    path.write_text(text)
    return path


_HEADER = (
    "Timestamp;Goal x;Goal y;Goal z;Goal roll;Goal pitch;Goal yaw;shoulder_pan_joint;"
    "shoulder_lift_joint;elbow_joint;wrist_1_joint;wrist_2_joint;wrist_3_joint;"
    "measurement_temperature;measurement_x;measurement_y;measurement_z;measurement_rx;"
    "measurement_ry;measurement_rz"
)
_ROW = (
    "1;0,3;0;1,4;1,57;1,57;1,57;-1,5708;-1,5708;0,0;-1,5708;0,0;0,0;23,68;"
    "2361,98;-1368,5;119,3;-90,4;-59,8;-90,8"
)


def test_cli_unparsable_number_names_file_row_column(capsys, tmp_path):
    bad = _ROW.replace("2361,98", "2361,98mm")
    path = _ipa_file(tmp_path, "\n".join([_HEADER, _ROW, bad]) + "\n")
    err = _one_error_line(capsys, ["import", "ipa", str(path), "--out", str(tmp_path / "o.csv")])
    assert f"{path}, row 2, column 'measurement_x': cannot read '2361,98mm'" in err


def test_cli_a_file_that_is_not_utf8_names_file_and_row(capsys, tmp_path):
    # before: "'utf-8' codec can't decode byte 0xb0 in position ...", no file named
    path = _ipa_file(tmp_path, "\n".join([_HEADER, _ROW, _ROW]) + "\n")
    text = path.read_bytes()
    path.write_bytes(text[: len(text) - 5] + b"\xb0" + text[len(text) - 5 :])  # a Latin-1 degree
    err = _one_error_line(capsys, ["import", "ipa", str(path), "--out", str(tmp_path / "o.csv")])
    assert f"{path}, row 2: byte 0xb0 (at byte {len(text) - 5}) is not UTF-8 text" in err


def test_cli_missing_column_lists_missing_and_found(capsys, tmp_path):
    header = _HEADER.replace(";measurement_temperature", "")
    row = _ROW.replace(";23,68", "")
    path = _ipa_file(tmp_path, f"{header}\n{row}\n")
    err = _one_error_line(capsys, ["import", "ipa", str(path), "--out", str(tmp_path / "o.csv")])
    assert f"{path}: missing column(s) 'measurement_temperature'" in err
    assert "found columns: Timestamp, Goal x" in err


def test_cli_empty_cell_names_file_row_column(capsys, tmp_path):
    path = _ipa_file(tmp_path, "\n".join([_HEADER, _ROW, _ROW.replace("-59,8", "")]) + "\n")
    err = _one_error_line(capsys, ["import", "ipa", str(path), "--out", str(tmp_path / "o.csv")])
    assert f"{path}, row 2, column 'measurement_ry': cannot read ''" in err


def test_cli_missing_source_and_bad_output_type(capsys, tmp_path):
    missing = tmp_path / "nope.csv"
    err = _one_error_line(capsys, ["import", "ipa", str(missing), "--out", str(tmp_path / "o.csv")])
    assert f"{missing}: no such file" in err
    path = _ipa_file(tmp_path, f"{_HEADER}\n{_ROW}\n")
    err = _one_error_line(capsys, ["import", "ipa", str(path), "--out", str(tmp_path / "o.txt")])
    assert "unsupported file type '.txt'" in err


_JOINTS = ";-1,5708;-1,5708;0,0;-1,5708;0,0;0,0;"  # the joint cells of _ROW


@pytest.mark.parametrize(
    ("joints", "column", "says"),
    [
        (";180;-1,5708;0,0;-1,5708;0,0;0,0;", "shoulder_pan_joint", "looks like degrees"),
        (";-1,5708;-1,5708;3,5;-1,5708;0,0;0,0;", "elbow_joint", "joint 'elbow_joint' value "
         "3.5 rad outside its limits [-3.14159, 3.14159] rad"),
    ],
)  # fmt: skip
def test_cli_a_joint_the_ur10_cannot_take_names_file_row_column(
    capsys, tmp_path, joints, column, says
):
    """A joint value that the table reader refuses for the UR10 (a 180 in a radian
    column, an elbow beyond +-pi) is refused at import, naming the source file, its row
    and column, and nothing is written (before: rc 0, a table every command refuses)."""
    bad = _ROW.replace(_JOINTS, joints, 1)
    path = _ipa_file(tmp_path, "\n".join([_HEADER, _ROW, _ROW, bad]) + "\n")
    out = tmp_path / "o.csv"
    err = _one_error_line(capsys, ["import", "ipa", str(path), "--out", str(out)])
    assert f"{path}, row 3, column '{column}': {says}" in err, err
    assert not out.exists()


def test_cli_format_that_disagrees_with_the_out_table_is_a_usage_error(capsys, tmp_path):
    """--format parquet --out x.csv: one line naming both, nothing written (before: a CSV
    written, --format ignored); --format that agrees, and --format for a directory of
    several tables, still write."""
    path = _ipa_file(tmp_path, f"{_HEADER}\n{_ROW}\n")
    for fmt, out in (("parquet", "x.csv"), ("csv", "x.pq")):
        argv = ["import", "ipa", str(path), "--format", fmt, "--out", str(tmp_path / out)]
        err = _one_error_line(capsys, argv)
        assert f"--format {fmt} disagrees with --out {tmp_path / out}, a " in err, err
        assert not (tmp_path / out).exists()
    assert (
        main(["import", "ipa", str(path), "--format", "parquet", "--out", str(tmp_path / "x.pq")])
        == 0
    )
    other = tmp_path / "other.csv"
    other.write_text(path.read_text())
    argv = ["import", "ipa", str(path), str(other), "--format", "parquet", "--out"]
    assert main([*argv, str(tmp_path / "series")]) == 0
    assert sorted(p.name for p in (tmp_path / "series").iterdir()) == [
        "ipa.parquet",
        "other.parquet",
    ]


def test_cli_help_states_units(capsys):
    with pytest.raises(SystemExit):
        main(["import", "ipa", "--help"])
    out = capsys.readouterr().out
    for unit in ("[rad]", "[mm]", "[deg]", "[m]", "°C"):
        assert unit in out


def test_cli_a_folder_out_that_would_replace_a_source_is_refused(capsys, tmp_path):
    path = _ipa_file(tmp_path, f"{_HEADER}\n{_ROW}\n")
    before = path.read_bytes()
    err = _one_error_line(capsys, ["import", "ipa", str(path), "--out", str(tmp_path)])
    assert f"{path}: --out {tmp_path}: its table ipa.csv would replace this source" in err
    assert path.read_bytes() == before


def test_cli_several_series_are_converted_all_or_none(capsys, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    good, bad = src / "measurements_a.csv", src / "measurements_b.csv"
    good.write_text(f"{_HEADER}\n{_ROW}\n")
    bad.write_text(f"{_HEADER}\n{_ROW.replace('2361,98', 'oops')}\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "measurements_a.csv").write_text("ORIGINAL\n")
    err = _one_error_line(capsys, ["import", "ipa", str(good), str(bad), "--out", str(out)])
    assert f"{bad}, row 1, column 'measurement_x'" in err
    assert (out / "measurements_a.csv").read_text() == "ORIGINAL\n"  # the first not replaced
    assert sorted(p.name for p in out.iterdir()) == ["measurements_a.csv"]
    bad.write_text(f"{_HEADER}\n{_ROW}\n")
    assert main(["import", "ipa", str(good), str(bad), "--out", str(out)]) == 0
    assert (out / "measurements_a.csv").read_text().startswith("shoulder_pan_joint,")

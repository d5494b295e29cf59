"""``hybrid-pk import columns``: general column-mapping import of tracker exports."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from hybrid_pk.cli.main import main
from hybrid_pk.data import read_table_for
from hybrid_pk.data.mapping import (
    convert_columns,
    load_column_map,
    parse_inline_map,
    read_mapped,
)
from hybrid_pk.errors import DataError
from hybrid_pk.robot import Robot
from hybrid_pk.simulate import simulate_campaign

UR = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def _elementary(axis: str, angle: float) -> np.ndarray:
    """Rotation about a coordinate axis, written out (independent of scipy)."""
    c, s = math.cos(angle), math.sin(angle)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis.lower()]


def _euler_oracle(seq: str, angles: np.ndarray) -> np.ndarray:
    """Intrinsic (upper case): R = R1(a) R2(b) R3(c); extrinsic: R = R3(c) R2(b) R1(a)."""
    mats = [_elementary(ax, a) for ax, a in zip(seq, angles, strict=True)]
    if seq.isupper():
        return mats[0] @ mats[1] @ mats[2]
    return mats[2] @ mats[1] @ mats[0]


def _quat_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _write(path, header: list[str], rows: list[list], sep=",", decimal=".", preamble=()):
    def cell(v) -> str:
        return f"{v:.12g}".replace(".", decimal) if isinstance(v, float) else str(v)

    lines = [*preamble, sep.join(header)]
    lines += [sep.join(cell(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.fixture
def leica_like(tmp_path):
    """A ';'/',' export with 2 comment lines, mm, deg joints, intrinsic ZYX deg, ms."""
    rng = np.random.default_rng(3)
    n = 6
    q = rng.uniform(-2.5, 2.5, (n, 6))
    pos = rng.uniform(-3, 3, (n, 3))
    eul = rng.uniform(-80, 80, (n, 3))
    header = ["J1", "J2", "J3", "J4", "J5", "J6", "X [mm]", "Y [mm]", "Z [mm]"]
    header += ["A", "B", "C", "Time [ms]", "Air"]
    rows = [[*np.degrees(q[k]), *(1000 * pos[k]), *eul[k], 12.5 * k, 20.0 + k] for k in range(n)]
    path = _write(
        tmp_path / "export.csv",
        header,
        [[float(v) for v in r] for r in rows],
        sep=";",
        decimal=",",
        preamble=("# Tracker export", "# units: mm, deg"),
    )
    return path, q, pos, eul


def _inline(seq_cols=("A", "B", "C")) -> str:
    joints = ",".join(f"{name}=J{k + 1}[deg]" for k, name in enumerate(UR))
    e = ",".join(f"e{k + 1}={c}[deg]" for k, c in enumerate(seq_cols))
    return f"{joints},x=X [mm],y=Y [mm],z=Z [mm],{e},t=Time [ms][ms],temperature=Air[C]"


def test_inline_map_converts_units_separators_and_intrinsic_euler(leica_like, tmp_path):
    path, q, pos, eul = leica_like
    cmap = parse_inline_map(_inline(), separator=";", decimal=",", skip_lines=2, euler="ZYX")
    table = read_mapped(path, cmap).frame
    np.testing.assert_allclose(table[list(UR)].to_numpy(), q, atol=1e-10)
    np.testing.assert_allclose(table[["x", "y", "z"]].to_numpy(), pos, atol=1e-12)
    np.testing.assert_allclose(table["t"].to_numpy(), 0.0125 * np.arange(len(q)), atol=1e-12)
    np.testing.assert_allclose(table["temperature"].to_numpy(), 20.0 + np.arange(len(q)))
    for k in range(len(q)):
        R = _quat_matrix(*table[["qw", "qx", "qy", "qz"]].to_numpy()[k])
        np.testing.assert_allclose(R, _euler_oracle("ZYX", np.radians(eul[k])), atol=1e-10)
    assert (table["qw"] >= 0).all()
    assert list(table.columns[:6]) == list(UR)


@pytest.mark.parametrize("seq", ["XYZ", "xyz", "ZYX", "zyx", "ZYZ", "yzx"])
@pytest.mark.parametrize("unit", ["deg", "rad"])
def test_any_scipy_euler_sequence_matches_the_written_out_rotation(tmp_path, seq, unit):
    rng = np.random.default_rng(7)
    angles = rng.uniform(-1.2, 1.2, (4, 3))
    written = np.degrees(angles) if unit == "deg" else angles
    rows = [[0.1, 0.2, 0.3, 1.0, 2.0, 3.0, *map(float, written[k])] for k in range(4)]
    header = ["j1", "j2", "j3", "px", "py", "pz", "a", "b", "c"]
    path = _write(tmp_path / "e.csv", header, rows)
    cmap = load_column_map(
        {
            "columns": {"j1": "j1", "j2": "j2", "j3": "j3", "x": "px", "y": "py", "z": "pz"},
            "euler": {"sequence": seq, "columns": ["a", "b", "c"], "unit": unit},
        }
    )
    frame = read_mapped(path, cmap).frame
    for k in range(4):
        R = _quat_matrix(*frame[["qw", "qx", "qy", "qz"]].to_numpy()[k])
        np.testing.assert_allclose(R, _euler_oracle(seq, angles[k]), atol=1e-10)


def _foreign_export(tmp_path, data, order: str) -> tuple:
    """``data`` written as another tracker would: mm, deg joints, quaternion in ``order``."""
    quat = data.quat.numpy()  # (w, x, y, z)
    idx = ["wxyz".index(c) for c in order]
    header = [f"Joint{k}" for k in range(1, 7)] + ["PX", "PY", "PZ"]
    header += [f"Q{k}" for k in range(1, 5)] + ["Temp"]
    rows = [
        [
            *np.degrees(data.q[k].numpy()),
            *(1000 * data.position[k].numpy()),
            *quat[k, idx],
            float(data.temperature[k]),
        ]
        for k in range(data.n)
    ]
    return _write(tmp_path / "foreign.txt", header, [[float(v) for v in r] for r in rows], "\t")


@pytest.mark.parametrize("fmt", ["json", "yaml"])
def test_map_file_round_trips_a_campaign_with_xyzw_quaternions(tmp_path, fmt):
    robot = Robot.from_urdf("ur10")
    data, _ = simulate_campaign(robot, 12, "none", noise_mm=0.01, noise_deg=0.01, seed=4)
    src = _foreign_export(tmp_path, data, "xyzw")
    spec = {
        "separator": "tab",
        "units": {"length": "mm", "angle": "deg"},
        "columns": {
            **{name: f"Joint{k + 1}" for k, name in enumerate(UR)},
            "x": "PX",
            "y": "PY",
            "z": "PZ",
            "temperature": "Temp",
        },
        "quaternion": {"columns": ["Q1", "Q2", "Q3", "Q4"], "order": "xyzw"},
    }
    map_path = tmp_path / f"map.{fmt}"
    if fmt == "json":
        map_path.write_text(json.dumps(spec))
    else:
        map_path.write_text(yaml.safe_dump(spec))
    dst = tmp_path / "table.parquet"
    result = convert_columns(src, dst, load_column_map(map_path))
    assert result.n_rows == data.n
    back = read_table_for(dst, robot, n_params=1)
    torch.testing.assert_close(back.q, data.q, atol=1e-10, rtol=0)
    torch.testing.assert_close(back.position, data.position, atol=1e-10, rtol=0)
    # q and -q are one rotation: compare up to sign
    sign = torch.sign((back.quat * data.quat).sum(-1, keepdim=True))
    torch.testing.assert_close(back.quat * sign, data.quat, atol=1e-10, rtol=0)


def test_datetime_time_column_gives_seconds_since_first_row(tmp_path):
    rows = [
        ["2024-03-01 10:00:00.000", 0.1, 1.0, 2.0, 3.0],
        ["2024-03-01 10:00:00.250", 0.2, 1.0, 2.0, 3.0],
        ["2024-03-01 10:00:01.500", 0.3, 1.0, 2.0, 3.0],
    ]
    path = _write(tmp_path / "d.csv", ["when", "j", "X", "Y", "Z"], rows)
    cmap = parse_inline_map("t=when,j=j,x=X,y=Y,z=Z", time_format="datetime")
    np.testing.assert_allclose(read_mapped(path, cmap).frame["t"], [0.0, 0.25, 1.5])


# ----------------------------------------------------------------------------- errors


def _simple(tmp_path, cells: list[list], header=("J", "X", "Y", "Z")):
    return _write(tmp_path / "bad.csv", list(header), cells)


@pytest.mark.parametrize(
    ("cells", "inline", "row", "column", "words"),
    [
        ([[0.1, 1.0, 2.0, 3.0], [0.2, "abc", 2.0, 3.0]], "j=J,x=X,y=Y,z=Z", 2, "X", "text"),
        ([[0.1, 1.0, 2.0, 3.0], [0.2, "nan", 2.0, 3.0]], "j=J,x=X,y=Y,z=Z", 2, "X", "NaN"),
        ([[0.1, 1.0, 2.0, 3.0], [0.2, "", 2.0, 3.0]], "j=J,x=X,y=Y,z=Z", 2, "X", "empty"),
        ([[0.1, 1500.0, 2.0, 3.0], [0.2, 1.0, 2.0, 3.0]], "j=J,x=X,y=Y,z=Z", 1, "X", "mm"),
        ([[90.0, 1.0, 2.0, 3.0], [45.0, 1.0, 2.0, 3.0]], "j=J,x=X,y=Y,z=Z", 1, "J", "degrees"),
        ([[0.1, '"1,5"', 2.0, 3.0]], "j=J,x=X,y=Y,z=Z", 1, "X", "decimal"),
    ],
)
def test_bad_cells_name_file_row_and_column(tmp_path, cells, inline, row, column, words):
    path = _simple(tmp_path, cells)
    with pytest.raises(DataError) as info:
        read_mapped(path, parse_inline_map(inline))
    err = info.value
    assert (err.file, err.row, err.column) == (str(path), row, column)
    assert words in str(err)
    assert "\n" not in str(err)


def test_missing_column_suggests_the_close_name(tmp_path):
    path = _simple(tmp_path, [[0.1, 1.0, 2.0, 3.0]], header=("J", "X_mm", "Y", "Z"))
    with pytest.raises(DataError, match=r"missing source column 'X_m'.*found 'X_mm'\?"):
        read_mapped(path, parse_inline_map("j=J,x=X_m,y=Y,z=Z"))


def test_wrong_separator_is_named(tmp_path):
    path = _write(tmp_path / "s.csv", ["J", "X", "Y", "Z"], [[0.1, 1.0, 2.0, 3.0]], sep=";")
    with pytest.raises(DataError, match="check the separator"):
        read_mapped(path, parse_inline_map("j=J,x=X,y=Y,z=Z"))


@pytest.mark.parametrize("n_rows", [1, 3])
def test_row_with_more_fields_than_the_header_is_an_error(tmp_path, n_rows):
    rows = [[0.1, 1.0, 2.0, 3.0]] * (n_rows - 1) + [[0.2, 1, 5, 2.0, 3.0]]
    path = _simple(tmp_path, rows)
    with pytest.raises(DataError, match="fields") as exc:
        read_mapped(path, parse_inline_map("j=J,x=X,y=Y,z=Z"))
    if n_rows == 1:  # pandas' warning path (the first data row is the long one)
        assert exc.value.row == 1
        assert exc.value.column == "field 5"
        assert str(path) in str(exc.value)


def test_non_unit_quaternion_points_at_the_order(tmp_path):
    rows = [[0.1, 1.0, 2.0, 3.0, 0.5, 0.5, 0.5, 0.2]]
    path = _write(tmp_path / "q.csv", ["J", "X", "Y", "Z", "a", "b", "c", "d"], rows)
    inline = "j=J,x=X,y=Y,z=Z,qw=a,qx=b,qy=c,qz=d"
    with pytest.raises(DataError, match=r"row 1.*quaternion norm .* order") as info:
        read_mapped(path, parse_inline_map(inline))
    assert info.value.row == 1


def test_decreasing_time_is_an_error(tmp_path):
    rows = [[0.0, 0.1, 1.0, 2.0, 3.0], [2.0, 0.1, 1.0, 2.0, 3.0], [1.0, 0.1, 1.0, 2.0, 3.0]]
    path = _write(tmp_path / "t.csv", ["T", "J", "X", "Y", "Z"], rows)
    with pytest.raises(DataError, match="time decreases") as info:
        read_mapped(path, parse_inline_map("t=T,j=J,x=X,y=Y,z=Z"))
    assert (info.value.row, info.value.column) == (3, "T")


@pytest.mark.parametrize(
    ("inline", "options", "words"),
    [
        ("j=J,x=X,y=Y", {}, "partial position"),
        ("j=J,x=X[parsec],y=Y,z=Z", {}, "unknown unit 'parsec'"),
        ("j=J,x=X[deg],y=Y,z=Z", {}, "expected a length unit"),
        ("j=J,x=X,y=Y,z=Z,e1=A,e2=B,e3=C", {}, "need a sequence, e.g. --euler XYZ"),
        ("j=J,x=X,y=Y,z=Z,e1=A,e2=B,e3=C", {"euler": "XYQ"}, "Euler sequence"),
        ("j=J,x", {}, "TARGET=SOURCE"),
        ("j=J,j=K,x=X,y=Y,z=Z", {}, "given twice"),
        ("j=J,x=X,y=Y,z=Z", {"decimal": "ab"}, "decimal 'ab' must be one character"),
        ("j=J,x=X,y=Y,z=Z", {"separator": ";", "decimal": ";"}, "other than the separator"),
    ],
)
def test_bad_maps_are_one_line_errors(inline, options, words):
    with pytest.raises(DataError, match=words):
        parse_inline_map(inline, **options)


def test_skip_bad_rows_reports_every_left_out_row(tmp_path):
    cells = [[0.1, 1.0, 2.0, 3.0], [0.2, "x", 2.0, 3.0], [0.3, 1.0, 2.0, 3.0], [0.4, 1.0, "", 3.0]]
    path = _simple(tmp_path, cells)
    table = read_mapped(path, parse_inline_map("j=J,x=X,y=Y,z=Z"), skip_bad_rows=True)
    assert [s.row for s in table.skipped] == [2, 4]
    np.testing.assert_array_equal(table.rows, [1, 3])
    np.testing.assert_allclose(table.frame["j"], [0.1, 0.3])


# ----------------------------------------------------------------------------- CLI


def test_cli_import_columns_writes_a_table_valid_for_the_robot(leica_like, tmp_path, capsys):
    path, _, pos, _ = leica_like
    dst = tmp_path / "table.csv"
    argv = ["import", "columns", str(path), "--map", _inline(), "--sep", ";", "--decimal", ","]
    argv += ["--skip-lines", "2", "--euler", "ZYX", "--out", str(dst), "--robot", "ur10"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "6 rows" in out
    assert "validated for ur10" in out
    table = pd.read_csv(dst)
    np.testing.assert_allclose(table[["x", "y", "z"]].to_numpy(), pos, atol=1e-12)


def test_cli_import_columns_checked_for_a_robot_replaces_nothing_it_refuses(
    leica_like, tmp_path, capsys
):
    """The tables are validated for --robot before any replaces a file (the table was
    written, then refused, rc 2, with the earlier file gone)."""
    path = leica_like[0]
    dst = tmp_path / "table.csv"
    dst.write_text("ORIGINAL\n")
    argv = ["import", "columns", str(path), "--map", _inline(), "--sep", ";", "--decimal", ","]
    argv += ["--skip-lines", "2", "--euler", "ZYX", "--out", str(dst), "--robot", "rx160"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert str(dst) in err
    assert ".table.csv." not in err  # named as the table it would be, not its temporary
    assert dst.read_text() == "ORIGINAL\n"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_cli_import_columns_error_is_one_line_with_location(tmp_path, capsys):
    path = _simple(tmp_path, [[0.1, 1.0, 2.0, 3.0], [0.2, "oops", 2.0, 3.0]])
    argv = ["import", "columns", str(path), "--map", "j=J,x=X,y=Y,z=Z", "--out"]
    assert main([*argv, str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "bad.csv, row 2, column 'X'" in err


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        (["--decimal", "ab"], "--decimal 'ab': give the decimal mark, one character (. or ,)"),
        (["--decimal", ";"], "--decimal ';' is also the field separator (--sep); the two must"),
    ],
)
def test_cli_decimal_is_one_character_other_than_the_separator(tmp_path, capsys, flags, says):
    """--decimal ab, or --decimal equal to --sep: one line naming the flag, nothing
    written (before: "row 1, column 'X': text '1,5' in a numeric column")."""
    path = _write(tmp_path / "e.csv", ["J", "X", "Y", "Z"], [[0.1, 1.5, 2.0, 3.0]], ";", ",")
    dst = tmp_path / "o.csv"
    argv = ["import", "columns", str(path), "--map", "j=J,x=X,y=Y,z=Z", "--sep", ";", *flags]
    assert main([*argv, "--out", str(dst)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"hybrid-pk import columns: error: {says}" in err, err
    assert not dst.exists()
    assert main([*argv[:-2], "--decimal", ",", "--out", str(dst)]) == 0
    assert pd.read_csv(dst)["x"].tolist() == [1.5]

"""Measured pose table: every bad-input kind of contract section 1, skip mode, round trips."""

from __future__ import annotations

import math
import re
import warnings
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from hybrid_pk.data import (
    IgnoredColumnsWarning,
    MeasuredData,
    RepeatedRowsWarning,
    SkippedRowsWarning,
    read_table,
    read_table_for,
    write_table,
)
from hybrid_pk.errors import DataError

JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
TWO_PI = 2 * math.pi
LOWER = [-TWO_PI, -TWO_PI, -math.pi, -TWO_PI, -TWO_PI, -TWO_PI]
UPPER = [TWO_PI, TWO_PI, math.pi, TWO_PI, TWO_PI, TWO_PI]
UR10 = {"joint_names": JOINTS, "lower": LOWER, "upper": UPPER}


def _frame(n: int, *, quat: bool = True, seed: int = 0, **extra: np.ndarray) -> pd.DataFrame:
    """A valid UR10-like table with ``n`` rows."""
    rng = np.random.default_rng(seed)
    cols = {name: rng.uniform(-1.5, 1.5, n) for name in JOINTS}
    cols.update(x=rng.uniform(-1, 1, n), y=rng.uniform(-1, 1, n), z=rng.uniform(0, 1, n))
    if quat:
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        cols.update(qw=q[:, 0], qx=q[:, 1], qy=q[:, 2], qz=q[:, 3])
    cols.update(extra)
    return pd.DataFrame(cols)


def _csv(tmp_path, frame: pd.DataFrame, name: str = "meas.csv"):
    path = tmp_path / name
    frame.to_csv(path, index=False)
    return path


def _set(frame: pd.DataFrame, row: int, column: str, value) -> pd.DataFrame:
    """Copy of ``frame`` with 1-based data ``row`` of ``column`` replaced (as text)."""
    frame = frame.astype(object)
    frame.loc[row - 1, column] = value
    return frame


def _where(path, row: int | None, column: str | None) -> str:
    """Regex for the location prefix DataError puts in front of the message."""
    parts = [re.escape(str(path))]
    if row is not None:
        parts.append(f"row {row}")
    if column is not None:
        parts.append(re.escape(f"column {column!r}"))
    return ", ".join(parts) + ": "


def _raises(path, row, column, message, **kwargs) -> DataError:
    with pytest.raises(DataError, match=_where(path, row, column) + message) as info:
        read_table(path, **{**UR10, **kwargs})
    assert "\n" not in str(info.value)  # the CLI prints it as one line
    assert (info.value.file, info.value.row, info.value.column) == (str(path), row, column)
    return info.value


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("value", "message"),
    [("nan", "value is NaN"), ("inf", "value is inf"), ("-inf", "value is -inf")],
)
def test_non_finite_value_names_file_row_column(tmp_path, value, message):
    path = _csv(tmp_path, _set(_frame(5), 3, "y", value))
    _raises(path, 3, "y", message)


def test_empty_cell_is_reported_not_dropped(tmp_path):
    path = _csv(tmp_path, _set(_frame(5), 4, "elbow_joint", ""))
    _raises(path, 4, "elbow_joint", "empty value")


def test_row_with_extra_field_names_the_row(tmp_path):
    path = _csv(tmp_path, _frame(4))
    lines = path.read_text().splitlines()
    lines[3] += ",0.5"  # data row 3
    path.write_text("\n".join(lines) + "\n")
    _raises(path, 3, "field 14", re.escape("14 fields where the header has 13: field 14 ('0.5')"))


@pytest.mark.parametrize("rows", [(1,), (1, 2, 3, 4)])
def test_extra_field_in_first_row_is_an_error_not_dropped(tmp_path, rows):
    # pandas (index_col=False) drops these with only a ParserWarning
    path = _csv(tmp_path, _frame(4))
    lines = path.read_text().splitlines()
    for row in rows:
        lines[row] += f",{row}.25"
    path.write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and no pandas warning either
        _raises(
            path, 1, "field 14", re.escape("14 fields where the header has 13: field 14 ('1.25')")
        )


def test_extra_field_row_is_counted_without_blank_lines(tmp_path):
    path = _csv(tmp_path, _frame(4))
    lines = path.read_text().splitlines()
    lines[3] += ",7"  # data row 3
    lines.insert(2, "")  # a blank line before it
    path.write_text("\n".join(lines) + "\n")
    _raises(path, 3, "field 14", "14 fields where the header has 13")


def test_row_with_missing_field_is_an_empty_value(tmp_path):
    path = _csv(tmp_path, _frame(4))
    lines = path.read_text().splitlines()
    lines[2] = lines[2].rsplit(",", 1)[0]  # data row 2 lacks qz
    path.write_text("\n".join(lines) + "\n")
    _raises(path, 2, "qz", "empty value")


def test_text_in_numeric_column_shows_the_text(tmp_path):
    path = _csv(tmp_path, _set(_frame(5), 2, "wrist_1_joint", "12,5 deg"))
    _raises(path, 2, "wrist_1_joint", re.escape("text '12,5 deg' in a numeric column"))


def test_first_bad_row_over_all_columns_is_reported(tmp_path):
    frame = _set(_set(_frame(6), 5, "shoulder_pan_joint", "nan"), 2, "z", "abc")
    _raises(_csv(tmp_path, frame), 2, "z", "text 'abc'")


def test_missing_joint_columns_lists_missing_and_found(tmp_path):
    path = _csv(tmp_path, _frame(5).drop(columns=["elbow_joint", "wrist_3_joint"]))
    err = _raises(path, None, None, "missing joint column\\(s\\) 'elbow_joint', 'wrist_3_joint'")
    assert "found columns: shoulder_pan_joint, shoulder_lift_joint, wrist_1_joint" in str(err)


def test_missing_joint_column_suggests_close_name(tmp_path):
    path = _csv(tmp_path, _frame(5).rename(columns={"elbow_joint": "Elbow_joint"}))
    err = _raises(path, None, None, "missing joint column")
    assert "'elbow_joint' (found 'Elbow_joint'?)" in str(err)


def test_joint_and_position_columns_in_other_case_are_named_as_close_matches(tmp_path):
    """Names match exactly; a header in capitals ('ELBOW_JOINT', 'X') gets the hint that a
    misspelling gets."""
    frame = _frame(3).rename(columns={"elbow_joint": "ELBOW_JOINT", "x": "X"})
    path = _csv(tmp_path, frame)
    _raises(
        path, None, None, ".*" + re.escape("close matches: 'elbow_joint' (found 'ELBOW_JOINT'?)")
    )
    path = _csv(tmp_path, _frame(3).rename(columns={"x": "X"}), "xyz.csv")
    found_x = re.escape("close matches: 'x' (found 'X'?)")
    _raises(path, None, None, ".*" + re.escape("[m]; found columns: ") + ".*" + found_x)


def test_missing_position_column(tmp_path):
    path = _csv(tmp_path, _frame(5).drop(columns=["z"]))
    _raises(path, None, None, re.escape("missing position column(s) 'z' [m]"))


def test_duplicated_csv_header_is_detected_before_pandas_renames_it(tmp_path):
    path = tmp_path / "dup.csv"
    frame = _frame(3)
    text = frame.to_csv(index=False).splitlines()
    text[0] = text[0] + ",x"
    path.write_text("\n".join([text[0], *(r + ",0.5" for r in text[1:])]) + "\n")
    _raises(path, None, "x", "duplicated header: column 'x' appears at positions 7 and 14")


def test_duplicated_parquet_column_is_detected(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    frame = _frame(3)
    arrays = [pa.array(frame[c]) for c in frame.columns] + [pa.array(frame["qw"])]
    path = tmp_path / "dup.parquet"
    pq.write_table(pa.table(arrays, names=[*frame.columns, "qw"]), path)
    _raises(path, None, "qw", "duplicated header: column 'qw'")


def test_non_unit_quaternion_beyond_tolerance(tmp_path):
    frame = _frame(5)
    frame.loc[3, ["qw", "qx", "qy", "qz"]] *= 1 + 3e-6  # data row 4
    frame.loc[1, ["qw", "qx", "qy", "qz"]] *= 1 + 5e-7  # within 1e-6: accepted
    _raises(_csv(tmp_path, frame), 4, "qw..qz", "quaternion norm 1.000003 is not 1 within 1e-06")


def test_joint_outside_limits_names_joint_value_and_limits(tmp_path):
    path = _csv(tmp_path, _set(_frame(5), 5, "elbow_joint", 3.5))
    _raises(
        path,
        5,
        "elbow_joint",
        re.escape("joint 'elbow_joint' value 3.5 rad outside its limits [-3.14159, 3.14159] rad"),
    )


def test_degrees_in_radian_column_reported_before_limits(tmp_path):
    frame = _frame(8)
    frame["shoulder_lift_joint"] = np.degrees(frame["shoulder_lift_joint"])
    frame.loc[2, "shoulder_lift_joint"] = -87.3  # largest magnitude, data row 3
    path = _csv(tmp_path, frame)
    _raises(
        path, 3, "shoulder_lift_joint", re.escape("looks like degrees (max 87.3); convert to rad")
    )
    # a file-level problem: asking to skip bad rows does not hide it
    _raises(path, 3, "shoulder_lift_joint", "looks like degrees", on_bad_row="skip")


def test_positions_in_mm_are_refused_with_file_row_column(tmp_path):
    """x, y, z written in mm (a tracker 2-3 m away: thousands) is a file-level error,
    never a diagnosis of 550 m errors; the largest value's row and column are named."""
    frame = _frame(8)
    frame[["x", "y", "z"]] = 1000 * (frame[["x", "y", "z"]] + [2.0, -1.0, 0.5])
    frame.loc[4, "y"] = -3456.5  # largest magnitude, data row 5
    path = _csv(tmp_path, frame)
    message = re.escape("position 3456.5 m: looks like mm")
    _raises(path, 5, "y", message)
    _raises(path, 5, "y", message, on_bad_row="skip")
    # a robot cell 20 m from the tracker, in metres, is read as it is
    frame = _frame(8)
    frame["x"] += 20.0
    assert read_table(_csv(tmp_path, frame, "far.csv"), **UR10).n == 8


def test_single_large_radian_typo_is_a_limit_error_not_degrees(tmp_path):
    path = _csv(tmp_path, _set(_frame(8), 6, "wrist_2_joint", 7.0))
    _raises(path, 6, "wrist_2_joint", "joint 'wrist_2_joint' value 7 rad outside")


def test_continuous_joint_is_not_checked_for_limits_or_degrees(tmp_path):
    frame = _frame(4)
    frame["wrist_3_joint"] = [20.0, -30.0, 45.0, 90.0]
    types = ["revolute"] * 5 + ["continuous"]
    data = read_table(_csv(tmp_path, frame), **UR10, joint_types=types)
    assert data.q[:, 5].tolist() == [20.0, -30.0, 45.0, 90.0]


def test_fewer_rows_than_parameters(tmp_path):
    path = _csv(tmp_path, _frame(5))
    _raises(path, None, None, "needs at least 42 rows for 42 parameters, found 5", n_params=42)
    assert read_table(path, **UR10, n_params=5).n == 5


def test_partial_orientation_columns(tmp_path):
    path = _csv(tmp_path, _frame(4).drop(columns=["qx", "qz"]))
    _raises(path, None, "qx", "partial orientation: found qw, qy but not qx, qz")


def test_time_not_monotonic_within_a_file(tmp_path):
    path = _csv(tmp_path, _frame(5, t=np.array([0.0, 1.0, 2.0, 1.5, 3.0])))
    _raises(path, 4, "t", "time stamp decreases from 2 s \\(row 3\\) to 1.5 s")


def test_empty_csv_file(tmp_path):
    path = tmp_path / "empty.csv"
    path.write_text("")
    _raises(path, None, None, "empty file")


@pytest.mark.parametrize("bom", [b"", b"\xef\xbb\xbf"])
def test_a_file_that_is_not_utf8_names_its_row_and_byte(tmp_path, bom):
    # before: "'utf-8' codec can't decode byte 0xe9 in position 62: ...", no file named
    text = _frame(3).to_csv(index=False).encode()
    lines = text.split(b"\n")
    lines[2] = lines[2].replace(b",", b",\xe9", 1)  # a Latin-1 e-acute in data row 2
    path = tmp_path / "latin1.csv"
    path.write_bytes(bom + b"\n".join(lines))
    at = len(bom) + len(b"\n".join(lines[:2])) + 1 + lines[2].index(b"\xe9")
    what = f"byte 0xe9 \\(at byte {at}\\) is not UTF-8 text: save the table as UTF-8"
    _raises(path, 2, None, what)
    path.write_bytes(bom + b"x\xe9" + b"\n".join(lines))  # in the header
    _raises(path, None, None, "the header: byte 0xe9")


def test_header_without_rows(tmp_path):
    path = tmp_path / "header.csv"
    path.write_text(",".join(_frame(1).columns) + "\n")
    _raises(path, None, None, "empty file: the header has no data rows")


def test_unsupported_extension(tmp_path):
    path = tmp_path / "meas.xlsx"
    path.write_text("x")
    _raises(path, None, None, "unsupported file type '.xlsx'; expected .csv, .parquet or .pq")


def test_semicolon_file_gets_a_hint(tmp_path):
    path = tmp_path / "semi.csv"
    _frame(3).to_csv(path, sep=";", index=False)
    err = _raises(path, None, None, "missing joint column")
    assert "looks ';'-separated" in str(err)


def test_files_of_one_read_need_the_same_columns(tmp_path):
    a = _csv(tmp_path, _frame(3), "a.csv")
    b = _csv(tmp_path, _frame(3, quat=False), "b.csv")
    with pytest.raises(DataError, match=_where(b, None, None) + "has no orientation column"):
        read_table([a, b], **UR10)


def test_a_file_given_twice_is_refused(tmp_path):
    # before: read twice, every row counted twice (and on both sides of a hold-out)
    a = _csv(tmp_path, _frame(3), "a.csv")
    with pytest.raises(DataError, match=_where(a, None, None) + "given twice: give each"):
        read_table([a, tmp_path / "." / "a.csv"], **UR10)


def test_a_copy_of_a_file_under_another_name_is_noted(tmp_path):
    # before: no word; the copy's rows counted twice
    frame = _frame(4, t=np.arange(4.0))
    a, b = _csv(tmp_path, frame, "a.csv"), _csv(tmp_path, frame.assign(t=frame.t + 9), "b.csv")
    copy = f"{re.escape(str(b))} repeats {re.escape(str(a))} row for row"
    with pytest.warns(RepeatedRowsWarning, match=copy):
        assert read_table([a, b], **UR10).n == 8
    # one measurement apart by a micrometre: two campaigns, no note
    c = _csv(tmp_path, _set(frame, 3, "x", float(frame.x[2]) + 1e-6), "c.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RepeatedRowsWarning)
        assert read_table([a, c], **UR10).n == 8


# ----------------------------------------------------------------------------- skip mode


def test_skip_mode_reports_count_and_rows_of_every_skipped_row(tmp_path):
    frame = _set(_frame(8), 2, "x", "nan")
    frame = _set(frame, 5, "elbow_joint", 4.0)
    frame = _set(frame, 7, "qw", 2.0)
    path = _csv(tmp_path, frame)
    with pytest.warns(
        SkippedRowsWarning, match=re.escape(f"skipped 3 bad row(s): {path} rows 2, 5, 7")
    ):
        data = read_table(path, **UR10, on_bad_row="skip")
    assert data.n == 5
    assert data.rows.tolist() == [1, 3, 4, 6, 8]
    assert [(s.file, s.row) for s in data.skipped] == [
        (str(path), 2),
        (str(path), 5),
        (str(path), 7),
    ]
    assert data.skipped[0].reason == "column 'x': value is NaN"
    assert "outside its limits" in data.skipped[1].reason
    assert "quaternion norm" in data.skipped[2].reason


def test_skip_mode_with_every_row_bad_raises(tmp_path):
    frame = _frame(2)
    frame["y"] = np.nan
    _raises(_csv(tmp_path, frame), None, None, "no valid rows: all 2 data rows", on_bad_row="skip")


def test_n_params_counts_rows_left_after_skipping(tmp_path):
    path = _csv(tmp_path, _set(_frame(4), 1, "x", "bad"))
    message = re.escape("needs at least 4 rows for 4 parameters, found 3 (1 bad row(s) skipped)")
    _raises(path, None, None, message, on_bad_row="skip", n_params=4)


# ----------------------------------------------------------------------------- good input


def test_extra_columns_are_listed_once_as_ignored(tmp_path):
    a = _csv(tmp_path, _frame(3, operator=np.zeros(3), std_x_mm=np.ones(3)), "a.csv")
    b = _csv(tmp_path, _frame(3, seed=1, operator=np.zeros(3)), "b.csv")  # not a copy of a
    with pytest.warns(IgnoredColumnsWarning) as record:
        data = read_table([a, b], **UR10)
    assert data.ignored_columns == ("operator", "std_x_mm")
    assert len(record) == 1
    assert "operator, std_x_mm" in str(record[0].message)


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".pq"])
def test_write_read_round_trip_is_exact(tmp_path, suffix):
    rng = np.random.default_rng(3)
    n = 50
    extra = {
        "t": np.cumsum(rng.uniform(0, 1e-3, n)),
        "temperature": rng.uniform(18, 25, n),
        "payload": 10 ** rng.uniform(-3, 1, n),
    }
    source = read_table(_csv(tmp_path, _frame(n, seed=4, **extra)), **UR10)
    path = write_table(tmp_path / f"out{suffix}", source)
    again = read_table(path, **UR10)
    for name in ("q", "position", "quat", "t", "temperature", "payload"):
        assert torch.equal(getattr(again, name), getattr(source, name)), name
    assert again.q.dtype == torch.float64
    assert list(
        pd.read_csv(path).columns if suffix == ".csv" else pd.read_parquet(path).columns
    ) == [*JOINTS, "x", "y", "z", "qw", "qx", "qy", "qz", "t", "temperature", "payload"]


def test_position_only_table(tmp_path):
    data = read_table(_csv(tmp_path, _frame(4, quat=False)), **UR10)
    assert not data.has_orientation
    assert data.quat is None
    T = data.T_measured()
    assert T.shape == (4, 4, 4)
    assert torch.equal(T[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
    assert torch.equal(T[:, :3, 3], data.position)


def test_T_measured_uses_the_quaternion(tmp_path):
    frame = _frame(1)
    half = math.radians(30) / 2  # 30 deg about z
    frame.loc[0, ["qw", "qx", "qy", "qz"]] = [math.cos(half), 0.0, 0.0, math.sin(half)]
    T = read_table(_csv(tmp_path, frame), **UR10).T_measured()[0]
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    expected = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(T[:3, :3], expected, rtol=0, atol=1e-15)


def test_multiple_files_give_file_index_and_rows(tmp_path):
    a = _csv(tmp_path, _frame(3, seed=1), "series_a.csv")
    b = write_table(
        tmp_path / "series_b.parquet",
        read_table(_csv(tmp_path, _frame(2, seed=2), "b.csv"), **UR10),
    )
    data = read_table([a, b], **UR10)
    assert data.sources == (str(a), str(b))
    assert data.file_index.tolist() == [0, 0, 0, 1, 1]
    assert data.rows.tolist() == [1, 2, 3, 1, 2]
    assert data.n == 5
    assert data.dof == 6


def test_subset_and_concat(tmp_path):
    data = read_table(_csv(tmp_path, _frame(6)), **UR10)
    head, tail = data.subset(slice(0, 2)), data.subset(torch.tensor([5, 3]))
    assert tail.rows.tolist() == [6, 4]
    both = MeasuredData.concat([head, tail])
    assert both.sources == data.sources  # the same file keeps one index
    assert both.file_index.tolist() == [0, 0, 0, 0]
    assert torch.equal(both.q, data.q[[0, 1, 5, 3]])
    mask = data.subset(data.position[:, 0] > 0)
    assert mask.n == int((data.position[:, 0] > 0).sum())


def test_concat_refuses_mixed_orientation(tmp_path):
    with_quat = read_table(_csv(tmp_path, _frame(2), "a.csv"), **UR10)
    without = read_table(_csv(tmp_path, _frame(2, quat=False), "b.csv"), **UR10)
    with pytest.raises(DataError, match="only some have 'quat'"):
        MeasuredData.concat([with_quat, without])


def test_read_table_for_takes_joints_limits_and_parameter_count_from_a_robot(tmp_path):
    robot = SimpleNamespace(
        joint_names=list(JOINTS),
        joint_limits=(torch.tensor(LOWER), torch.tensor(UPPER)),
        joint_types=["revolute"] * 6,
        n_kinematic_params=10,
    )
    path = _csv(tmp_path, _frame(4))
    with pytest.raises(DataError, match="needs at least 10 rows for 10 parameters, found 4"):
        read_table_for(path, robot)
    assert read_table_for(path, robot, n_params=None).joint_names == JOINTS


def test_targets_without_joint_columns(tmp_path):
    frame = _frame(3).drop(columns=list(JOINTS))
    data = read_table(_csv(tmp_path, frame), **UR10, require_joints=False)
    assert data.q.shape == (3, 0)
    assert data.joint_names == ()
    _raises(_csv(tmp_path, frame, "t2.csv"), None, None, "missing joint column")


@pytest.mark.parametrize("module", ["hybrid_pk.data", "hybrid_pk.data.table", "hybrid_pk.data.ipa"])
def test_every_name_in_all_resolves(module):
    import importlib

    mod = importlib.import_module(module)
    missing = [name for name in mod.__all__ if not hasattr(mod, name)]
    assert missing == []


def test_a_data_file_that_does_not_exist_is_named(tmp_path, capsys):
    """read_table / read_table_for and every command reading DATA (evaluate, calibrate,
    export --data) say 'FILE: file not found' (before: '[Errno 2] No such file or
    directory: ...', the text of Python's OSError)."""
    from hybrid_pk.cli.main import main

    missing = tmp_path / "nothere.csv"
    with pytest.raises(DataError, match=r"nothere\.csv: file not found"):
        read_table(missing, **UR10)
    for argv in (
        ["evaluate", "nominal:rx160", str(missing)],
        ["calibrate", str(missing), "--robot", "rx160", "--out", str(tmp_path / "m.pt")],
        ["diagnose", str(missing), "--robot", "rx160", "--json", str(tmp_path / "d.json")],
    ):
        assert main(argv) != 0
        err = capsys.readouterr().err
        assert "nothere.csv: file not found" in err, err
        assert "Errno" not in err


@pytest.mark.parametrize(
    ("column", "value", "message"),
    [
        ("payload", -2.0, "a payload is a mass >= 0 kg"),
        ("payload", 5000.0, "looks like grams"),
        ("temperature", 295.0, "looks like kelvin"),
        ("temperature", -400.0, "below absolute zero (-273.15 °C)"),
    ],
)
def test_payload_and_temperature_in_other_units_are_refused(tmp_path, column, value, message):
    """A negative payload, a payload in grams (beyond the heaviest arm's 2.3 t), a
    temperature in kelvin and one below absolute zero name file, row and column (before:
    read as kg / degC; a 5 kg payload written as 5000 made evaluate report a 36 deg mean
    orientation error; -400 °C was accepted)."""
    frame = _frame(5, payload=np.full(5, 2.0), temperature=np.full(5, 22.0))
    path = _csv(tmp_path, _set(frame, 3, column, value))
    with pytest.raises(DataError, match=_where(path, 3, column) + ".*" + re.escape(message)):
        read_table(path, **UR10)


@pytest.mark.parametrize("column", ["shoulder_pan_joint", "z", "payload"])
@pytest.mark.parametrize("nulls", [False, True])
def test_a_boolean_parquet_column_is_no_numbers(tmp_path, column, nulls):
    """A Parquet column of booleans, with or without nulls, names file and column (before:
    True / False read as 1 / 0 rad, m or kg, rc 0)."""
    frame = _frame(5, payload=np.full(5, 2.0))
    flags = [True, False, True, False, True]
    frame[column] = pd.array([None, *flags[1:]] if nulls else flags, dtype="boolean")
    path = tmp_path / "bool.parquet"
    frame.to_parquet(path)
    _raises(path, None, column, "boolean, expected numbers")


def test_cli_refuses_a_boolean_joint_column_and_a_temperature_below_absolute_zero(tmp_path, capsys):
    """evaluate on a table with a boolean joint column or a -400 °C temperature: one line
    naming file (and row) and column, exit code 2 (before: rc 0)."""
    from hybrid_pk.cli.main import main

    names = [f"joint_{k}" for k in range(1, 7)]
    frame = _frame(12, temperature=np.full(12, 22.0)).rename(
        columns=dict(zip(JOINTS, names, strict=True))
    )
    cold = _csv(tmp_path, _set(frame, 4, "temperature", -400.0), "cold.csv")
    frame["joint_1"] = frame["joint_1"] > 0
    frame.to_parquet(tmp_path / "bool.parquet")
    for path, where in (
        (tmp_path / "bool.parquet", "column 'joint_1': boolean, expected numbers"),
        (cold, "row 4, column 'temperature': -400: below absolute zero"),
    ):
        assert main(["evaluate", "nominal:rx160", str(path), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert f"{path}, {where}" in err, err

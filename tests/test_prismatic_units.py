"""A prismatic joint's column in mm says so in one line, as a revolute one in degrees
does (tour 5: a lifting column's extension written in mm read 'value 49.6958 m outside
its limits [0, 0.9] m')."""

from __future__ import annotations

import re

import pandas as pd
import pytest

import hybrid_pk as hpk
from hybrid_pk.data import read_table_for, write_table
from hybrid_pk.errors import DataError
from hybrid_pk.simulate import simulate_campaign

COLUMN = "column_prismatic_joint"


@pytest.fixture(scope="module")
def robot():
    r = hpk.Robot.from_urdf("column_arm", end_link="tool0")
    r.requires_grad_(False)
    return r


def _table(robot, tmp_path):
    data, _ = simulate_campaign(
        robot, 20, "none", noise_mm=0.1, position_only=True, temperature_range=None, seed=2
    )
    return pd.read_csv(write_table(tmp_path / "m.csv", data))


def test_a_column_extension_in_mm_is_named(robot, tmp_path):
    frame = _table(robot, tmp_path)
    frame[COLUMN] *= 1000.0
    k = int(frame[COLUMN].abs().idxmax())
    frame.to_csv(tmp_path / "mm.csv", index=False)
    with pytest.raises(DataError, match=re.escape("looks like mm")) as exc:
        read_table_for(tmp_path / "mm.csv", robot)
    assert exc.value.column == COLUMN
    assert exc.value.row == k + 1
    assert "divide by 1000 (limits [0, 0.9] m)" in str(exc.value)


def test_one_bad_value_in_metres_is_a_limit_error_not_mm(robot, tmp_path):
    frame = _table(robot, tmp_path)
    frame.loc[4, COLUMN] = 5.0
    frame.to_csv(tmp_path / "typo.csv", index=False)
    with pytest.raises(DataError, match="outside its limits") as exc:
        read_table_for(tmp_path / "typo.csv", robot)
    assert exc.value.row == 5

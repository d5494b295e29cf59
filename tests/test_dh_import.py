"""``hybrid-pk import dh``: the URDF written from a DH table loads in pinocchio and
yourdfpy with the table's FK and mass distribution; bad tables get one line naming
file, row and column."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.errors import DataError
from hybrid_pk.robot import STANDARD_GRAVITY
from hybrid_pk.robot.dh_table import read_dh_table
from tests.dh_reader import chain_pose, rows_of

pytestmark = pytest.mark.usefixtures("one_thread")

PI = math.pi
# A 6-axis arm with a prismatic joint, a Hayati row (parallel axes 2, 3 slightly tilted)
# and a zero offset, in both conventions; lengths [m], angles [rad].
ROWS = [
    {"name": "j1", "a": 0.1, "alpha": -PI / 2, "d": 0.4, "theta": 0.0, "type": "revolute"},
    {"name": "j2", "a": 0.5, "alpha": 0.0, "d": 0.0, "theta": -PI / 2, "beta": 0.002},
    {"name": "j3", "a": 0.05, "alpha": PI / 2, "d": 0.0, "theta": 0.1, "type": "revolute"},
    {"name": "j4", "a": 0.0, "alpha": -PI / 2, "d": 0.3, "theta": 0.0, "type": "prismatic"},
    {"name": "j5", "a": 0.0, "alpha": PI / 2, "d": 0.0, "theta": 0.0, "type": "revolute"},
    {"name": "j6", "a": 0.0, "alpha": 0.0, "d": 0.1, "theta": 0.0, "type": "continuous"},
]
for r in ROWS:
    r.setdefault("type", "revolute")
    r.setdefault("beta", 0.0)
    r["lower"], r["upper"] = (-0.2, 0.2) if r["type"] == "prismatic" else (-2.5, 2.5)
    if r["type"] == "continuous":
        r["lower"] = r["upper"] = ""
# A payload table: mass [kg], centre of mass [m] and inertia [kg m^2] in frame i.
MASSES = [
    (20.0, (0.0, 0.05, -0.1), (0.5, 0.0, 0.0, 0.4, 0.0, 0.3)),
    (15.0, (-0.25, 0.0, 0.02), (0.2, 0.01, 0.0, 0.6, 0.0, 0.6)),
    (8.0, (0.0, -0.05, 0.0), (0.1, 0.0, 0.0, 0.1, 0.0, 0.05)),
    (5.0, (0.0, 0.0, -0.1), (0.05, 0.0, 0.0, 0.05, 0.0, 0.02)),
    (2.0, (0.0, 0.01, 0.0), (0.01, 0.0, 0.0, 0.01, 0.0, 0.01)),
    (0.5, (0.0, 0.0, 0.02), (0.001, 0.0, 0.0, 0.001, 0.0, 0.001)),
]


def _csv(tmp_path: Path, convention: str) -> Path:
    frame = pd.DataFrame(ROWS)
    for i, (m, c, inertia) in enumerate(MASSES):
        frame.loc[i, "mass"] = m
        frame.loc[i, ["com_x", "com_y", "com_z"]] = c
        frame.loc[i, ["ixx", "ixy", "ixz", "iyy", "iyz", "izz"]] = inertia
    path = tmp_path / f"arm_{convention}.csv"
    frame.to_csv(path, index=False)
    return path


def _q(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.uniform(-2.5, 2.5, (n, 6))
    q[:, 3] = rng.uniform(-0.2, 0.2, n)
    return q


def _pin_q(q: np.ndarray) -> np.ndarray:
    """pinocchio's configuration: the continuous joint 6 as (cos, sin)."""
    return np.concatenate([q[:5], [math.cos(q[5]), math.sin(q[5])]])


@pytest.mark.parametrize("convention", ["dh", "mdh"])
def test_written_urdf_in_pinocchio_and_yourdfpy(tmp_path, convention, pin, capsys):
    """The URDF of `import dh` gives the table's FK (its definition, tests/dh_reader.py)
    in hybrid_pk, pinocchio and yourdfpy to 1e-12 m, and pinocchio's centre of mass
    is the table's masses placed in the table's frames."""
    yourdfpy = pytest.importorskip("yourdfpy")
    out = tmp_path / "arm.urdf"
    argv = ["import", "dh", str(_csv(tmp_path, convention)), "--convention", convention]
    assert main([*argv, "--out", str(out)]) == 0
    assert "statics from the table" in capsys.readouterr().out
    rows = rows_of([r | {"lower": 0, "upper": 0} for r in ROWS])
    q = _q(50, 0)
    want = chain_pose(rows, convention, q)
    with torch.no_grad():
        ours = Robot.from_urdf(out).fk(torch.as_tensor(q)).numpy()
    assert np.abs(ours - want).max() < 1e-12
    model = pin.buildModelFromUrdf(str(out))
    data = model.createData()
    frame = model.getFrameId("flange")
    u = yourdfpy.URDF.load(str(out), load_meshes=False)
    names = [r["name"] for r in ROWS]
    for k in range(len(q)):
        qp = _pin_q(q[k])
        pin.framesForwardKinematics(model, data, qp)
        assert np.abs(data.oMf[frame].homogeneous - want[k]).max() < 1e-12
        com = pin.centerOfMass(model, data, qp)
        frames = [chain_pose(rows[: i + 1], convention, q[k : k + 1, : i + 1])[0] for i in range(6)]
        total = sum(m for m, _, _ in MASSES)
        placed = zip(frames, MASSES, strict=True)
        expect = sum(m * (F[:3, :3] @ c + F[:3, 3]) for F, (m, c, _) in placed)
        assert np.abs(com - expect / total).max() < 1e-12
        if k < 10:  # yourdfpy walks a scene graph per configuration: a few suffice
            u.update_cfg(dict(zip(names, q[k], strict=True)))
            assert np.abs(u.get_transform("flange", "base_link") - want[k]).max() < 1e-12


def test_from_dh_yaml_with_frames_and_statics(tmp_path, pin):
    """YAML with convention, base and flange; gravity torques of the table's masses
    equal pinocchio's on the written URDF (what the compliance effects read)."""
    import yaml

    doc = {
        "convention": "mdh",
        "name": "arm",
        "base": {"xyz": [0.1, -0.2, 0.3], "rpy": [0.0, 0.0, PI / 2]},
        "flange": {"xyz": [0.0, 0.0, 0.05], "rpy": [PI, 0.0, 0.0]},
        "joints": [
            r | {"mass": m, "com_x": c[0], "com_y": c[1], "com_z": c[2]}
            for r, (m, c, _) in zip(ROWS, MASSES, strict=True)
        ],
    }
    for row in doc["joints"]:
        if row["type"] == "continuous":
            del row["lower"], row["upper"]
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    robot = Robot.from_dh(path)  # the file states the convention
    assert robot.name == "arm"
    q = _q(20, 1)
    rows = rows_of(doc["joints"])
    table = read_dh_table(path)
    with torch.no_grad():
        ours = robot.fk(torch.as_tensor(q)).numpy()
        tau = robot.gravity_torques(torch.as_tensor(q)).numpy()
    assert np.abs(ours - chain_pose(rows, "mdh", q, table.base, table.flange)).max() < 1e-12
    model = pin.buildModelFromUrdf(robot.spec.urdf_path)
    model.gravity.linear = np.array([0.0, 0.0, -STANDARD_GRAVITY])  # pinocchio's is 9.81
    data = model.createData()
    for k in range(len(q)):
        qp = _pin_q(q[k])
        g = pin.computeGeneralizedGravity(model, data, qp)
        assert np.abs(g[:5] - tau[k, :5]).max() < 1e-9  # continuous j6: pinocchio's 2 coordinates
    with pytest.raises(DataError, match="states convention 'mdh', but 'dh' was given"):
        Robot.from_dh(path, "dh")


def _bad(tmp_path: Path, cell: tuple | None) -> Path:
    """The CSV of ROWS with ``cell = (row index, column, value)`` set; value None drops
    the column."""
    rows = [dict(r) for r in ROWS]
    if cell is not None:
        i, column, value = cell
        for k, r in enumerate(rows):
            if value is None:
                del r[column]
            elif k == i:
                r[column] = value
    path = tmp_path / "bad.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


@pytest.mark.parametrize(
    ("cell", "where", "says"),
    [
        ((0, "d", None), "column 'd'", "missing column"),
        ((2, "alpha", 90.0), "row 3, column 'alpha'", "degrees"),
        ((1, "lower", -170.0), "row 2, column 'lower'", "degrees"),
        ((3, "a", "0,3"), "row 4, column 'a'", "not a number"),
        ((0, "type", "rotary"), "row 1, column 'type'", "revolute"),
        ((4, "d", 625.0), "row 5, column 'd'", "mm"),
    ],
)
def test_bad_table_one_line(tmp_path, capsys, cell, where, says):
    """A bad cell: exit 2 and one line naming the file, row and column."""
    path = _bad(tmp_path, cell)
    argv = ["import", "dh", str(path), "--convention", "dh", "--out", str(tmp_path / "x.urdf")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(path) in err
    assert where in err
    assert says in err
    assert not (tmp_path / "x.urdf").exists()


def test_convention_must_be_given(tmp_path, capsys):
    """A CSV cannot state its convention: without --convention, one line says so."""
    path = _bad(tmp_path, None)
    assert main(["import", "dh", str(path), "--out", str(tmp_path / "x.urdf")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert str(path) in err
    assert "column 'convention'" in err
    assert "--convention dh|mdh" in err
    with pytest.raises(DataError, match="convention is not given"):
        Robot.from_dh(ROWS)


def test_a_dh_table_given_as_robot_says_how_to_make_a_urdf(tmp_path, capsys):
    """--robot TABLE.yaml (an exported DH table) where a URDF is expected: one line that
    names import dh and Robot.from_dh (before: 'cannot parse URDF: Invalid input object:
    NoneType' after yourdfpy's 'Using different parsing approach.'); Robot.from_dh still
    reads the table."""
    from hybrid_pk.effects import ExtendedModel
    from hybrid_pk.io.dh_export import model_dh_table, write_dh_yaml

    table = write_dh_yaml(
        model_dh_table(ExtendedModel(Robot.from_urdf("rx160")), "dh"), tmp_path / "t.yaml"
    )
    data = tmp_path / "d.csv"
    data.write_text("x,y,z\n0,0,1\n")
    assert (
        main(["diagnose", str(data), "--robot", str(table), "--json", str(tmp_path / "j.json")])
        != 0
    )
    err = capsys.readouterr().err
    assert "is a table, not a URDF" in err, err
    assert "import dh" in err
    assert Robot.from_dh(table).dof == 6


@pytest.mark.parametrize(
    ("text", "where"),
    [("- 1\n- 2\n", ", row 1: found 1 where a row"), ("", ": holds nothing, not a table")],
)
def test_a_yaml_that_holds_no_rows_says_what_it_should_hold(tmp_path, capsys, text, where):
    """A YAML list of numbers, or an empty YAML: one line saying what the file should
    hold (before: blamed on "column 'convention'", and 'cannot read a DH table from a
    NoneType'), with or without --convention."""
    path = tmp_path / "t.yaml"
    path.write_text(text)
    for flags in ([], ["--convention", "dh"]):
        assert main(["import", "dh", str(path), *flags, "--out", str(tmp_path / "x.urdf")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert f"error: {path}{where}" in err, err
        assert "a YAML DH table holds joints: (a list with one mapping of name, a," in err
        assert "convention" not in err.split(";")[0]


@pytest.mark.parametrize(("name", "where"), [("t.yaml", "line 2"), ("t.csv", "row 1")])
def test_a_table_that_is_not_utf8_names_its_line(tmp_path, capsys, name, where):
    # before: "'utf-8' codec can't decode byte 0xe9 ...", no file named (YAML)
    path = tmp_path / name
    body = b"joints:\n  - {a: 0\xe9}\n" if name.endswith(".yaml") else b"a,d\n0,\xe9\n"
    path.write_bytes(body)
    assert main(["import", "dh", str(path), "--out", str(tmp_path / "x.urdf")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"error: {path}" in err, err
    assert f"{where}: byte 0xe9" in err, err


def test_out_must_be_named_as_a_urdf(tmp_path, capsys):
    """--out h.csv: one line naming --out and the suffixes, nothing written (before: URDF
    XML written into a .csv, rc 0); .urdf and .xml are written."""
    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump({"convention": "dh", "joints": ROWS}))
    assert main(["import", "dh", str(path), "--out", str(tmp_path / "h.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"--out {tmp_path / 'h.csv'}: import dh writes a URDF (XML); name the file *.urdf" in err
    assert not (tmp_path / "h.csv").exists()
    for name in ("h.urdf", "h.XML"):
        assert main(["import", "dh", str(path), "--out", str(tmp_path / name)]) == 0
        assert Robot.from_urdf(tmp_path / name).dof == len(ROWS)

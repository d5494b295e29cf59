"""``hybrid-pk calibrate`` / ``evaluate`` end to end on a small simulated campaign.

The campaign is made here with ExtendedModel directly (not with ``simulate``): RX160,
joint_offset:joint_3 = 8e-4 rad, 0.01 mm / 1e-5 rad noise, a tracker at an unknown
place and a target off the flange.
"""

from __future__ import annotations

import contextlib
import io
import json
import types
from pathlib import Path

import pandas as pd
import pytest
import torch
from scipy.spatial.transform import Rotation

import hybrid_pk.pipelines.calibration as calibration_pipeline
from hybrid_pk import Robot
from hybrid_pk.cli.main import main
from hybrid_pk.data import MeasuredData, write_table
from hybrid_pk.effects import ExtendedModel, make_effect
from hybrid_pk.geometry import so3_exp, transform
from hybrid_pk.io.model_file import load_model

F64 = torch.float64
N_ROWS = 200
OFFSET = 8e-4  # [rad] joint_offset:joint_3
TOOL = transform(
    so3_exp(torch.tensor([0.1, 0.2, 0.3], dtype=F64)), torch.tensor([0.02, -0.01, 0.12], dtype=F64)
)


def _base(shift: float) -> torch.Tensor:
    """Tracker pose ``T_meas_root``; ``shift`` moves and turns it [m, rad]."""
    rotvec = torch.tensor([0.05, -0.1, 2.0 + shift], dtype=F64)
    return transform(so3_exp(rotvec), torch.tensor([2.5, 1.0 + shift, -0.4], dtype=F64))


def _campaign(path: Path, seed: int, base_shift: float) -> Path:
    robot = Robot.from_urdf("rx160")
    gen = torch.Generator().manual_seed(seed)
    q = robot.sample_q(N_ROWS, gen)
    truth = ExtendedModel(
        robot,
        [make_effect(robot, "joint_offset:joint_3", OFFSET)],
        base=_base(base_shift),
        tool=TOOL,
    )
    with torch.no_grad():
        T = truth(q)
    position = T[:, :3, 3] + 1e-5 * torch.randn(N_ROWS, 3, generator=gen, dtype=F64)
    R = T[:, :3, :3] @ so3_exp(1e-5 * torch.randn(N_ROWS, 3, generator=gen, dtype=F64))
    xyzw = torch.as_tensor(Rotation.from_matrix(R.numpy()).as_quat())
    data = MeasuredData(
        q=q,
        position=position,
        quat=xyzw[:, [3, 0, 1, 2]],
        joint_names=robot.joint_names,
        file_index=torch.zeros(N_ROWS, dtype=torch.long),
        rows=torch.arange(1, N_ROWS + 1),
        sources=(str(path),),
    )
    write_table(path, data)
    return path


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("campaign")
    return {
        "a": _campaign(d / "a.csv", seed=0, base_shift=0.0),
        "moved": _campaign(d / "moved.csv", seed=1, base_shift=0.3),  # tracker moved
        "dir": d,
    }


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _error_line(err: str) -> str:
    """The one error line (the progress bar, if any, is on other \\r-separated lines)."""
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0]


def _evaluate(capsys, tmp_path: Path, *argv) -> dict:
    out_json = tmp_path / "eval.json"
    rc, _, err = _run(capsys, "evaluate", *argv, "--json", out_json)
    assert rc == 0, err
    return json.loads(out_json.read_text())


@pytest.fixture(scope="module")
def calibrated(campaign, tmp_path_factory):
    """``calibrate a.csv --robot rx160 --effects joint_offset:joint_3``, run once (a module
    fixture cannot use capsys)."""
    model = tmp_path_factory.mktemp("model") / "m.pt"
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(
            [
                "calibrate",
                str(campaign["a"]),
                "--robot",
                "rx160",
                "--effects",
                "joint_offset:joint_3",
                "--out",
                str(model),
            ]
        )
    assert rc == 0, err.getvalue()
    return model, out.getvalue()


# ----------------------------------------------------------------------------- calibrate


def test_calibrate_recovers_the_joint_offset(calibrated):
    model, out = calibrated
    loaded = load_model(model, robot_check="rx160")
    value = float(loaded.model.effect("joint_offset:joint_3").value.detach())
    assert abs(value - OFFSET) < 0.05 * OFFSET, value
    assert loaded.frames_fitted
    assert loaded.metadata["effects"][0]["effect"] == "joint_offset:joint_3"
    assert "joint_offset:joint_3" in out
    assert "(nominal, frames fitted) ->" in out
    # the default corrected URDF next to the model, with the offset noted
    urdf = Path(f"{model}.urdf")
    assert "joint_offset:joint_3 = " in urdf.read_text()
    assert Robot.from_urdf(urdf).joint_names == loaded.model.robot.joint_names
    # ... and the summary says the URDF reads true joint values (its offsets are comments),
    # naming the two ways to fold them for a controller (before: 'wrote m.pt and m.pt.urdf')
    assert "offsets of joint_3 are comments" in out, out
    assert "--urdf-fold-offsets" in out


def test_evaluate_writes_exactly_the_contract_json(calibrated, campaign, capsys, tmp_path):
    model, _ = calibrated
    result = _evaluate(capsys, tmp_path, model, campaign["a"])
    assert set(result) == {"n", "position_mm", "orientation_deg"}
    assert result["n"] == N_ROWS
    for key in ("position_mm", "orientation_deg"):
        assert set(result[key]) == {"mean", "rms", "p95", "max"}
        assert all(isinstance(v, float) for v in result[key].values())
    assert result["position_mm"]["mean"] < 0.05


def test_evaluate_nominal_needs_fitted_frames_and_is_worse(calibrated, campaign, capsys, tmp_path):
    model, _ = calibrated
    good = _evaluate(capsys, tmp_path, model, campaign["a"])
    nominal = _evaluate(capsys, tmp_path, "nominal:rx160", campaign["a"], "--fit-frames")
    assert nominal["position_mm"]["mean"] > 0.2
    assert nominal["position_mm"]["mean"] > 5 * good["position_mm"]["mean"]

    rc, out, _ = _run(capsys, "evaluate", "nominal:rx160", campaign["a"])
    assert rc == 0
    assert "warning: base and tool frames are identity" in out


def test_evaluate_position_only_data_has_null_orientation(calibrated, campaign, capsys, tmp_path):
    model, _ = calibrated
    table = pd.read_csv(campaign["a"]).drop(columns=["qw", "qx", "qy", "qz"])
    points = tmp_path / "points.csv"
    table.to_csv(points, index=False)
    result = _evaluate(capsys, tmp_path, model, points)
    assert result["orientation_deg"] is None
    assert result["position_mm"]["mean"] < 0.05


def test_refit_base_after_the_tracker_moved(calibrated, campaign, capsys, tmp_path):
    model, _ = calibrated
    stale = _evaluate(capsys, tmp_path, model, campaign["moved"])
    assert stale["position_mm"]["mean"] > 10  # the old base frame is far off now

    refitted = tmp_path / "m2.pt"
    rc, out, err = _run(
        capsys,
        "calibrate",
        campaign["moved"],
        "--model",
        model,
        "--refit",
        "base",
        "--out",
        refitted,
    )
    assert rc == 0, err
    assert "re-fitted the base frame of" in out
    assert _evaluate(capsys, tmp_path, refitted, campaign["moved"])["position_mm"]["mean"] < 0.05
    both = tmp_path / "m3.pt"
    argv = ["calibrate", campaign["moved"], "--model", model, "--refit", "frames"]
    rc, out, err = _run(capsys, *argv, "--out", both)
    assert rc == 0, err
    assert "re-fitted the base and tool frames of" in out  # not "the frames frame(s)"

    before, after = load_model(model).model, load_model(refitted).model
    assert torch.equal(after.effects[0].value, before.effects[0].value)  # effects kept
    assert torch.equal(after.tool.matrix(), before.tool.matrix())  # tool kept
    assert not torch.allclose(after.base.matrix(), before.base.matrix())


def test_evaluate_fits_one_frame_set_per_file(calibrated, campaign, capsys, tmp_path):
    model, _ = calibrated
    files = (campaign["a"], campaign["moved"])
    result = _evaluate(capsys, tmp_path, model, *files, "--fit-frames", "--frames-per-file")
    assert result["n"] == 2 * N_ROWS
    assert result["position_mm"]["mean"] < 0.05


# ----------------------------------------------------------------------------- errors


def test_mismatched_robot_is_a_one_line_error(calibrated, campaign, capsys, tmp_path):
    model, _ = calibrated
    rc, _, err = _run(
        capsys, "calibrate", campaign["a"], "--model", model, "--refit", "tool",
        "--robot", "ur10", "--out", tmp_path / "x.pt",
    )  # fmt: skip
    assert rc == 2
    line = _error_line(err)
    assert line.startswith("hybrid-pk calibrate: error: model file")
    assert "made for robot 'rx160'" in line
    assert "not 'ur10'" in line
    assert not (tmp_path / "x.pt").exists()


def test_bad_data_file_names_file_row_and_column(campaign, capsys, tmp_path):
    lines = campaign["a"].read_text().splitlines()
    header = lines[0].split(",")
    row = lines[3].split(",")
    row[header.index("joint_2")] = "nan"
    lines[3] = ",".join(row)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    rc, _, err = _run(
        capsys,
        "calibrate",
        bad,
        "--robot",
        "rx160",
        "--effects",
        "none",
        "--out",
        tmp_path / "x.pt",
    )
    assert rc == 2
    line = _error_line(err)
    assert line.startswith(f"hybrid-pk calibrate: error: {bad}, row 3, column 'joint_2'"), line


def test_unknown_effect_is_refused_before_reading(capsys, tmp_path):
    rc, _, err = _run(
        capsys, "calibrate", tmp_path / "absent.csv", "--robot", "rx160",
        "--effects", "joint_offset:joint_9", "--out", tmp_path / "x.pt",
    )  # fmt: skip
    assert rc == 2
    assert "joint_offset needs a joint of rx160" in _error_line(err)


def test_evaluate_refuses_a_file_that_is_not_a_model(campaign, capsys):
    rc, _, err = _run(capsys, "evaluate", campaign["a"], campaign["a"])
    assert rc == 2
    assert "is not a hybrid_pk model file" in _error_line(err)


# ----------------------------------------------------------------------------- auto


def test_effects_auto_fits_the_diagnosed_causes(campaign, capsys, tmp_path, monkeypatch):
    """The wiring of --effects auto (the diagnosis itself is tested on its own)."""
    robot = Robot.from_urdf("rx160")
    seen = {}

    def fake_diagnose(robot_arg, data, *, holdout, seed, frames_per_file, progress, **priors):
        seen.update(holdout=holdout, seed=seed, n=data.n, upright=priors["gravity"].is_default)
        progress("scoring candidates")
        cause = types.SimpleNamespace(effect="joint_offset", joint="joint_3")
        model = ExtendedModel(robot_arg, [make_effect(robot_arg, "joint_offset:joint_3", 7e-4)])
        stats = {"position_mm": {"mean": 0.6}, "orientation_deg": None}
        return types.SimpleNamespace(
            causes=[cause],
            model=model,
            n_holdout=10,
            nominal=stats,
            extended={"position_mm": {"mean": 0.02}},
            ambiguous=[],
            setup_moves=[],
            to_json=lambda: {"robot": robot.name, "causes": [{"effect": "joint_offset"}]},
        )

    monkeypatch.setattr(calibration_pipeline, "diagnose", fake_diagnose)
    out_model = tmp_path / "auto.pt"
    rc, out, err = _run(
        capsys, "calibrate", campaign["a"], "--robot", "rx160", "--out", out_model,
        "--holdout", "0.3", "--seed", "7", "--no-urdf",
    )  # fmt: skip
    assert rc == 0, err
    assert seen == {"holdout": 0.3, "seed": 7, "n": N_ROWS, "upright": True}
    loaded = load_model(out_model)
    assert [e.label for e in loaded.model.effects] == ["joint_offset:joint_3"]
    assert abs(float(loaded.model.effects[0].value.detach()) - OFFSET) < 0.05 * OFFSET
    assert loaded.metadata["diagnosis"]["causes"] == [{"effect": "joint_offset"}]
    assert "1 cause(s)" in out
    assert not Path(f"{out_model}.urdf").exists()


def test_constant_orientation_registers_and_warns_of_unidentifiable_frames(tmp_path, capsys):
    """ISO 9283 cube poses keep the flange orientation: the hand-eye rotation is noise,
    so registration falls back to points, and calibrate names the tool translation as
    not determined (held at the flange origin by the prior) instead of walking off."""
    sim = tmp_path / "cube.csv"
    rc, _, err = _run(
        capsys, "simulate", "rx160", "--n", "200", "--trajectory", "iso-cube", "--noise-mm",
        "0.02", "--effects", "none", "--seed", "2", "--out", str(sim),
    )  # fmt: skip
    assert rc == 0, err
    model = tmp_path / "cube.pt"
    rc, out, err = _run(
        capsys, "calibrate", str(sim), "--robot", "rx160", "--effects", "none", "--out", str(model)
    )
    assert rc == 0, err
    assert "warning: tool translation (all three components): not determined" in out
    assert "warning: condition number" not in out  # the prior holds what the data cannot
    js = tmp_path / "eval.json"
    rc, _, err = _run(capsys, "evaluate", str(model), str(sim), "--json", str(js))
    assert rc == 0, err
    # the rows themselves are still fitted to the noise level (0.02 mm per axis)
    assert json.loads(js.read_text())["position_mm"]["mean"] < 0.06


def test_calibrate_takes_the_causes_of_a_diagnosis_file(campaign, tmp_path, capsys):
    diag = tmp_path / "diag.json"
    diag.write_text(json.dumps({"causes": [{"effect": "joint_offset", "joint": "joint_2"}]}))
    model = tmp_path / "from_diag.pt"
    rc, _, err = _run(
        capsys, "calibrate", str(campaign["a"]), "--robot", "rx160", "--effects", str(diag),
        "--out", str(model),
    )  # fmt: skip
    assert rc == 0, err
    assert [e.label for e in load_model(model).model.effects] == ["joint_offset:joint_2"]
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    rc, _, err = _run(
        capsys, "calibrate", str(campaign["a"]), "--robot", "rx160", "--effects", str(bad),
        "--out", str(model),
    )  # fmt: skip
    assert rc == 2
    assert "no 'causes' list" in err
    assert len(err.strip().splitlines()) == 1


def test_gross_refit_warning_names_what_was_refitted():
    # with --refit frames the warning read "more changed than the frames frame"
    from hybrid_pk.cli.calibrate_refit import _gross_warning

    both = _gross_warning("frames", torch.tensor([40.0, 42.0]))
    assert "more changed than the base and tool frames, or" in both
    assert "frames frame" not in both
    tool = _gross_warning("tool", torch.tensor([40.0]))
    assert "more changed than the tool frame (--refit frames re-fits both frames)" in tool
    assert _gross_warning("base", torch.tensor([1.0])) is None

"""Leave one file out (hybrid_pk.pipelines.transfer, ``--refit-rows``): a model fitted
on other set-ups, frames re-fitted on a few rows of the left-out one."""

from __future__ import annotations

import dataclasses
import json

import pytest

from hybrid_pk.cli.main import main
from hybrid_pk.data import MeasuredData, write_table
from hybrid_pk.io.model_file import load_model
from hybrid_pk.pipelines.transfer import leave_one_file_out
from hybrid_pk.simulate import simulate_campaign
from tests.helpers import RUN_SEED, run_rng

pytestmark = pytest.mark.usefixtures("one_thread")
NOISE_MM = 0.02  # a laser tracker's noise per coordinate


def _setups(robot, effect: str, sizes: tuple[int, ...], seed: int) -> MeasuredData:
    """Campaigns of the same robot, each a set-up of its own (own tracker and tool)."""
    parts = []
    for k, n in enumerate(sizes):
        data, _ = simulate_campaign(
            robot, n, effect, noise_mm=NOISE_MM, temperature_range=None, seed=seed + k
        )
        parts.append(dataclasses.replace(data, sources=(f"setup_{k}.csv",)))
    return MeasuredData.concat(parts)


def _hidden(robot, salt: str) -> tuple[str, str]:
    """A random offset or gear-ratio error of a random joint, 1-3 mrad (1-5 mm at reach)."""
    rng = run_rng(salt)
    kind = str(rng.choice(["joint_offset", "gear_ratio"]))
    joint = str(rng.choice(robot.joint_names[1:5]))
    value = float(rng.uniform(1e-3, 3e-3) * rng.choice([-1, 1]))
    return f"{kind}:{joint}", f"{kind}:{joint}={value:.6g}"


def test_the_right_cause_carries_over_to_each_left_out_setup(rx160):
    label, spec = _hidden(rx160, "transfer-library")
    data = _setups(rx160, spec, (300, 300, 40), seed=RUN_SEED % 1000)
    res = leave_one_file_out(rx160, data, [label], refit_rows=50, seed=1)
    assert [f.file for f in res.files] == list(data.sources)
    small = res.files[2]
    assert small.skipped is not None
    assert "40 rows" in small.skipped, small
    for f in res.files[:2]:
        assert f.skipped is None, f
        assert (f.judged_rows, f.fit_rows) == (250, 340), f
        # Frames re-fitted on 50 rows: the extended model is left with about the noise
        # (3D mean of 0.02 mm per coordinate: 0.03 mm) plus the re-fit's share of it,
        # nominal + frames with the millimetres of the hidden error.
        assert f.extended_mm["mean"] < 0.1, (spec, RUN_SEED, f)
        assert f.ratio < 0.3, (spec, RUN_SEED, f)
    doc = res.to_json()
    assert doc["files"][0]["extended_over_nominal"] == pytest.approx(res.files[0].ratio)


def test_refit_rows_must_be_positive(rx160):
    data = _setups(rx160, "none", (30, 30), seed=0)
    with pytest.raises(ValueError, match="refit_rows"):
        leave_one_file_out(rx160, data, [], refit_rows=0)


def test_diagnose_and_calibrate_report_the_check(rx160, tmp_path, capsys):
    label, spec = _hidden(rx160, "transfer-cli")
    data = _setups(rx160, spec, (200, 200), seed=RUN_SEED % 1000 + 7)
    files = []
    for k in range(2):
        rows = data.subset(data.file_index == k)
        files.append(write_table(tmp_path / f"setup_{k}.csv", rows))
    diag = tmp_path / "diag.json"
    common = ["--robot", "rx160", "--frames-per-file", "--refit-rows", "30"]
    report = ["--report", str(tmp_path / "report")]
    assert main(["diagnose", *map(str, files), *common, "--json", str(diag), *report]) == 0
    assert "## Transfer: leave one file out" in (tmp_path / "report" / "report.md").read_text()
    out = capsys.readouterr().out
    assert "transfer (leave one file out" in out
    assert "setup_1.csv" in out
    doc = json.loads(diag.read_text())["transfer"]
    assert doc["refit_rows"] == 30
    assert [f["judged_rows"] for f in doc["files"]] == [170, 170]
    model = tmp_path / "m.pt"
    argv = ["calibrate", *map(str, files), *common, "--effects", str(diag), "--out", str(model)]
    assert main([*argv, "--no-urdf"]) == 0
    assert "transfer (leave one file out" in capsys.readouterr().out
    stored = load_model(model).metadata["transfer"]
    assert stored["effects"] == [label]
    assert len(stored["files"]) == 2
    one = tmp_path / "one.json"
    assert main(["diagnose", str(files[0]), "--robot", "rx160", "--json", str(one)]) == 0
    assert json.loads(one.read_text())["transfer"] is None


def test_the_printed_table_keeps_whole_file_names():
    """File names longer than the old 40-column cut (which dropped their first letters:
    'easurements_joint_configurations.parquet') print whole, the columns aligned."""
    from hybrid_pk.pipelines.transfer import FileTransfer, TransferResult

    stats = {"mean": 0.39, "rms": 0.4, "p95": 0.7, "max": 2.2}
    names = ["/data/measurements_joint_configurations_second_setup.parquet", "/data/a.csv"]
    files = tuple(FileTransfer(n, 100, 50, 1445, stats, stats) for n in names)
    lines = TransferResult(50, ("joint_offset:joint_2",), files, 0).lines()
    rows = lines[2:]
    assert rows[0].startswith("  measurements_joint_configurations_second_setup.parquet ")
    assert rows[1].startswith("  a.csv ")
    assert len({len(r) for r in rows}) == 1  # aligned
    assert lines[1].index("judged") + len("judged") == rows[0].index("1445") + 4

"""The reproduction script runs end to end on its smoke-test sizes, and its parts merge."""

from __future__ import annotations

import json

import pytest

from experiments import reproduce_paper

pytestmark = pytest.mark.slow


def test_reproduce_paper_quick_parts_merge(tmp_path):
    a, bc, merged = tmp_path / "a", tmp_path / "bc", tmp_path / "merged"
    assert reproduce_paper.main(["--quick", "--out", str(a), "--skip", "table", "fig5"]) == 0
    effects = ",".join(
        json.loads((a / "results.json").read_text())["acceptance"]["calibrated"]["effects"]
    )
    assert effects  # the diagnosis named the springs (or their stand-ins)
    argv = ["--quick", "--out", str(bc), "--skip", "acceptance", "--nominal-mlp"]
    assert reproduce_paper.main([*argv, "--effects", effects]) == 0
    assert reproduce_paper.main(["--merge", str(a), str(bc), "--out", str(merged)]) == 0

    results = json.loads((merged / "results.json").read_text())
    acc = results["acceptance"]
    # physics first: the calibrated model beats nominal + frames by an order of magnitude
    assert (
        acc["calibrated"]["position_mm"]["mean"]
        < 0.2 * acc["nominal_frames"]["position_mm"]["mean"]
    )
    assert set(results["table_one"]) == set(reproduce_paper.TABLE_ARCHS)
    assert list(results["figure_five"]) == [str(n) for n in reproduce_paper.QUICK.fig5_sizes]
    assert "nominal_mlp" in results
    text = (merged / "reproduce_paper.md").read_text()
    for heading in ("## A. Acceptance", "## B. Table I", "## C. Fig. 5"):
        assert heading in text
    assert "| nominal + frames + our MLPs, our training |" in text
    assert (merged / "figure5.png").stat().st_size > 10_000


def test_real_ur10_runs_every_split_on_thin_data_and_keeps_its_models(tmp_path):
    """experiments/real_ur10.py on every 30th row, one epoch, named effects (no
    diagnosis): the four models of each split, the tables, the subset check; a second
    run with --evaluate-only reuses the model files."""
    from experiments import real_ur10

    out = tmp_path / "ur10"
    argv = ["--out", str(out), "--thin", "30", "--epochs", "1", "--splits", "pan,random"]
    argv += ["--effects", "joint_compliance:shoulder_lift_joint"]
    assert real_ur10.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    for split in ("pan", "random"):
        res = results["splits"][split]
        assert set(res["evaluate"]) == {k for k, _ in real_ur10.MODELS}
        for key in ("hybrid_joints", "hybrid"):
            assert res[f"{key}_vs_extended"]["worst_subset_ratio"] > 0
    # pan: every held-out row is outside the joint box, so the paper's networks are off
    pan = results["splits"]["pan"]
    assert pan["hybrid_joints_stage_weights"] == {"joints": 0.0}
    assert "## Split `pan`" in (out / "results.md").read_text()
    stamp = (out / "pan" / "hybrid.pt").stat().st_mtime_ns
    assert real_ur10.main([*argv, "--evaluate-only"]) == 0
    assert (out / "pan" / "hybrid.pt").stat().st_mtime_ns == stamp


def test_real_ur10_diagnoses_each_split_on_its_own_fit_rows_only(tmp_path):
    """The default --diagnose-on each: the pan split's causes are chosen on its fit rows
    alone (none of its held-out rows, where joint 1 was never turned), so its extended
    model carries nothing learned there; --diagnose-on region diagnoses once for all."""
    from experiments import real_ur10

    out = tmp_path / "ur10"
    argv = ["--out", str(out), "--thin", "15", "--epochs", "1", "--splits", "pan"]
    assert real_ur10.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    pan = results["splits"]["pan"]
    fit_rows = sum(
        len(real_ur10.read_rows([f], real_ur10.Robot.from_urdf("ur10")).q)
        for f in real_ur10.split_files(out / "pan")[0]
    )
    assert pan["diagnosis"]["n_samples"] == fit_rows  # the fit rows, no held-out row
    assert (out / "pan" / "diagnosis.json").exists()
    assert "diagnosis" not in results
    assert "## Diagnosis (fit rows of the pan split)" in (out / "results.md").read_text()
    with pytest.raises(SystemExit, match="region"):
        real_ur10.main([*argv, "--diagnose-on", "region"])  # needs the region split


def test_transfer_ur10_carries_each_series_to_the_other(tmp_path):
    """experiments/transfer_ur10.py on 400 rows of each fit series, one epoch, named
    effects (no diagnosis): both directions and the pan region (joint 1 turned where no
    fit row was), frames re-fitted on 50 rows of the other series or region, judged on
    the rest of it."""
    from experiments import transfer_ur10

    out = tmp_path / "transfer"
    argv = ["--out", str(out), "--rows", "400", "--epochs", "1", "--directions", "A->B,B->A,pan"]
    argv += ["--effects", "link_length:elbow_joint,link_length:wrist_1_joint"]
    assert transfer_ur10.main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    below = results["directions"]["pan"]["pan_below_rad"]
    ur10 = transfer_ur10.Robot.from_urdf("ur10")
    series = transfer_ur10.read_rows([out / "series" / "measurements_grid.parquet"], ur10)
    new_region = int((series.q[:, 0] < below).sum())  # Series A below the pan angle
    assert 0.2 * series.n < new_region < 0.3 * series.n  # --pan-share 0.25 of Series A
    judged = {"A->B": results["rows_of"]["B"] - 50, "B->A": results["rows_of"]["A"] - 50}
    judged["pan"] = new_region - 50
    for name, res in results["directions"].items():
        assert res["judged_rows"] == judged[name]
        assert res["fit_rows"] == (800 if name == "pan" else 400)  # pan: 400 of each
        assert set(res["models"]) == {k for k, _ in transfer_ur10.MODELS}
        # the link lengths carry over: they beat nominal + frames on the other series
        assert res["models"]["extended"]["mean"] < res["models"]["nominal_frames"]["mean"]
        # the re-fit judged the networks on its 50 rows; fallen back, the hybrid is the
        # extended model
        assert res["networks"]["rows"] == 50
        if not res["networks"]["used"]:
            hybrid, extended = res["models"]["hybrid"], res["models"]["extended"]
            assert hybrid["mean"] == pytest.approx(extended["mean"], rel=1e-6)
    assert "## B->A" in (out / "results.md").read_text()
    assert "The re-fit's verdict: residual networks" in (out / "results.md").read_text()

    from experiments import network_rule_picks

    assert network_rule_picks.main(["--out", str(out), "--picks", "2"]) == 0
    picks = json.loads((out / "rule_picks.json").read_text())
    for rows in picks.values():
        assert [r["seed"] for r in rows] == [0, 1]
        for r in rows:  # fallen back: the judged hybrid is the extended model
            if not r["used"]:
                assert r["judged_hybrid_mm"] == pytest.approx(r["judged_extended_mm"], rel=1e-6)


def test_limit_precise_tracker_diagnoses_each_seed_at_both_limits(capsys):
    """experiments/limit_precise_tracker.py on 150 rows a half: one table row per limit,
    each with its causes, the other half's error and the margin."""
    pytest.importorskip("cmeel", reason="example-robot-data (dev extras) not installed")
    from experiments import limit_precise_tracker

    assert limit_precise_tracker.main(["--seeds", "3", "--rows", "150", "--repeats", "20"]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| 3 |")]
    assert [r.split("|")[2].strip() for r in rows] == ["8", "24"]
    for r in rows:
        cells = [c.strip() for c in r.split("|")[1:-1]]
        assert 0 <= int(cells[2]) <= int(cells[1]), r  # causes named, within the limit
        assert float(cells[4]) > 0, r  # the other half's mean error [mm]
        assert float(cells[5]) > 0, r  # the practical margin [mm]

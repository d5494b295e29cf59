"""Robust fits (issue 15): rows with gross errors are down-weighted, listed by file and
row, and do not change what the diagnosis names."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import pytest
import torch

from hybrid_pk.calibration.diagnosis import diagnose
from hybrid_pk.calibration.fit import fit, model_errors
from hybrid_pk.calibration.known_frames import initialise_with_priors
from hybrid_pk.calibration.robust import (
    list_outliers,
    outlier_threshold,
    robust_cost,
    robust_weights,
)
from hybrid_pk.cli.main import main
from hybrid_pk.data import MeasuredData, read_table_for, write_table
from hybrid_pk.data.ipa import convert_ipa
from hybrid_pk.effects import ExtendedModel, conditions_from_data
from hybrid_pk.simulate import displace_rows, simulate_campaign
from tests.helpers import RUN_SEED, is_periodic, run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

F64 = torch.float64


def test_weights_costs_and_thresholds():
    d2 = torch.tensor([0.0, 1.0, 9.0, 100.0, 1e4], dtype=F64)
    for loss in ("huber", "cauchy"):
        w = robust_weights(d2, 3, loss)
        assert float(w[0]) == 1.0
        assert bool((w[1:] <= w[:-1]).all())  # falls with distance
        assert float(w[-1]) < 0.05
        # a clean row costs its square, a wild one far less
        assert robust_cost(d2[:2], 3, loss) == pytest.approx(1.0, rel=0.2)
        assert robust_cost(d2[-1:], 3, loss) < 0.1 * 1e4
    # k = 4: the tail probability of a 4-sigma normal deviation, 6.3e-5
    from scipy import stats

    for dim in (3, 6):
        assert stats.chi2.sf(outlier_threshold(dim), dim) == pytest.approx(6.334e-5, rel=1e-3)


def _rows(file_index: torch.Tensor, rows: torch.Tensor, sources: tuple[str, ...]) -> MeasuredData:
    """Rows of a 6-joint robot, all zero, from ``sources`` (only the bookkeeping matters)."""
    n = len(rows)
    return MeasuredData(
        q=torch.zeros(n, 6, dtype=F64),
        position=torch.zeros(n, 3, dtype=F64),
        quat=None,
        joint_names=tuple(f"j{i}" for i in range(6)),
        file_index=file_index,
        rows=rows,
        sources=sources,
    )


def test_outliers_are_listed_by_file_and_one_based_row():
    n = 50
    data = _rows(
        torch.tensor([0] * 25 + [1] * 25),
        torch.cat([torch.arange(1, 26), torch.arange(1, 26)]),
        ("a.csv", "b.csv"),
    )
    err = torch.full((n,), 0.05, dtype=F64)
    err[30], err[3] = 3.0, 0.5  # [mm] file b row 6, file a row 4
    listed = list_outliers(data, err, None, sigma_pos_mm=0.05, sigma_rot_rad=None)
    assert [(o["file"], o["row"]) for o in listed] == [("b.csv", 6), ("a.csv", 4)]
    assert listed[0]["position_mm"] == 3.0
    assert listed[0]["orientation_deg"] is None


def test_round_off_is_no_outlier():
    """Rows simulated without noise fit to float64 round-off (~1e-13 mm): a row at 7
    times the others' round-off was listed as an outlier (a noise-free 5-row UR10
    diagnosis printed "1 outlier row(s) beyond 4 sigma: n3.csv:5 (7.32e-13)"). Below
    ``NOISE_FLOOR_MM`` nothing is noise, so nothing is an outlier; a real one still is."""
    n = 8
    data = _rows(torch.zeros(n, dtype=torch.long), torch.arange(1, n + 1), ("n.csv",))
    err = torch.full((n,), 1e-13, dtype=F64)
    err[4] = 7.3e-13
    ori = torch.full((n,), 5e-15, dtype=F64)
    ori[4] = 3.7e-14
    assert list_outliers(data, err, ori, sigma_pos_mm=1e-6, sigma_rot_rad=1e-9) == []
    err[4] = 1e-4  # 100 nm among rows fitted to round-off: far beyond a nanometre's noise
    assert [o["row"] for o in list_outliers(data, err, None, 1e-6, None)] == [5]


def test_a_robust_frame_fit_ignores_wild_rows(rx160):
    data, _ = simulate_campaign(rx160, 120, "none", noise_mm=0.05, noise_deg=0.005, seed=3)
    dirty, bad = displace_rows(data, 0.03, torch.Generator().manual_seed(4), 5.0, 10.0)
    frames = ["base_frame.translation", "base_frame.rotation", "tool_frame.translation",
              "tool_frame.rotation"]  # fmt: skip
    results = {}
    for name, rows, robust in (
        ("clean", data, None),
        ("ls", dirty, None),
        ("cauchy", dirty, "cauchy"),
    ):
        model = ExtendedModel(rx160)
        cond = conditions_from_data(rows)
        initialise_with_priors(model, rows, cond, None)
        res = fit(model, rows, free=frames, cond=cond, robust=robust)
        results[name] = (model_errors(model, data)[0], res)
    clean, ls, rob = (results[k][0] for k in ("clean", "ls", "cauchy"))
    assert float(rob.mean()) < float(clean.mean()) + 0.01  # [mm] as if the rows were clean
    assert float(ls.mean()) > float(rob.mean()) + 0.05  # least squares is pulled away
    res = results["cauchy"][1]
    assert float(res.weights[bad].max()) < 0.01
    assert float(res.sigma_pos_mm) == pytest.approx(0.05, rel=0.25)  # median, not the wild rows


@pytest.mark.slow
def test_gross_errors_change_neither_the_causes_nor_their_values(rx160):
    """Acceptance of issue 15: virtual RX160 with two hidden effects, 2 % of the rows
    displaced by 2-10 mm: the robust diagnosis names the clean data's causes with values
    within 2 sigma, lists >= 95 % of the bad rows and falsely lists < 1 % of the rows."""
    rng = run_rng("robust-acceptance")
    seed = int(rng.integers(1_000_000))
    data, truth = simulate_campaign(rx160, 300, "random:2", noise_mm=0.05, noise_deg=0.005,
                                    seed=seed, payload=20.0)  # fmt: skip
    dirty, bad = displace_rows(data, 0.02, torch.Generator().manual_seed(seed + 1))
    clean = diagnose(rx160, data)
    robust = diagnose(rx160, dirty, robust="cauchy")
    why = f"HYBRID_PK_TEST_SEED={RUN_SEED}, campaign seed {seed}, truth {truth['effects']}"
    # The same causes, in whatever order each diagnosis found them; values by cause.
    by_label = {f"{c.effect}:{c.joint}": c for c in robust.causes}
    labels = [f"{c.effect}:{c.joint}" for c in clean.causes]
    assert len(by_label) == len(robust.causes), why  # no cause named twice
    # ... but for a cause one of them names in place of another whose signature is the
    # same in these rows (100 % alike), that it reports as ambiguous with it: the rows
    # cannot choose, and the down-weighted rows' noise weights may tip the choice (seed
    # 373737: a joint-3 offset or a joint-4 misalignment, the misalignment's second
    # direction gaining 0.0016-0.0041 mm against a 0.005 mm margin).
    alike = {
        frozenset(a["effects"])
        for d in (clean, robust)
        for a in d.ambiguous
        if len(a["effects"]) == 2 and "100.0 %" in a.get("why", "")
    }
    only_clean, only_robust = set(labels) - set(by_label), set(by_label) - set(labels)
    for mine, theirs in ((only_clean, only_robust), (only_robust, only_clean)):
        for label in mine:
            assert any(frozenset((label, o)) in alike for o in theirs), (label, alike, why)
    for a in clean.causes:
        if f"{a.effect}:{a.joint}" in only_clean:
            continue
        b = by_label[f"{a.effect}:{a.joint}"]
        va, vb, sa = (torch.tensor(x, dtype=F64).reshape(-1) for x in (a.value, b.value, a.std))
        assert bool(((va - vb).abs() <= 2 * sa).all()), (a, b, why)
    listed = {o["row"] for o in robust.outliers}
    truly = {int(data.rows[i]) for i in bad}
    assert len(listed & truly) >= math.ceil(0.95 * len(truly)), (listed, truly, why)
    assert len(listed - truly) < 0.01 * data.n, (listed - truly, why)
    cut = {r["row"] for r in robust.robust["down_weighted"] if r["weight"] < 0.1}
    assert cut <= truly, (cut - truly, why)


def test_cli_diagnose_lists_outliers_and_what_was_down_weighted(rx160, tmp_path, capsys):
    data, _ = simulate_campaign(rx160, 150, "joint_offset:joint_3=1e-3", noise_mm=0.05,
                                noise_deg=0.005, seed=8)  # fmt: skip
    dirty, bad = displace_rows(data, 0.02, torch.Generator().manual_seed(9), 4.0, 8.0)
    table = tmp_path / "campaign.csv"
    write_table(table, dirty)
    out_json = tmp_path / "diag.json"
    candidates = "joint_offset:joint_3,joint_offset:joint_2"
    report = tmp_path / "report"
    argv = ["diagnose", str(table), "--robot", "rx160", "--json", str(out_json)]
    rc = main([*argv, "--robust", "cauchy", "--candidates", candidates, "--report", str(report)])
    out = capsys.readouterr().out
    assert rc == 0
    doc = json.loads(out_json.read_text())
    rows = sorted(int(data.rows[i]) for i in bad)
    assert sorted(o["row"] for o in doc["outliers"]) == rows
    assert set(doc["outliers"][0]) >= {"file", "row", "position_mm", "orientation_deg"}
    assert doc["outliers"][0]["file"].endswith("campaign.csv")
    assert doc["robust"]["loss"] == "cauchy"
    cut = {r["row"] for r in doc["robust"]["down_weighted"] if r["weight"] < 0.1}
    assert cut
    assert cut <= set(rows)  # only the bad rows lose their pull, each one reported
    assert "down-weighted" in out
    assert "outlier row(s) beyond 4 sigma" in out
    assert [c["effect"] + ":" + c["joint"] for c in doc["causes"]] == ["joint_offset:joint_3"]
    text = (report / "report.md").read_text()
    assert "## Outliers and down-weighted rows" in text
    assert f"| campaign.csv | {rows[0]} |" in text


IPA_B = (
    Path(__file__).resolve().parents[1].parent
    / "shared/data/ipa-ur10/Series_B/measurements_joint_configurations.csv"
)


@pytest.mark.slow
@pytest.mark.skipif(not IPA_B.is_file(), reason=f"shared data not found at {IPA_B}")
def test_series_b_bad_visits_are_listed_and_down_weighted(ur10, tmp_path):
    """The shared Series B measures some configurations twice; four pairs of visits
    disagree by 0.4-2.3 mm. The robust diagnosis lists the worse visit of the three
    pairs beyond 1.5 mm as its largest outliers and down-weights them (the 0.44 mm pair
    is within the noise of the rows' remaining error); the causes are those of least
    squares (:func:`_same_findings`)."""
    table = tmp_path / "B.parquet"
    convert_ipa(IPA_B, table)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = read_table_for(table, ur10)
    D = torch.cdist(data.q, data.q)
    D.fill_diagonal_(math.inf)
    i, j = torch.nonzero(D < 2e-3, as_tuple=True)
    apart = 1e3 * (data.position[i] - data.position[j]).norm(dim=1)
    far = apart > 1.5  # [mm]
    pairs = {
        tuple(sorted((int(data.rows[a]), int(data.rows[b]))))
        for a, b in zip(i[far], j[far], strict=True)
    }
    assert len(pairs) == 3
    robust = diagnose(ur10, data, robust="cauchy")
    top = [o["row"] for o in robust.outliers[:3]]
    assert all(len(set(p) & set(top)) == 1 for p in pairs), (pairs, top)
    weights = {r["row"]: r["weight"] for r in robust.robust["down_weighted"]}
    assert all(weights.get(r, 1.0) < 0.25 for r in top)
    plain = diagnose(ur10, data)
    _same_findings(robust, plain, 0.01)


def _label(c) -> str:
    return f"{c.effect}:{c.joint}" if c.joint else c.effect


def _same_findings(a, b, floor_mm: float) -> None:
    """Every cause that gains at least ``floor_mm`` on the hold-out rows in one
    diagnosis is named by the other, or the other names a cause that either diagnosis
    lists as ambiguous with it, or, for a periodic error of a joint (eccentricity,
    ``cyclic_error_<n>``), a periodic error of the same joint. Series B's 1,495 rows
    carry several weak periodic errors per joint (0.01-0.03 mm each); which orders the
    two weightings pick among them differs (robust 8, least squares 4 cycles per turn
    of the shoulder lift; 6 and 21 of the shoulder pan): the finding both make is the
    joint whose transmission errs periodically. Causes below the floor (Series B's
    noise, 0.010 mm per axis) are marginal on real data with unmodelled structure: the
    two fits may rank them differently."""
    pairs = {frozenset(x["effects"]) for d in (a, b) for x in d.ambiguous}
    for one, other in ((a, b), (b, a)):
        named = {_label(c) for c in other.causes}
        periodic = {c.joint for c in other.causes if is_periodic(c.effect)}
        for c in one.causes:
            if c.position_gain_mm < floor_mm or _label(c) in named:
                continue
            if is_periodic(c.effect) and c.joint in periodic:
                continue
            stand_ins = [n for n in named if frozenset((_label(c), n)) in pairs]
            assert stand_ins, (_label(c), c.position_gain_mm, sorted(named), pairs)

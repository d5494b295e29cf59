"""What the streams show of the time offset (:mod:`hybrid_pk.data.offset_evidence`): the
likelihood interval covers the truth when the model is exact, and an offset the streams
cannot show is said, not returned silently."""

from __future__ import annotations

import math
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hybrid_pk.cli.main import main
from hybrid_pk.data.streams import OffsetEstimate, estimate_time_offset
from hybrid_pk.effects import ExtendedModel, make_effect
from tests.test_streams import simulate_streams, write_streams


class _Exact:
    """The simulated robot itself (the joint offset ``simulate_streams`` hides): no model
    error, only the tracker's noise."""

    def __init__(self, robot) -> None:
        self.dtype = robot.dtype
        self.model = ExtendedModel(
            robot, [make_effect(robot, "joint_offset:shoulder_lift_joint", 3e-4)]
        )

    def fk(self, q: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.model(q)


def _random_offset(seed: int) -> float:
    return float(np.random.default_rng(seed).uniform(-0.3, 0.3))


@pytest.mark.parametrize(
    ("duration", "seed"), [(12.0, 0), (12.0, 1), *[(3.0, s) for s in range(6)]]
)
def test_interval_covers_the_true_offset_when_the_model_is_exact(ur10, duration, seed):
    """With nothing but noise, the offsets the data allow (a likelihood ratio under 100,
    ~3 standard errors) hold the truth; 12 s of turning path pins it to < 0.4 ms."""
    offset = _random_offset(seed)
    t_r, q, t_m, pos, quat, _ = simulate_streams(ur10, offset, duration=duration, seed=seed)
    est = estimate_time_offset(t_r, q, t_m, pos, _Exact(ur10), quat=quat if seed % 2 else None)
    lo, hi = est.interval
    assert lo <= offset <= hi, (est.summary(), offset)
    assert lo <= est.offset <= hi, est.summary()
    if duration == 12.0:
        assert hi - lo < 4e-4, est.summary()
        assert est.determined, est.summary()
        assert est.ambiguity_warning("s") == "", est.summary()


def test_short_streams_never_return_a_wrong_offset_silently(ur10):
    """0.3-1 s of slow path: a rigid change of frames carries the piece onto itself
    shifted in time, and the nominal model's 0.3 mrad error places the minimum (before,
    offsets 5-680 ms off with no word). Every estimate off by more than one robot sample
    now comes with the warning; the streams are ones where several are that far off."""
    wrong = 0
    for duration in (0.3, 0.5, 1.0):
        for seed in range(4):
            offset = _random_offset(seed)
            t_r, q, t_m, pos, _, _ = simulate_streams(ur10, offset, duration=duration, seed=seed)
            reach = max(abs(t_m[0] - t_r[-1]), abs(t_m[-1] - t_r[0]))
            est = estimate_time_offset(t_r, q, t_m, pos, ur10, max_offset=min(1.0, 0.7 * reach))
            line = est.ambiguity_warning("robot.csv, tracker.csv")
            if abs(est.offset - offset) > est.sample_s:
                wrong += 1
                assert line.startswith("robot.csv, tracker.csv: the time offset is not determined")
                assert "\n" not in line, line
                assert "nan" not in line, line
            assert bool(line) == (not est.determined)
    assert wrong >= 3  # the check above is not vacuous


def test_cli_says_when_the_streams_cannot_show_the_offset(ur10, tmp_path, capsys):
    t_r, q, t_m, pos, _, _ = simulate_streams(ur10, 0.12, duration=0.5, seed=0)
    robot_csv, tracker_csv = write_streams(tmp_path, ur10.joint_names, t_r, q, t_m, pos)
    argv = ["import", "streams", str(robot_csv), str(tracker_csv), "--robot", "ur10"]
    argv += ["--max-offset", "0.7", "--out", str(tmp_path / "table.csv"), "--no-progress"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    lines = [x for x in out.splitlines() if "not determined" in x]
    assert len(lines) == 1, out
    assert lines[0].startswith(f"warning: {robot_csv}, {tracker_csv}: the time offset"), out
    assert "--offset" in lines[0]
    assert "the noise allows" in out  # the summary line's interval
    assert (tmp_path / "table.csv").exists()  # the table is written; the user decides


def test_interval_words_show_its_width_and_open_ends():
    def est(lo, hi):
        return OffsetEstimate(0.12, 0.1, 1.0, 0.03, 1.0, (0.1, 0.14), 880, 1.0,
                              interval=(lo, hi), sample_s=1 / 110)  # fmt: skip

    narrow = est(0.119973, 0.120013)
    assert narrow.interval_text() == "offsets from 119.973 to 120.013 ms"
    assert narrow.determined
    assert narrow.ambiguity_warning("s") == ""
    assert est(-math.inf, math.inf).interval_text() == "all the offsets searched"
    assert est(0.05, math.inf).interval_text() == "offsets from 50.0 ms on"
    wide = est(0.08, 0.2)  # 40 ms below the offset: more than a robot sample
    assert not wide.determined
    assert wide.ambiguity_warning("s").startswith("s: the time offset is not determined: "
                                                  "offsets from 80.0 to 200.0 ms fit")  # fmt: skip
    unknown = OffsetEstimate(0.12, 0.1, 1.0, 0.03, 1.0, (0.1, 0.14), 880, 1.0)
    assert unknown.interval_text() == ""
    assert unknown.determined  # not computed: nothing to say


def test_a_pause_of_the_robot_logger_leaves_the_interval_as_narrow(ur10):
    """3 s without robot rows: the tracker samples there are not compared against a
    path the spline would make up across the pause."""
    offset = _random_offset(3)
    t_r, q, t_m, pos, _, _ = simulate_streams(ur10, offset, seed=3)
    keep = (t_r < 4.0) | (t_r > 7.0)
    est = estimate_time_offset(t_r[keep], q[keep], t_m, pos, _Exact(ur10))
    lo, hi = est.interval
    assert lo <= offset <= hi, est.summary()
    assert hi - lo < 4e-4, est.summary()
    assert est.determined, est.summary()


@pytest.mark.parametrize("seed", [3, 7])
def test_interval_covers_the_truth_when_the_tracker_filters_its_noise(ur10, seed):
    """A tracker averaging 30 of its samples (10 ms at 3 kHz): its noise is correlated
    over that span, and at most one sample per robot sample is compared, so the
    evidence is not counted thirty times."""
    offset = _random_offset(seed)
    t_r, q, t_m, pos, _, _ = simulate_streams(ur10, offset, duration=3.0, seed=seed, noise_mm=0.0)
    white = np.random.default_rng(seed).normal(0, 0.02e-3 * 30**0.5, (len(t_m) + 30, 3))
    box = np.ones(30) / 30
    noise = np.stack([np.convolve(white[:, k], box, mode="valid")[: len(t_m)] for k in range(3)], 1)
    est = estimate_time_offset(t_r, q, t_m, pos + noise, _Exact(ur10))
    lo, hi = est.interval
    assert lo <= offset <= hi, (est.summary(), offset)


def test_the_bench_runs_and_finds_no_silent_wrong_offset(monkeypatch, capsys):
    """``bench/time_offset.py`` on one short stream pair: its table, and no wrong offset
    without the warning."""
    bench = Path(__file__).resolve().parents[1] / "bench" / "time_offset.py"
    monkeypatch.setattr(sys, "argv", [str(bench), "--seeds", "100", "--durations", "0.5"])
    runpy.run_path(str(bench), run_name="__main__")
    row = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("| 0.5 s"))
    assert row.endswith("| 0 |"), row  # wrong and not told

"""Clock jumps inside a robot stream and a tracker stream (hybrid_pk.data.clock_jump).

Before, a jump of either clock inside the recording passed without a word: joints
shifted by one sample from row 400 on moved the one offset and its residual (0.03 ->
0.5 mm RMS) and the table was wrong after the jump. Now the step is reported at its row
with the offsets of both parts, and streams without a jump raise nothing.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from hybrid_pk.cli.main import main
from hybrid_pk.data.clock_jump import step_scores
from hybrid_pk.data.streams import estimate_time_offset
from tests.test_streams import ROBOT_HZ, simulate_streams, write_streams

OFFSET = 0.0373  # [s] tracker = robot + offset


@pytest.mark.parametrize(
    ("seed", "jump", "row"),
    [(0, 0.002, 700), (1, -0.004, 250), (2, 0.009, 1000), (3, 0.03, 480), (4, 0.3, 150)],
)
def test_robot_clock_jump_is_reported_at_its_row_with_both_offsets(ur10, seed, jump, row):
    """Robot time stamps that jump by ``jump`` [s] from ``row`` (0-based) on: the rows
    after it sit on the offset ``OFFSET - jump``."""
    t_r, q, t_m, pos, quat, _ = simulate_streams(ur10, OFFSET, seed=seed)
    t_r[row:] += jump
    est = estimate_time_offset(t_r, q, t_m, pos, ur10, quat=quat if seed % 2 else None)
    assert len(est.jumps) == 1, [j.summary() for j in est.jumps]
    found = est.jumps[0]
    assert abs(found.index - row) <= 2, found.summary()
    assert abs(found.z) > found.threshold
    # each part's offset within 0.3 ms (the joint offset of the simulated robot leaves
    # a small systematic error) and within its few standard errors of the other's step
    assert abs(found.before[0] - OFFSET) < 3e-4, found.summary()
    assert abs(found.after[0] - (OFFSET - jump)) < 3e-4, found.summary()
    assert 0 < found.before[1] < 1e-4, found.summary()
    assert 0 < found.after[1] < 1e-4, found.summary()


@pytest.mark.parametrize(("seed", "row"), [(5, 400), (6, 90), (7, 1200)])
def test_joints_one_sample_late_from_a_row_on_are_reported(ur10, seed, row):
    """The case of the defect: the joint values one sample late from ``row`` on."""
    t_r, q, t_m, pos, quat, _ = simulate_streams(ur10, OFFSET, seed=seed)
    q[row:] = q[row - 1 : -1].copy()
    est = estimate_time_offset(t_r, q, t_m, pos, ur10, quat=quat)
    assert [abs(j.index - row) <= 2 for j in est.jumps] == [True], est.summary()
    step = est.jumps[0].after[0] - est.jumps[0].before[0]
    assert abs(step + 1 / ROBOT_HZ) < 5e-4, est.jumps[0].summary()


@pytest.mark.parametrize(
    ("seed", "offset", "noise_mm", "jitter", "orientation"),
    [
        (0, 0.0, 0.005, 0.0, True),
        (1, OFFSET, 0.02, 0.0, False),
        (2, -0.21, 0.05, 0.0, True),
        (3, 0.0, 0.02, 2e-4, False),
        (4, 0.12, 0.005, 1e-3, True),
        (5, -0.05, 0.1, 1e-3, False),
    ],
)
def test_streams_without_a_jump_raise_no_warning(ur10, seed, offset, noise_mm, jitter, orientation):
    """Several seeds, noise levels, offsets (none and constant ones) and time-stamp
    jitter of the robot logger (noise along the motion, which grows with the speed)."""
    t_r, q, t_m, pos, quat, _ = simulate_streams(
        ur10, offset, seed=seed, noise_mm=noise_mm, stamp_jitter=jitter
    )
    est = estimate_time_offset(t_r, q, t_m, pos, ur10, quat=quat if orientation else None)
    assert abs(est.offset - offset) < 1e-3, est.summary()
    assert est.jumps == (), [j.summary() for j in est.jumps]


def test_beam_break_and_tracker_spikes_are_no_clock_jump(ur10):
    t_r, q, t_m, pos, _, _ = simulate_streams(ur10, OFFSET, seed=8)
    cut = (t_m > 4.0) & (t_m < 4.3)  # 0.3 s without tracker data
    rng = np.random.default_rng(8)
    spikes = rng.integers(3000, len(t_m) - 3000, 5)
    pos[spikes] += rng.normal(0, 5e-4, (5, 3))  # five 0.5 mm outliers
    est = estimate_time_offset(t_r, q, t_m[~cut], pos[~cut], ur10)
    assert est.jumps == (), [j.summary() for j in est.jumps]


def test_step_z_of_white_noise_is_standard_normal():
    """The step statistic's own scale: on white noise of known variance, |z| has the
    median of |N(0, 1)| and the largest of 20,000 rows stays below the rule's bound."""
    rng = np.random.default_rng(0)
    n, sigma = 20000, 2e-5
    t = np.arange(n) / ROBOT_HZ
    v = 0.2 * np.sin(2 * np.pi * np.array([0.05, 0.07, 0.11]) * t[:, None] + [0.0, 1.0, 2.0])
    r = rng.normal(0, sigma, (n, 3))
    _, z, tried = step_scores(r, v, np.full(n, sigma**-2))
    assert tried.sum() > n - 40
    assert abs(np.median(np.abs(z[tried])) / norm.ppf(0.75) - 1) < 0.05
    assert np.abs(z).max() < norm.isf(1e-3 / (2 * tried.sum()))


def test_cli_import_streams_warns_of_a_clock_jump_with_file_and_row(ur10, tmp_path, capsys):
    t_r, q, t_m, pos, _, _ = simulate_streams(ur10, OFFSET, duration=8.0, seed=2)
    q[400:] = q[399:-1].copy()  # the joints one sample late from the 401st row on
    robot_csv, tracker_csv = write_streams(tmp_path, ur10.joint_names, t_r, q, t_m, pos)
    argv = ["import", "streams", str(robot_csv), str(tracker_csv), "--robot", "ur10"]
    argv += ["--out", str(tmp_path / "table.csv"), "--no-progress"]
    for extra in ([], ["--offset", str(OFFSET)]):  # estimated, and given
        assert main(argv + extra) == 0
        warnings = [s for s in capsys.readouterr().out.splitlines() if "warning" in s]
        assert len(warnings) == 1, warnings
        assert warnings[0].startswith(f"warning: {robot_csv}, row 401 (t "), warnings
        assert "the time offset jumps from 37." in warnings[0], warnings
        assert "ms (rows 1-400) to 28." in warnings[0], warnings

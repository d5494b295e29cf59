"""The thread policy (issue 30): how many torch threads, from what, and where it is set.

Speed itself is measured by bench/contention.py, not here (no timing asserts)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hybrid_pk import threads
from hybrid_pk.cli.main import main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def fresh(monkeypatch):
    """No --threads fixed and no HYBRID_PK_THREADS; torch's setting restored after."""
    before = torch.get_num_threads()
    monkeypatch.delenv(threads.ENV, raising=False)
    threads.configure(None)  # forgets an earlier --threads
    yield monkeypatch
    monkeypatch.delenv(threads.ENV, raising=False)
    threads.configure(None)
    torch.set_num_threads(before)


def test_parse_accepts_counts_auto_and_torch():
    assert threads.parse_threads("3") == 3
    assert threads.parse_threads(" auto ") is None
    assert threads.parse_threads(None) is None
    assert threads.parse_threads("TORCH") == "torch"
    for bad in ("0", "-2", "many", "1.5"):
        with pytest.raises(ValueError, match="expected a count >= 1"):
            threads.parse_threads(bad)


def test_cores_follow_affinity_and_thecgroup_quota(fresh, tmp_path):
    fresh.setattr(os, "sched_getaffinity", lambda _pid: {0, 1, 2, 3}, raising=False)
    fresh.setattr(threads, "cgroup_quota", lambda: None)
    assert threads.usable_cores() == 4
    fresh.setattr(threads, "cgroup_quota", lambda: 1.5)  # 1.5 CPUs keep 2 threads busy
    assert threads.usable_cores() == 2
    fresh.setattr(threads, "cgroup_quota", lambda: 0.3)
    assert threads.usable_cores() == 1
    fresh.setattr(os, "sched_getaffinity", lambda _pid: {5}, raising=False)
    fresh.setattr(threads, "cgroup_quota", lambda: 8.0)
    assert threads.usable_cores() == 1


def testcgroup_quota_files(tmp_path):
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert threads.cgroup_quota(tmp_path) == pytest.approx(1.5)
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert threads.cgroup_quota(tmp_path) is None
    (tmp_path / "cpu.max").unlink()
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("300000")
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000")
    assert threads.cgroup_quota(tmp_path) == pytest.approx(3.0)
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1")
    assert threads.cgroup_quota(tmp_path) is None


def test_small_work_gets_one_thread_large_work_every_core(fresh):
    fresh.setattr(threads, "usable_cores", lambda: 4)
    rows = threads.ROWS_PER_THREAD
    assert threads.threads_for(1000) == 1
    assert threads.threads_for(2 * rows) == 2
    assert threads.threads_for(100 * rows) == 4
    assert threads.threads_for(None) == 4


def test_work_threads_sizes_restores_and_respects_the_caller(fresh):
    fresh.setattr(threads, "usable_cores", lambda: 2)
    big = 10 * threads.ROWS_PER_THREAD
    torch.set_num_threads(2)
    with threads.work_threads(500) as n:
        assert n == 1 == torch.get_num_threads()
        with threads.work_threads(big) as inner:  # nested: the outer choice holds
            assert inner == 1 == torch.get_num_threads()
    assert torch.get_num_threads() == 2
    torch.set_num_threads(1)  # the caller's setting caps auto
    with threads.work_threads(big) as n:
        assert n == 1
    fresh.setenv(threads.ENV, "2")  # a fixed count wins over the size rule
    with threads.work_threads(500) as n:
        assert n == 2 == torch.get_num_threads()
    assert torch.get_num_threads() == 1
    fresh.setenv(threads.ENV, "torch")
    with threads.work_threads(500) as n:
        assert n == 1  # left alone
    fresh.setenv(threads.ENV, "lots")
    with pytest.raises(ValueError, match="HYBRID_PK_THREADS"), threads.work_threads(500):
        pass


def test_fits_run_on_fit_threads_unless_the_user_fixed_a_count(fresh):
    """A fit or the diagnosis of many rows takes ``FIT_THREADS`` under ``auto`` (their
    operations do not grow with the rows); ``--threads`` / the environment still win,
    and the caller's setting is restored after."""
    fresh.setattr(threads, "usable_cores", lambda: 4)
    seen = []

    @threads.fit_work
    def fake_fit(_model, data):
        seen.append(torch.get_num_threads())

    class Rows:
        n = 100 * threads.ROWS_PER_THREAD

    torch.set_num_threads(4)
    fake_fit(None, Rows())
    fake_fit(None, data=Rows())
    assert seen == [threads.FIT_THREADS] * 2
    assert torch.get_num_threads() == 4
    fresh.setenv(threads.ENV, "3")
    fake_fit(None, Rows())
    assert seen[-1] == 3
    assert torch.get_num_threads() == 4


def test_every_command_takes_threads_and_a_bad_value_is_one_line(fresh, capsys):
    from hybrid_pk.cli.main import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name, parser in sub.choices.items():
        leaves = [parser]
        for action in parser._actions:  # import FORMAT: the formats are the commands
            if getattr(action, "choices", None) and isinstance(action.choices, dict):
                leaves = list(action.choices.values())
        for leaf in leaves:
            assert "--threads" in leaf.format_help(), name
    with pytest.raises(SystemExit):
        main(["simulate", "rx160", "--n", "5", "--out", "x.csv", "--threads", "0"])
    assert "expected a count >= 1" in capsys.readouterr().err
    fresh.setenv(threads.ENV, "-1")
    assert main(["simulate", "rx160", "--n", "5", "--out", "never.csv"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "HYBRID_PK_THREADS" in err[0]


def test_cli_threads_sets_torch(fresh, tmp_path):
    out = tmp_path / "sim.csv"
    assert main(["simulate", "rx160", "--n", "5", "--out", str(out), "--threads", "1"]) == 0
    assert torch.get_num_threads() == 1
    assert threads.requested_threads() == 1


def test_a_count_beyond_the_usable_cores_is_cut_to_them(fresh, tmp_path, capsys):
    """More threads than cores only take turns on them: ``--threads`` and the
    environment are cut to :func:`usable_cores`, the command line says so."""
    fresh.setattr(threads, "usable_cores", lambda: 2)
    fresh.setenv(threads.ENV, "8")
    with threads.work_threads(500) as n:
        assert n == 2 == torch.get_num_threads()
    fresh.delenv(threads.ENV)
    out = tmp_path / "sim.csv"
    assert main(["simulate", "rx160", "--n", "5", "--out", str(out), "--threads", "100000"]) == 0
    assert torch.get_num_threads() == 2
    assert "note: --threads 100000: this process may use 2 cores" in capsys.readouterr().out


def _waiting_policy(env: dict) -> str:
    code = "import os, hybrid_pk; print(os.environ.get('OMP_WAIT_POLICY', 'unset'))"
    full = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", threads.ENV)}
    full.update(env, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", code], env=full, capture_output=True, text=True)
    return out.stdout.strip()


def test_waiting_threads_sleep_unless_the_user_chose():
    assert _waiting_policy({}) == "PASSIVE"
    assert _waiting_policy({"OMP_WAIT_POLICY": "ACTIVE"}) == "ACTIVE"
    assert _waiting_policy({threads.ENV: "torch"}) == "unset"


def _blas_threads() -> set[int]:
    from threadpoolctl import threadpool_info

    return {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}


def test_numpy_and_scipy_blas_follow_the_policy_in_a_call(fresh):
    """numpy's and scipy's own BLAS (OpenBLAS, which threads a large product on every
    core) take the call's count with torch (a fit: one thread) and get theirs back after."""
    import scipy.linalg.blas  # noqa: F401  (loaded: the diagnosis' Gram updates use it)

    fresh.setattr(threads, "usable_cores", lambda: 2)
    torch.set_num_threads(2)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=2, user_api="blas"):  # the caller's, whatever this machine
        before = _blas_threads()
        if not before or before == {1}:
            pytest.skip("no BLAS library here that takes more than one thread")
        with threads.work_threads(10 * threads.ROWS_PER_THREAD, at_most=threads.FIT_THREADS):
            assert _blas_threads() == {1}
        assert _blas_threads() == before
        fresh.setenv(threads.ENV, "torch")  # torch's own setting: nothing is touched
        with threads.work_threads(500):
            assert _blas_threads() == before

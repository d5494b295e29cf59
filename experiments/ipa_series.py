"""What the UR10 experiments (``real_ur10.py``, ``transfer_ur10.py``) share: the two IPA
series, their ``--data`` flag, the in-process ``hybrid-pk`` runner that prints and logs
each command, and importing and reading the series."""

from __future__ import annotations

import argparse
import shlex
import sys
import time
import warnings
from pathlib import Path

from hybrid_pk import Robot
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.data import MeasuredData, read_table_for

__all__ = ["REPO", "SERIES", "add_data", "import_series", "read_rows", "run", "series_paths"]

REPO = Path(__file__).resolve().parents[1]
SERIES = {
    "A": ("Series_A/measurements_grid.csv", "measurements_grid"),
    "B": ("Series_B/measurements_joint_configurations.csv", "measurements_joint_configurations"),
}


def add_data(p: argparse.ArgumentParser) -> None:
    """The ``--data`` flag: the IPA UR10 data set."""
    p.add_argument(
        "--data",
        type=Path,
        default=REPO.parent / "shared" / "data" / "ipa-ur10",
        help="IPA UR10 data set (Series_A/, Series_B/) (default: ../shared/data/ipa-ur10)",
    )


def run(argv: list, log: dict) -> None:
    """One ``hybrid-pk`` command in-process; fails loudly; records its wall time."""
    print("\n$ hybrid-pk " + " ".join(shlex.quote(str(a)) for a in argv), flush=True)
    t = time.perf_counter()
    rc = hybrid_pk([str(a) for a in argv])
    dt = time.perf_counter() - t
    sys.stdout.flush()
    log.setdefault("commands", []).append(
        {"argv": ["hybrid-pk", *map(str, argv)], "seconds": round(dt, 1), "rc": rc}
    )
    print(f"  [{dt:.1f} s]", flush=True)
    if rc != 0:
        raise SystemExit(f"hybrid-pk {argv[0]} failed (exit {rc})")


def read_rows(paths: list[Path], robot: Robot) -> MeasuredData:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Series B's std_* extra columns are not read
        return read_table_for([str(p) for p in paths], robot)


def series_paths(out: Path) -> dict[str, Path]:
    """Where the imported series stand in ``out``, by series key."""
    return {k: out / "series" / f"{name}.parquet" for k, (_, name) in SERIES.items()}


def import_series(out: Path, data: Path, log: dict) -> dict[str, Path]:
    """``hybrid-pk import ipa`` both series of ``data`` into ``out`` unless already
    there; their paths by series key."""
    paths = series_paths(out)
    if not all(f.exists() for f in paths.values()):
        sources = [data / SERIES[k][0] for k in SERIES]
        run(["import", "ipa", *sources, "--out", out / "series", "--format", "parquet"], log)
    return paths

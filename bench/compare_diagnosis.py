"""The same diagnosis with two versions of hybrid_pk: causes and values side by side.

Diagnoses the two shared UR10 series (``--frames-per-file``) with the candidate
vocabulary of before the deflection effects (no ``tilt_compliance`` /
``column_bending``), with whichever hybrid_pk is importable, and writes its causes,
values, std and time to a JSON file. ``--compare A.json B.json`` prints both side by
side with the largest |difference| / std. Run the two versions **one after the other**
(two torch processes on two cores make each other's threads spin)::

    python bench/compare_diagnosis.py --out new.json
    git worktree add /tmp/old 0a897fe && (cd /tmp && PYTHONPATH=/tmp/old \\
        python /work/main/bench/compare_diagnosis.py --out old.json)
    python bench/compare_diagnosis.py --compare old.json new.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

IPA = Path(__file__).resolve().parents[2] / "shared" / "data" / "ipa-ur10"
FILES = ("Series_A/measurements_grid.csv", "Series_B/measurements_joint_configurations.csv")


def run(out: Path) -> None:
    import hybrid_pk as hpk

    try:
        from hybrid_pk.calibration.diagnosis.selection import candidate_labels
    except ImportError:  # the layout of before issue 14
        from hybrid_pk.calibration.diagnose import candidate_labels
    tables = Path(tempfile.mkdtemp(prefix="compare_diag_"))
    cmd = [sys.executable, "-m", "hybrid_pk.cli.main", "import", "ipa"]
    subprocess.run([*cmd, *(str(IPA / f) for f in FILES), "--out", str(tables), "--format",
                    "parquet"], check=True, capture_output=True)  # fmt: skip
    robot = hpk.Robot.from_urdf("ur10")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Series B's std_* columns are not read
        parts = [hpk.read_table_for(tables / f"{Path(f).stem}.parquet", robot) for f in FILES]
    data = hpk.MeasuredData.concat(parts)
    old = ("tilt_compliance", "column_bending")
    candidates = [c for c in candidate_labels(robot, data) if not c.startswith(old)]
    start = time.perf_counter()
    diag = hpk.diagnose(robot, data, frames_per_file=True, candidates=candidates)
    result = {
        "seconds": time.perf_counter() - start,
        "hybrid_pk": hpk.__file__,
        "causes": [
            {"effect": c.effect, "joint": c.joint, "value": c.value, "std": c.std}
            for c in diag.causes
        ],
        "extended": diag.extended,
    }
    out.write_text(json.dumps(result, indent=1, default=float))
    print(f"{len(diag.causes)} causes in {result['seconds']:.1f} s -> {out}")


def compare(a_path: Path, b_path: Path) -> None:
    a, b = (json.loads(p.read_text()) for p in (a_path, b_path))
    ka = {(c["effect"], c["joint"]): c for c in a["causes"]}
    kb = {(c["effect"], c["joint"]): c for c in b["causes"]}
    print(f"{a_path.name}: {a['seconds']:.1f} s, {b_path.name}: {b['seconds']:.1f} s")
    print("same causes" if set(ka) == set(kb) else f"differ: {sorted(set(ka) ^ set(kb))}")
    worst = 0.0
    for key in ka.keys() & kb.keys():
        va, vb = np.atleast_1d(ka[key]["value"]), np.atleast_1d(kb[key]["value"])
        sa = np.atleast_1d(ka[key]["std"])
        z = float((np.abs(va - vb) / np.where(sa > 0, sa, np.inf)).max())
        worst = max(worst, z)
        print(f"  {key[0]}:{key[1]}  {np.round(va, 8)}  {np.round(vb, 8)}  |diff|/std {z:.4f}")
    print(f"largest |difference| / std: {worst:.4f}")
    ea, eb = (d["extended"]["position_mm"]["mean"] for d in (a, b))
    print(f"hold-out mean position error: {ea:.5f} mm / {eb:.5f} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write this version's diagnosis here")
    ap.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"))
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
    elif args.out:
        run(args.out)
    else:
        ap.error("give --out FILE or --compare A B")


if __name__ == "__main__":
    main()

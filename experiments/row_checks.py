"""What the checks of the rows say on the shared UR10 series made wrong the way users'
tables are: both series given one frame set, a tracker bumped within a file,
quaternions written inverted or as x y z w, shoulder-lift values counted from another
zero, and 300 position-only rows of Series A whose error drifts over the hours; then
Series B as measured, with its rows from row 501 on moved by 1 mm (a tracker nudged),
the same diagnosed again with frames of their own from row 501 (``--split-at``), and
with a move growing to 1 mm over its rows (a tripod settling).

    python experiments/row_checks.py --out DIR [--data ../shared/data/ipa-ur10]

Each case is a table written to DIR and one ``hybrid-pk diagnose`` run on it; the
first line it prints to stderr (the refusal) or its ``structural:`` line is echoed.
The numbers the README and the closing note quote come from this script.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
from dataclasses import replace
from pathlib import Path

import torch

from experiments.ipa_series import add_data, import_series, read_rows
from hybrid_pk import Robot
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.data import write_table
from hybrid_pk.geometry import matrix_to_quat, quat_to_matrix, so3_exp


def _cases(a, b) -> dict:
    """The wrong tables, by name: ``(rows, flags)``."""
    first = b.subset(torch.arange(600))  # Series B in the order measured
    turn = so3_exp(torch.tensor([0.0, 0.0, math.radians(3.0)], dtype=torch.float64))
    shift = torch.tensor([0.05, -0.02, 0.01], dtype=torch.float64)  # [m], 55 mm
    pos, quat = first.position.clone(), first.quat.clone()
    pos[360:] = pos[360:] @ turn.T + shift
    quat[360:] = matrix_to_quat(turn @ quat_to_matrix(first.quat[360:]))
    sample = b.subset(torch.randperm(b.n, generator=torch.Generator().manual_seed(5))[:400])
    q90 = sample.q.clone()
    q90[:, 1] += math.pi / 2  # shoulder lift counted from a zero 90 degrees away
    a300 = a.subset(torch.randperm(a.n, generator=torch.Generator().manual_seed(3))[:300])
    move = torch.tensor([0.8e-3, 0.6e-3, 0.0], dtype=torch.float64)  # [m], 1 mm
    step = (torch.arange(b.n) >= 500).double()[:, None]
    ramp = torch.linspace(0.0, 1.0, b.n, dtype=torch.float64)[:, None]
    return {
        "bumped": (replace(first, position=pos, quat=quat), []),
        "inverse": (replace(sample, quat=sample.quat * torch.tensor([1.0, -1, -1, -1])), []),
        "xyzw": (replace(sample, quat=sample.quat[:, [1, 2, 3, 0]]), []),
        "zero90": (replace(sample, q=q90), []),
        "drift": (replace(a300, quat=None), []),
        "series_b": (b, []),
        "nudged": (replace(b, position=b.position + step * move), []),
        "nudged_split": (
            replace(b, position=b.position + step * move),
            ["--frames-per-file", "--split-at", "nudged_split.csv:501"],
        ),
        "settling": (replace(b, position=b.position + ramp * move), []),
    }


def _diagnose(tables: list[Path], flags: list[str], out: Path) -> str:
    """The refusal line, or the structural message and the causes, of one diagnosis."""
    err, json_out = io.StringIO(), out.with_suffix(".json")
    argv = ["diagnose", *map(str, tables), "--robot", "ur10", "--json", str(json_out)]
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = hybrid_pk([*argv, "--no-progress", *flags])
    if rc != 0:
        return err.getvalue().strip().splitlines()[-1]
    doc = json.loads(json_out.read_text())
    causes = ", ".join(
        c["effect"] + (f":{c['joint']}" if c.get("joint") else "") for c in doc["causes"]
    )
    structural = (doc["structural"] or {}).get("message", "none")
    findings = [f["why"] for f in (doc["structural"] or {}).get("findings", [])]
    moves = [w["why"] for w in doc["warnings"] if w["cause"] == "set-up"]
    return (
        f"causes ({len(doc['causes'])}): {causes or 'none'}\n  structural: {structural}\n"
        f"  findings: {findings}\n  set-up: {moves or 'no move named'}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for the tables")
    add_data(ap)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    paths = import_series(args.out, args.data, {})
    robot = Robot.from_urdf("ur10")
    a, b = (read_rows([paths[k]], robot) for k in ("A", "B"))
    print("one frame set for both series:")
    print("  " + _diagnose([paths["A"], paths["B"]], [], args.out / "both"))
    for name, (rows, flags) in _cases(a, b).items():
        table = args.out / f"{name}.csv"
        write_table(table, rows)
        print(f"{name} ({rows.n} rows):\n  " + _diagnose([table], flags, args.out / name))


if __name__ == "__main__":
    main()

"""The networks' rule on a new set-up over many random choices of the re-fit rows (issue 27).

Reads the models ``experiments/transfer_ur10.py`` made in OUT (``extended.pt`` and
``hybrid.pt`` of each direction) and, for ``--picks`` seeds, draws ``--refit-rows``
random rows of the other series, re-fits the frames of both models on them (the
hybrid's re-fit applies :mod:`hybrid_pk.pipelines.network_rule`) and judges both on
the remaining rows: how often the networks are kept, and what the judged rows say of
each verdict. Writes ``OUT/rule_picks.json`` and ``OUT/rule_picks.md``. Run from the
repository root after transfer_ur10.py::

    python experiments/network_rule_picks.py --out /tmp/ur10_transfer --picks 10
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from hybrid_pk.effects import conditions_from_data
from hybrid_pk.evaluation.metrics import row_errors
from hybrid_pk.io.hybrid_file import predict_poses
from hybrid_pk.io.model_file import load_model, model_robot
from hybrid_pk.pipelines.refit import refit

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ipa_series import SERIES, read_rows, series_paths


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="transfer_ur10.py's OUT")
    p.add_argument("--directions", default="A->B,B->A", help="from A->B, B->A (default: both)")
    p.add_argument("--picks", type=int, default=10, help="random choices of re-fit rows")
    p.add_argument("--refit-rows", type=int, default=50, help="rows per re-fit (default 50)")
    return p.parse_args(argv)


def _mean_mm(loaded, rows) -> float:
    T = predict_poses(loaded, rows, conditions_from_data(rows))
    return float(row_errors(T, rows)[0].mean())


def picks(out: Path, name: str, args) -> list[dict]:
    """One row per seed: the verdict and the judged mean errors [mm] of both models."""
    fit, _, judge = name.partition("->")
    d = out / f"{fit}_to_{judge}"
    hybrid, extended = load_model(d / "hybrid.pt"), load_model(d / "extended.pt")
    robot = model_robot(hybrid)
    robot.requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the series' extra columns are not read
        data = read_rows([series_paths(out)[judge]], robot)
    rows = []
    for seed in range(args.picks):
        perm = np.random.default_rng(seed).permutation(data.n)
        pick = torch.zeros(data.n, dtype=torch.bool)
        pick[torch.as_tensor(perm[: args.refit_rows])] = True
        fit_rows, judged = data.subset(pick), data.subset(~pick)
        moved = refit(hybrid, fit_rows, "frames")
        physics = refit(extended, fit_rows, "frames").model
        h = _mean_mm(
            dataclasses.replace(hybrid, model=moved.model, networks=moved.networks), judged
        )
        e = _mean_mm(dataclasses.replace(extended, model=physics), judged)
        rows.append({"seed": seed, **moved.verdict.to_json(), "judged_hybrid_mm": h,
                     "judged_extended_mm": e})  # fmt: skip
        print(f"{name} seed {seed}: {moved.verdict.line()}; judged hybrid / extended {h / e:.4f}")
    return rows


def write_markdown(results: dict, path: Path) -> None:
    lines = ["# The networks' rule over random re-fit rows", ""]
    for name, rows in results.items():
        kept = [r for r in rows if r["used"]]
        ratios = [r["judged_hybrid_mm"] / r["judged_extended_mm"] for r in rows]
        lines += [
            f"## {name}: {len(kept)} of {len(rows)} picks keep the networks",
            "",
            "| seed | kept | gain on the re-fit rows [mm] | judged hybrid / extended |",
            "|---|---|---|---|",
        ]
        for r, ratio in zip(rows, ratios, strict=True):
            gain = f"{r['gain_mm']:+.4f} ± {r['se_mm']:.4f}"
            lines.append(f"| {r['seed']} | {r['used']} | {gain} | {ratio:.4f} |")
        lines += ["", f"worst judged ratio {max(ratios):.4f}", ""]
    path.write_text("\n".join(lines))


def main(argv=None) -> int:
    args = parse_args(argv)
    out = args.out.resolve()
    results = {}
    for name in (s.strip() for s in args.directions.split(",") if s.strip()):
        if name not in ("A->B", "B->A") or not all(k in SERIES for k in name.split("->")):
            raise SystemExit(f"unknown direction {name!r}: A->B or B->A")
        results[name] = picks(out, name, args)
    (out / "rule_picks.json").write_text(json.dumps(results, indent=1) + "\n")
    write_markdown(results, out / "rule_picks.md")
    print((out / "rule_picks.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

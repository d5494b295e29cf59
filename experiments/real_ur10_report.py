"""``results.md`` of ``experiments/real_ur10.py``: the tables of each split and the
diagnosis."""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["write_markdown"]

TITLES = {
    "pan": "(a) shoulder pan turned where no fit row was",
    "region": "(b) the top of the workspace held out",
    "random": "random rows held out (inside the region)",
    "joint": "a joint's upper range held out",
}


def _four(s: dict | None) -> str:
    if s is None:
        return "–"
    return " / ".join(f"{s[k]:.3f}" for k in ("mean", "rms", "p95", "max"))


def _value(v) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"
    if isinstance(v, dict):
        return json.dumps(v)
    return f"{v:.4g}"


def _split_lines(name: str, res: dict, models) -> list[str]:
    lines = ["", f"## Split `{name}`: {TITLES.get(name, name)}", ""]
    lines += [f"- Series {k}: {rule}" for k, rule in res["rules"].items()]
    lines += [
        "",
        "| model | n | position mm mean / RMS / p95 / max "
        "| orientation deg mean / RMS / p95 / max |",
        "|---|---|---|---|",
    ]
    for key, label in models:
        ev = res["evaluate"][key]
        lines.append(
            f"| {label} | {ev['n']} | {_four(ev['position_mm'])} | "
            f"{_four(ev.get('orientation_deg'))} |"
        )
    ext = res["evaluate"]["extended"]["position_mm"]["mean"]
    lines.append("")
    for key, label in models[2:]:
        cmp = res[f"{key}_vs_extended"]
        change = cmp["mean_ratio"] - 1
        word = "lower" if change < 0 else "higher"
        series = ", ".join(f"{n} {r:.3f}" for n, r in cmp["series_ratios"].items())
        weights = ", ".join(f"{s} {w:.2f}" for s, w in res[f"{key}_stage_weights"].items())
        lines.append(
            f"- {label}: mean position error {abs(change):.1%} {word} than the extended "
            f"model's ({ext:.3f} mm); error / extended per series: {series}; worst held-out "
            f"subset ({cmp['worst_subset']}): {cmp['worst_subset_ratio']:.3f}; mean weight "
            f"of the networks on these rows: {weights}."
        )
    return lines


def _diagnosis_lines(diag: dict, rows: str = "fit rows of the region split") -> list[str]:
    lines = [
        "",
        f"## Diagnosis ({rows})",
        "",
        f"`hybrid-pk diagnose` on {diag['n_samples']} rows ({diag['n_holdout']} of them its "
        "own random hold-out); hold-out mean position error "
        f"{diag['nominal']['position_mm']['mean']:.3f} mm nominal -> "
        f"{diag['extended']['position_mm']['mean']:.3f} mm extended.",
        "",
        "| cause | value | ± std (1σ) | unit | gain mm | gain deg |",
        "|---|---|---|---|---|---|",
    ]
    for c in diag["causes"]:
        label = c["effect"] + (f":{c['joint']}" if c.get("joint") else "")
        lines.append(
            f"| {label} | {_value(c['value'])} | {_value(c['std'])} | {c['unit']} | "
            f"{c['position_gain_mm']:.3f} | {c['orientation_gain_deg']:.4f} |"
        )
    for a in diag.get("ambiguous", []):
        lines.append(f"\nAmbiguous: {' / '.join(a['effects'])}: {a.get('why', '')}")
    return lines


def write_markdown(results: dict, models, path: Path) -> None:
    """Write the tables of ``results`` (``real_ur10.main``'s dict) to ``path``."""
    thin = results["thin"]
    rows = f"every {thin}-th row" if thin > 1 else "all rows"
    lines = [
        "# IPA UR10: held-out evaluation",
        "",
        f"Command: `{results['command']}`  ",
        f"Rows: {results['rows']} ({rows}); training epochs {results['epochs']}; "
        f"total wall time {results.get('seconds_total', 0) / 60:.1f} min.",
        "",
        "Errors on the held-out rows, each mean / RMS / p95 / max. Held-out subsets: "
        "each series, and every window of consecutive held-out rows ordered by a joint.",
    ]
    for name, res in results["splits"].items():
        if "evaluate" in res:
            lines += _split_lines(name, res, models)
        if res.get("diagnosis"):
            lines += _diagnosis_lines(res["diagnosis"], f"fit rows of the {name} split")
    if results.get("diagnosis"):
        rows = results.get("diagnosis_rows", "fit rows of the region split")
        lines += _diagnosis_lines(results["diagnosis"], rows)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")

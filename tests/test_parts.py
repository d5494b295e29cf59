"""``--split-at FILE:ROW``: the rows of a file from a row on are a file of their own, with
frames of their own under ``--frames-per-file`` (hybrid_pk.data.parts), so that a set-up
the diagnosis names as moved at a row is diagnosed again without cutting the table."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

import hybrid_pk as hpk
from hybrid_pk.cli.main import main as hybrid_pk
from hybrid_pk.data.parts import parse_split, split_all, split_at
from tests.helpers import run_rng

pytestmark = pytest.mark.usefixtures("one_thread")

LABEL = "joint_offset:joint_3"


def _two_files(rx160, rng) -> hpk.MeasuredData:
    parts = []
    for name in ("a.csv", "b.csv"):
        data, _ = hpk.simulate_campaign(
            rx160, 300, f"{LABEL}=4e-4", noise_mm=0.02, noise_deg=0.002,
            seed=int(rng.integers(1 << 30)),
        )  # fmt: skip
        parts.append(dataclasses.replace(data, sources=(name,)))
    return hpk.MeasuredData.concat(parts)


def test_a_split_makes_the_rows_from_the_row_on_a_file_of_their_own(rx160):
    data = _two_files(rx160, run_rng("split"))
    cut = split_at(data, "a.csv", 101)
    assert cut.sources == ("a.csv", "a.csv (from row 101)", "b.csv")
    a = data.file_index == 0
    assert torch.equal(cut.file_index[a], (data.rows[a] >= 101).long())
    assert torch.equal(cut.file_index[~a], torch.full((300,), 2))
    assert torch.equal(cut.rows, data.rows)  # every row keeps its number in its file
    assert torch.equal(cut.position, data.position)
    # by the file's name alone, and at several rows: the parts named in order
    twice = split_all(data, ["a.csv:101", "b.csv:51", "a.csv (from row 101):201"])
    assert twice.sources == (
        "a.csv", "a.csv (from row 101)", "a.csv (from row 101) (from row 201)",
        "b.csv", "b.csv (from row 51)",
    )  # fmt: skip
    assert torch.bincount(twice.file_index).tolist() == [100, 100, 100, 50, 250]


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("a.csv", "expected FILE:ROW"),
        ("a.csv:0", "expected FILE:ROW"),
        ("c.csv:5", "c.csv is not one DATA file"),
        ("a.csv:1", "both parts need rows; the file's rows are 1 .. 300"),
        ("a.csv:301", "both parts need rows"),
    ],
)
def test_a_split_that_names_no_part_is_refused_in_one_line(rx160, spec, message):
    data = _two_files(rx160, run_rng("split-bad"))
    with pytest.raises(hpk.DataError, match=message):
        split_at(data, *parse_split(spec))


def test_the_commands_split_with_frames_per_file_only(rx160, tmp_path, capsys):
    """diagnose --frames-per-file --split-at: one frame set per part (the transfer check
    leaves each part out in turn); without --frames-per-file: one line, exit 2."""
    data = _two_files(rx160, run_rng("split-cli")).subset(torch.arange(300))
    table = hpk.write_table(tmp_path / "a.csv", data)
    common = [str(table), "--robot", "rx160", "--candidates", LABEL, "--no-progress"]
    out = str(tmp_path / "d.json")
    assert hybrid_pk(["diagnose", *common, "--json", out, "--split-at", "a.csv:151"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("--split-at gives the rows from a row on frames of their own: it "
                            "needs --frames-per-file")  # fmt: skip
    argv = ["diagnose", *common, "--json", out, "--frames-per-file", "--split-at", "a.csv:151"]
    assert hybrid_pk(argv) == 0
    text = capsys.readouterr().out
    assert "a.csv (from row 151)" in text  # the transfer check's second part
    assert json.loads(Path(out).read_text())["n_samples"] == 300

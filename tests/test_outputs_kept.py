"""Outputs never cost an input or an earlier file: a command refuses, before any work,
to write over one of its inputs or a folder; a write that fails (here a real one: the
file-size limit at 0) keeps the file that was there and names it in one line."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

from hybrid_pk.cli.main import main
from hybrid_pk.output_file import OutputError, replacing, write_text

REPO = Path(__file__).resolve().parents[1]
ORIGINAL = "ORIGINAL\n"


def _cli_without_room(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``hybrid-pk ARGS`` in a process that may not write a byte to any file."""

    def no_room():
        resource.setrlimit(resource.RLIMIT_FSIZE, (0, resource.RLIM_INFINITY))

    env = {**os.environ, "PYTHONPATH": str(REPO), "HYBRID_PK_THREADS": "1"}
    cmd = [sys.executable, "-m", "hybrid_pk.cli.main", *args, "--no-progress"]
    return subprocess.run(
        cmd, cwd=cwd, env=env, capture_output=True, text=True, preexec_fn=no_room, timeout=300
    )


def _only_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def _write_through(path: Path, writer) -> None:
    with replacing(path) as tmp:
        writer(tmp)


def test_a_failed_write_keeps_the_old_file_and_leaves_no_part(tmp_path):
    target = tmp_path / "table.csv"
    target.write_text(ORIGINAL)

    def write_half(tmp: Path):
        tmp.write_text("half")
        raise OSError(28, "disk full")

    with pytest.raises(OutputError, match=r"table\.csv: cannot write it \(disk full\); the file"):
        _write_through(target, write_half)
    assert target.read_text() == ORIGINAL
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    fresh = tmp_path / "new" / "out.json"  # folders made; the mode a plain open gives
    write_text(fresh, "{}\n")
    umask = os.umask(0)
    os.umask(umask)
    assert fresh.read_text() == "{}\n"
    assert fresh.stat().st_mode & 0o777 == 0o666 & ~umask


def test_a_table_and_a_model_that_cannot_be_written_keep_the_files_there(tmp_path):
    assert main(["simulate", "rx160", "--n", "40", "--out", str(tmp_path / "a.csv")]) == 0
    for name in ("new.csv", "new.csv.truth.json", "model.pt"):
        (tmp_path / name).write_text(ORIGINAL)
    sim = _cli_without_room(["simulate", "rx160", "--n", "20", "--out", "new.csv"], tmp_path)
    assert sim.returncode == 2
    assert "cannot write it (File too large); the file there is unchanged" in _only_line(sim.stderr)
    calib = ["calibrate", "a.csv", "--robot", "rx160", "--effects", "none", "--out", "model.pt"]
    cal = _cli_without_room([*calib, "--no-urdf"], tmp_path)
    assert cal.returncode == 2, cal.stderr
    assert _only_line(cal.stderr).startswith("hybrid-pk calibrate: error: model.pt: cannot write")
    for name in ("new.csv", "new.csv.truth.json", "model.pt"):
        assert (tmp_path / name).read_text() == ORIGINAL, name
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["calibrate", "{a}", "--robot", "rx160", "--effects", "none", "--out", "{a}"],
         "--out {a} is also the input DATA"),
        (["evaluate", "nominal:rx160", "{a}", "--json", "{a}"],
         "--json {a} is also the input DATA"),
        (["simulate", "rx160", "--poses", "{a}", "--out", "{a}"],
         "--out {a} is also the input --poses"),
        (["calibrate", "{a}", "--robot", "rx160", "--out", "{d}/m.pt", "--urdf", "{d}/m.pt"],
         "--urdf and --out are one file"),
        (["calibrate", "{a}", "--robot", "rx160", "--out", "{d}/m.pt", "--urdf", "{d}/u.urdf",
          "--no-urdf"], "--urdf {d}/u.urdf and --no-urdf: give one of them"),
        (["evaluate", "nominal:rx160", "{a}", "--json", "{d}"], "--json {d} is a folder"),
        (["evaluate", "nominal:rx160", "{a}", "--report", "{a}"], "--report {a} is a file"),
        (["evaluate", "nominal:rx160", "{a}", "--json", "{d}/r/evaluation.json", "--report",
          "{d}/r"], "--json {d}/r/evaluation.json is inside --report {d}/r"),
        (["evaluate", "nominal:rx160", "{a}", "--json", "{a}/x.json"],
         "--json {a}/x.json: {a} is a file, not a folder"),
        (["simulate", "rx160", "--n", "5", "--out", "{d}/t.csv"],
         "its truth file {d}/t.csv.truth.json is a folder"),
    ],
)  # fmt: skip
def test_outputs_over_an_input_or_a_folder_are_refused_before_any_work(
    tmp_path, capsys, args, message
):
    a, d = tmp_path / "a.csv", tmp_path
    assert main(["simulate", "rx160", "--n", "20", "--out", str(a)]) == 0
    (tmp_path / "t.csv.truth.json").mkdir()  # where simulate would put t.csv's truth
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    capsys.readouterr()
    assert main([s.format(a=a, d=d) for s in args]) == 2
    err = _only_line(capsys.readouterr().err)
    assert message.format(a=a, d=d) in err
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    assert after == before  # nothing written


def test_a_link_is_written_through_and_a_device_as_it_is(tmp_path):
    target, link = tmp_path / "target.csv", tmp_path / "link.csv"
    target.write_text(ORIGINAL)
    link.symlink_to(target.name)
    write_text(link, "new\n")
    assert link.is_symlink()
    assert target.read_text() == "new\n"
    full = Path("/dev/full")  # a device is written in place, never replaced by a file
    if not full.exists():
        pytest.skip("no /dev/full here")
    with pytest.raises(OutputError, match=r"/dev/full: cannot write it"):
        write_text(full, "x" * 100_000)
    assert full.is_char_device()


def test_a_urdf_named_as_the_model_is_an_input_too(tmp_path, capsys):
    urdf = tmp_path / "robot.urdf"
    urdf.write_text((REPO / "urdf" / "rx160.urdf").read_text())
    table = tmp_path / "a.csv"
    assert main(["simulate", str(urdf), "--n", "20", "--out", str(table)]) == 0
    capsys.readouterr()
    assert main(["evaluate", f"nominal:{urdf}", str(table), "--json", str(urdf)]) == 2
    assert "--json" in _only_line(capsys.readouterr().err)
    assert urdf.read_text() == (REPO / "urdf" / "rx160.urdf").read_text()


def test_stdout_and_long_names_are_written(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "HYBRID_PK_THREADS": "1"}
    table = tmp_path / ("a" * 240 + ".csv")  # a name near the 255-character limit
    cmd = [sys.executable, "-m", "hybrid_pk.cli.main", "simulate", "rx160", "--n", "5"]
    run = subprocess.run([*cmd, "--out", str(table)], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert table.is_file()
    plan = [sys.executable, "-m", "hybrid_pk.cli.main", "plan", "rx160", "--n", "12"]
    plan += ["--candidates", "40", "--out", str(tmp_path / "p.csv"), "--json", "/dev/stdout"]
    run = subprocess.run(plan, env=env, capture_output=True, text=True)  # stdout: a pipe
    assert run.returncode == 0, run.stderr
    assert '"robot": "rx160"' in run.stdout


def test_a_model_and_its_urdf_are_written_both_or_neither(tmp_path, capsys):
    full = Path("/dev/full")  # the URDF's write fails: the model file must not be replaced
    if not full.exists():
        pytest.skip("no /dev/full here")
    table, model = tmp_path / "a.csv", tmp_path / "m.pt"
    assert main(["simulate", "rx160", "--n", "30", "--out", str(table)]) == 0
    model.write_text(ORIGINAL)
    capsys.readouterr()
    args = ["calibrate", str(table), "--robot", "rx160", "--effects", "none", "--out", str(model)]
    assert main([*args, "--urdf", str(full), "--no-progress"]) == 2
    assert "/dev/full: cannot write it" in _only_line(capsys.readouterr().err)
    assert model.read_text() == ORIGINAL
    assert main([*args, "--no-progress"]) == 0  # and both are written when they can be
    assert model.read_bytes() != ORIGINAL.encode()
    assert (tmp_path / "m.pt.urdf").read_text().startswith("<?xml")


def test_a_plan_and_its_json_are_written_both_or_neither(tmp_path, capsys):
    full = Path("/dev/full")  # the JSON's write fails: the poses must not be replaced
    if not full.exists():
        pytest.skip("no /dev/full here")
    poses = tmp_path / "p.csv"
    poses.write_text(ORIGINAL)
    args = ["plan", "rx160", "--n", "12", "--candidates", "40", "--out", str(poses)]
    assert main([*args, "--json", str(full), "--no-progress"]) == 2
    assert "/dev/full: cannot write it" in _only_line(capsys.readouterr().err)
    assert poses.read_text() == ORIGINAL
    assert main([*args, "--json", str(tmp_path / "p.json"), "--no-progress"]) == 0
    assert poses.read_text() != ORIGINAL
    assert '"robot": "rx160"' in (tmp_path / "p.json").read_text()


_TERMINATED_WHILE_WRITING = """
import os, signal, sys
from pathlib import Path
import pandas as pd
from hybrid_pk.cli.main import main

written = pd.DataFrame.to_csv

def terminated_while_writing(self, path, *args, **kwargs):
    Path(path).write_text("part of a table")
    os.kill(os.getpid(), signal.SIGTERM)  # a `kill` while the table is half written
    return written(self, path, *args, **kwargs)

pd.DataFrame.to_csv = terminated_while_writing
sys.exit(main(sys.argv[1:]))
"""


def test_sigterm_while_writing_keeps_the_old_file_and_leaves_no_part(tmp_path):
    """SIGTERM (`kill`, a scheduler) while a table is written: exit code 143, one line,
    the file it would replace kept and no temporary file beside it (before: the process
    ended at once and left `.campaign.csv.XXXXXXXX.csv` in the folder)."""
    out = tmp_path / "campaign.csv"
    out.write_text(ORIGINAL)
    env = {**os.environ, "PYTHONPATH": str(REPO), "HYBRID_PK_THREADS": "1"}
    args = ["simulate", "rx160", "--n", "10", "--out", str(out), "--no-progress"]
    proc = subprocess.run(
        [sys.executable, "-c", _TERMINATED_WHILE_WRITING, *args],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 143, proc.stderr
    assert _only_line(proc.stderr) == "hybrid-pk simulate: terminated"
    assert out.read_text() == ORIGINAL
    assert sorted(p.name for p in tmp_path.iterdir()) == ["campaign.csv"]


def test_a_read_only_output_is_refused_and_kept(tmp_path, capsys):
    """An output file without write permission (`chmod a-w`) is refused before any work,
    naming the flag; in Python, ``replacing`` refuses it too (before: the rename replaced
    it, even where a plain ``open`` is refused)."""
    out = tmp_path / "campaign.csv"
    out.write_text(ORIGINAL)
    out.chmod(0o444)
    assert main(["simulate", "rx160", "--n", "5", "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert _only_line(err) == (
        f"hybrid-pk simulate: error: --out {out}: the file is read-only; make it writable "
        "or give another name"
    )
    with pytest.raises(OutputError, match=r"\(the file is read-only\); it is unchanged"):
        write_text(out, "NEW\n")
    assert out.read_text() == ORIGINAL
    assert sorted(p.name for p in tmp_path.iterdir()) == ["campaign.csv"]
    out.chmod(0o644)
    assert main(["simulate", "rx160", "--n", "5", "--out", str(out), "--no-progress"]) == 0

"""The progress display of long commands, off a terminal: one line per stage and the
latest inner step, time per stage kept, nothing during the first ``delay`` seconds."""

from __future__ import annotations

import io

from hybrid_pk.cli.progress import Progress


def test_stages_and_steps_become_lines_and_times():
    stream = io.StringIO()
    bar = Progress("demo", 3, stream=stream, delay=0.0)
    bar.stage("simulating")
    bar("writing the table")
    bar.report("diagnosing", None)
    bar.report("diagnosing", "scoring 41 candidates")
    bar.stage("writing the report")
    bar.close()
    lines = stream.getvalue().splitlines()
    assert all(line.startswith("demo [") for line in lines)
    texts = [line.split("] ", 1)[1] for line in lines]
    for stage in ("1/3 simulating", "2/3 diagnosing", "3/3 writing the report"):
        assert stage in texts  # every stage start is printed
    assert texts.index("1/3 simulating") < texts.index("2/3 diagnosing")
    assert list(bar.seconds) == ["simulating", "diagnosing", "writing the report"]


def test_the_latest_step_is_printed_by_the_end():
    stream = io.StringIO()
    with_steps = Progress("calibrate", stream=stream, delay=0.0)
    with_steps.stage("reading data")
    for k in range(5):
        with_steps(f"row block {k}")
    with_steps.close()
    assert stream.getvalue().splitlines()[-1].endswith("reading data | row block 4")


def test_a_quick_command_prints_nothing():
    stream = io.StringIO()
    bar = Progress("evaluate", 2, stream=stream, delay=60.0)
    bar.stage("reading data")
    bar.stage("predicting")
    bar.close()
    assert stream.getvalue() == ""
    assert set(bar.seconds) == {"reading data", "predicting"}


def _leaf_parsers(parser, words=()):
    """``(command words, parser)`` of every command that runs (``import ipa``, not
    ``import``)."""
    import argparse

    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield words, parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from _leaf_parsers(sub, (*words, name))


def test_every_command_takes_no_progress():
    from hybrid_pk.cli.main import build_parser

    leaves = list(_leaf_parsers(build_parser()))
    assert len(leaves) >= 14  # 10 commands + import's 4 formats
    refused = [
        " ".join(words)
        for words, parser in leaves
        if getattr(parser._option_string_actions.get("--no-progress"), "dest", None)
        != "no_progress"
    ]
    assert not refused, f"--no-progress refused by: {refused}"


def test_no_progress_silences_the_bars_a_command_opens(monkeypatch, capsys, tmp_path, rx160):
    """The real calibrate opens its bar without being told about the flag: main's switch
    holds it. The bar is the real one, opened without the half-second delay (a quick
    fit would otherwise print nothing either way)."""
    import hybrid_pk.cli.calibrate_cmd as calibrate_cmd
    from hybrid_pk.cli.main import main
    from hybrid_pk.cli.progress import progress
    from hybrid_pk.data import write_table
    from hybrid_pk.simulate import simulate_campaign

    opened = []

    def at_once(name, total=None, **kw):  # the real bar, shown from its first line
        opened.append(name)
        return progress(name, total, **{**kw, "delay": 0.0})

    monkeypatch.setattr(calibrate_cmd, "progress", at_once)
    data, _ = simulate_campaign(rx160, 60, "joint_offset:joint_3=1e-3", noise_mm=0.01, seed=2)
    write_table(tmp_path / "d.csv", data)
    argv = [
        "calibrate", str(tmp_path / "d.csv"), "--robot", "rx160", "--effects", "none",
        "--out", str(tmp_path / "m.pt"),
    ]  # fmt: skip
    assert main(argv) == 0
    assert "calibrate [" in capsys.readouterr().err  # the bar shows by default
    assert main([*argv, "--no-progress"]) == 0
    assert opened == ["calibrate", "calibrate"]  # the second run opened its bar too
    assert "calibrate [" not in capsys.readouterr().err  # and it stayed silent
    assert main(argv) == 0  # the switch does not outlive the command
    assert "reading data" in capsys.readouterr().err

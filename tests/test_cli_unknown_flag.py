"""A flag the command does not take names the command that does, or its closest own
flag (tour 5: ``diagnose --mount tilt:8``, the mounting flag of ``simulate``, said only
'unrecognized arguments')."""

from __future__ import annotations

import pytest

from hybrid_pk.cli.main import main


@pytest.mark.parametrize(
    ("argv", "hint"),
    [
        (["--mount", "tilt:8"], "--mount is a flag of simulate, not of diagnose"),
        (["--gravty", "level-tracker"], "--gravty: did you mean --gravity?"),
    ],
)
def test_an_unknown_flag_names_its_owner_or_its_closest_match(tmp_path, capsys, argv, hint):
    data = tmp_path / "d.csv"
    data.write_text("x\n")
    with pytest.raises(SystemExit) as exc:
        main(["diagnose", str(data), "--robot", "rx160", "--json", str(tmp_path / "o.json"), *argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments" in err, err
    assert hint in err, err
    assert "see hybrid-pk diagnose --help" in err, err


def test_a_stray_word_is_refused_as_before(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "m.pt", "d.csv", "--json", str(tmp_path / "o.json"), "--bogus-flag-xyz"])
    assert exc.value.code == 2
    assert "unrecognized arguments: --bogus-flag-xyz" in capsys.readouterr().err

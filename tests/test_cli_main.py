"""The CLI's error policy: one line on stderr, never a traceback unless --debug."""

from __future__ import annotations

import pytest

import hybrid_pk.cli.evaluate_cmd as evaluate_cmd
from hybrid_pk.cli.main import main
from hybrid_pk.errors import HybridPKError


def _fail_with(exc: Exception):
    def run(args):
        raise exc

    return run


@pytest.mark.parametrize(
    ("exc", "code", "text"),
    [
        (HybridPKError("give --fit-frames"), 2, "hybrid-pk evaluate: error: give --fit-frames"),
        (RuntimeError("boom\nsecond line"), 1, "internal error: RuntimeError: boom second line"),
    ],
)
def test_an_error_is_one_line(monkeypatch, capsys, tmp_path, exc, code, text):
    monkeypatch.setattr(evaluate_cmd, "run", _fail_with(exc))
    assert main(["evaluate", "nominal:rx160", str(tmp_path / "d.csv")]) == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert text in err
    assert "Traceback" not in err


def test_debug_shows_the_traceback(monkeypatch, tmp_path):
    monkeypatch.setattr(evaluate_cmd, "run", _fail_with(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        main(["--debug", "evaluate", "nominal:rx160", str(tmp_path / "d.csv")])

"""Docs are code: every code block of the README and the walkthroughs runs, in order,
as written (sizes reduced where a directive says so; see tests/doc_blocks.py and
docs/code_blocks.md for the convention)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.doc_blocks import REPO, BlockFailure, main, parse_blocks, run_document

DOCUMENTS = [REPO / "README.md", *sorted((REPO / "experiments").glob("*.md"))]
SHARED = REPO.parent / "shared" / "data"


def _id(doc: Path) -> str:
    return doc.relative_to(REPO).as_posix()


@pytest.mark.parametrize("doc", DOCUMENTS, ids=_id)
def test_every_code_block_runs_or_says_why_not(doc):
    """Fast check of the directives alone: every block runs, or names its reason."""
    blocks = parse_blocks(doc)
    assert blocks, f"{doc.name} has no code block"
    for block in blocks:
        for key in ("skip", "long"):
            assert all(reason for reason in block.get(key)), (
                f"{block.where}: {key} without a reason"
            )
        block.source()  # every sub directive still matches its block


@pytest.mark.slow
@pytest.mark.parametrize("doc", DOCUMENTS, ids=_id)
def test_document_blocks_run(doc):
    text = doc.read_text(encoding="utf-8")
    if "../shared/data" in text and not SHARED.is_dir():
        pytest.skip(f"{doc.name} reads the shared data, not found at {SHARED}")
    failure, done = None, []
    try:
        done = run_document(doc)
    except BlockFailure as exc:
        failure = str(exc)
    if failure:  # the block, its line and its output; no harness internals
        pytest.fail(failure, pytrace=False)
    assert any(status == "ran" for _, status, _ in done)


def _write(tmp_path: Path, text: str) -> Path:
    doc = tmp_path / "doc.md"
    doc.write_text(text, encoding="utf-8")
    return doc


def test_a_broken_block_fails_and_names_it(tmp_path):
    doc = _write(
        tmp_path,
        "# Doc\n\n```bash\necho first > out.txt\n```\n\nThen:\n\n"
        "```python\nfrom pathlib import Path\nassert Path('out.txt').read_text() == 'first\\n'\n"
        "import hybrid_pk as hpk\nhpk.no_such_function()\n```\n",
    )
    with pytest.raises(BlockFailure) as exc:
        run_document(doc)
    message = str(exc.value)
    assert "doc.md:9 (python block): exit code 1" in message  # the second block, its line
    assert "no_such_function" in message


def test_a_broken_command_fails(tmp_path):
    doc = _write(
        tmp_path, "```bash\nhybrid-pk simulate rx160 --n 5 --no-such-flag --out a.csv\n```\n"
    )
    with pytest.raises(BlockFailure, match=r"doc\.md:1 .*exit code 2"):
        run_document(doc)


def test_shell_variables_and_files_carry_over_and_directives_apply(tmp_path):
    doc = _write(
        tmp_path,
        "```bash\nN=3000\n```\n\n<!-- test\nsub: 3000 => 7\ncreates: a.csv\n"
        "expect: simulated 7 rows\n-->\n\n```bash\nN=3000\n"
        "hybrid-pk simulate rx160 --n $N --seed 1 --out a.csv\n```\n\n"
        "<!-- test skip: shows a server -->\n```bash\ntensorboard --logdir runs\n```\n",
    )
    statuses = [status for _, status, _ in run_document(doc)]
    assert statuses == ["ran", "ran", "skipped"]


def test_a_command_prefix_is_not_a_shell_variable(tmp_path):
    """``VAR=value cmd`` sets VAR for that command only: the block still passes and VAR
    does not carry over; real assignments (also quoted, ``$( )``, in a branch) do."""
    doc = _write(
        tmp_path,
        '```bash\nA=1\nexport B="two words" C=$(echo "x y")\nHPK_DOC_PREFIX=5 true\n'
        "if false; then E=5; fi\n```\n\n"
        "<!-- test expect: [1|two words|x y|unset|unset] -->\n```bash\n"
        'echo "[$A|$B|$C|${HPK_DOC_PREFIX-unset}|${E-unset}]"\n```\n',
    )
    assert [status for _, status, _ in run_document(doc)] == ["ran", "ran"]


def test_one_block_runs_as_written(tmp_path, capsys):
    """``python -m tests.doc_blocks DOC --block LINE --in DIR``: no earlier block, no
    directive applied, in DIR."""
    doc = _write(
        tmp_path,
        "```bash\nN=1\n```\n\n<!-- test sub: 3000 => 7 -->\n```bash\n"
        'echo "n=${N-unset} 3000" > seen.txt\nOMP_NUM_THREADS=1 cat seen.txt\n```\n',
    )
    folder = tmp_path / "run"
    folder.mkdir()
    assert main([str(doc), "--block", "6", "--in", str(folder)]) == 0
    assert capsys.readouterr().out == "n=unset 3000\n"
    assert (folder / "seen.txt").exists()


@pytest.mark.parametrize(
    ("directive", "error"),
    [
        ("<!-- test sub: 3001 => 7 -->", "the block has no '3001'"),
        ("<!-- test frobnicate: yes -->", "unknown test directive"),
        ("<!-- test expect: never printed -->", "output lacks 'never printed'"),
        ("<!-- test creates: nothing.csv -->", "did not create nothing.csv"),
    ],
)
def test_a_wrong_directive_fails(tmp_path, directive, error):
    doc = _write(tmp_path, f"{directive}\n```bash\necho 3000\n```\n")
    with pytest.raises(BlockFailure, match=re.escape(error)):
        run_document(doc)

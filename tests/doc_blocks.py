"""Run the code blocks of a Markdown document, in order, as a user would.

The convention (also in ``docs/code_blocks.md``):

- Every fenced block tagged ``bash``, ``sh``, ``shell`` or ``python`` is code and runs.
  Untagged and ``text`` blocks (trees, output) are not code.
- The blocks of one document run in order, in one fresh folder per document, so a
  later block sees the files (and the shell variables: :func:`assigned_names`) of the
  earlier ones. The folder
  stands where the repository root would: every top-level entry of the repository is
  linked into it (``train/``, ``experiments/``, ``bench/`` ...) and ``../shared`` is
  the shared data folder beside the repository.
- ``hybrid-pk`` and ``python`` are this checkout's (``PYTHONPATH`` is the repository).
  A bash block runs under ``bash -e -o pipefail``; a python block runs as a script.
- An HTML comment right before a block (blank lines between are allowed) changes how
  it runs, one directive a line::

      <!-- test
      sub: --n 3000 => --n 300
      setup: hybrid-pk simulate rx160 --n 200 --seed 1 --out campaign.csv
      cd: hybrid_pk_demo
      creates: report.md model.pt
      expect: solutions
      -->

  or one directive on one line: ``<!-- test skip: the suite itself (CI runs it) -->``.

  ``sub: OLD => NEW``   replace OLD by NEW in the block before it runs (smaller sizes,
                        fewer epochs: the same flags); OLD must occur, so a stale
                        directive fails. May repeat.
  ``setup: COMMAND``    shell command run first, in the same folder (files the block
                        expects, e.g. a campaign). May repeat.
  ``cd: DIR``           run the block in DIR (relative to the document's folder).
  ``creates: FILE...``  the block must create these files (relative to where it ran).
  ``expect: TEXT``      its output must contain TEXT. May repeat.
  ``timeout: S``        seconds before it counts as failed (default 600).
  ``skip: REASON``      not run; REASON says why (installation, the test suite itself).
  ``long: REASON``      too long for the test suite: run, with its ``creates`` and
                        ``expect`` checks, by ``python -m tests.doc_blocks --long DOC``.

``tests/test_docs.py`` runs every document's blocks except the long ones.
``python -m tests.doc_blocks README.md --block LINE --in DIR`` runs one block exactly as
written in DIR (e.g. the Python example in a demo's output folder).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

__all__ = [
    "Block",
    "BlockFailure",
    "assigned_names",
    "parse_blocks",
    "run_block_as_written",
    "run_document",
]

REPO = Path(__file__).resolve().parents[1]
CODE_TAGS = {"bash": "bash", "sh": "bash", "shell": "bash", "python": "python"}
DIRECTIVES = {"sub", "setup", "cd", "creates", "expect", "timeout", "skip", "long"}
_FENCE = re.compile(r"^(?P<indent> *)(?P<fence>```+|~~~+)\s*(?P<tag>[\w+-]*)")
_ASSIGNMENT = re.compile(r"(?:(?:export|declare|readonly|local)(?:\s+-\w+)*\s+)?([A-Za-z_]\w*)=")
_CLOSE = {"(": ")", "{": "}"}


def _word_end(line: str, i: int) -> int:
    """Where the shell word starting at ``line[i]`` ends: quotes, ``$( )``, ``${ }``,
    backquotes and backslashes are skipped over; an unquoted blank or ``;&|<>`` ends it."""
    while i < len(line) and not line[i].isspace() and line[i] not in ";&|<>":
        c = line[i]
        if c == "\\":
            i += 2
        elif c in "'\"`":
            i += 1
            while i < len(line) and line[i] != c:
                i += 2 if c != "'" and line[i] == "\\" else 1
            i += 1
        elif c == "$" and line[i + 1 : i + 2] in _CLOSE:
            opening, depth, i = line[i + 1], 0, i + 1
            while i < len(line):
                depth += {opening: 1, _CLOSE[opening]: -1}.get(line[i], 0)
                i += 1
                if depth == 0:
                    break
        else:
            i += 1
    return i


def assigned_names(code: str) -> list[str]:
    """The shell variables a bash block sets: names of the lines (or ``;``-separated
    parts) that are only assignments (``N=3000``, ``export OUT="a b"``, ``X=$(cmd)``).
    ``VAR=value cmd`` sets VAR for that one command only, so it is not one of them."""
    names: set[str] = set()
    for line in code.splitlines():
        for part in re.split(r"\s*(?:;|&&|\|\||\bthen\b|\bdo\b|\belse\b)\s*", line.strip()):
            found, i = [], 0
            while (m := _ASSIGNMENT.match(part, i)) is not None:
                found.append(m[1])
                i = _word_end(part, m.end())
                i += len(part[i:]) - len(part[i:].lstrip())
            if found and (i >= len(part) or part[i] == "#"):
                names.update(found)
    return sorted(names)


class BlockFailure(AssertionError):
    """A block failed: the message names the document, line, command and output."""


@dataclass
class Block:
    """One code block of a document and the directives of the comment before it."""

    doc: Path
    line: int  # 1-based line of the opening fence
    lang: str  # "bash" or "python"
    code: str
    directives: dict[str, list[str]] = field(default_factory=dict)

    def get(self, key: str) -> list[str]:
        return self.directives.get(key, [])

    @property
    def where(self) -> str:
        return f"{self.doc.name}:{self.line}"

    def source(self) -> str:
        """The code after the ``sub`` directives; a stale directive raises."""
        code = self.code
        for item in self.get("sub"):
            old, sep, new = item.partition("=>")
            old, new = old.strip(), new.strip()
            if not sep or not old:
                raise BlockFailure(f"{self.where}: 'sub: {item}' is not 'sub: OLD => NEW'")
            if old not in code:
                raise BlockFailure(
                    f"{self.where}: 'sub: {old} => ...' but the block has no {old!r}"
                )
            code = code.replace(old, new)
        return code


def _directives(comment: str, where: str) -> dict[str, list[str]]:
    body = comment.strip()[len("<!--") : -len("-->")].strip()
    assert body.startswith("test")
    body = body[len("test") :]
    out: dict[str, list[str]] = {}
    for raw in body.splitlines():
        line = raw.strip()
        if not line:
            continue
        key, sep, value = line.partition(":")
        if not sep or key.strip() not in DIRECTIVES:
            raise BlockFailure(
                f"{where}: unknown test directive {line!r} (known: {sorted(DIRECTIVES)})"
            )
        out.setdefault(key.strip(), []).append(value.strip())
    return out


def parse_blocks(doc: Path) -> list[Block]:
    """The code blocks of ``doc`` with their directives, in document order."""
    lines = doc.read_text(encoding="utf-8").splitlines()
    blocks: list[Block] = []
    pending: tuple[int, str] | None = None  # (line, comment) of a "<!-- test" comment
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.strip().startswith("<!-- test"):
            start, text = i, line
            while "-->" not in text and i + 1 < len(lines):
                i += 1
                text += "\n" + lines[i]
            pending = (start + 1, text)
            i += 1
            continue
        m = _FENCE.match(line)
        if m is None:
            if line.strip() and pending is not None:
                raise BlockFailure(
                    f"{doc.name}:{pending[0]}: a test directive must stand right before a "
                    "code block"
                )
            i += 1
            continue
        fence, tag, indent = m["fence"], m["tag"].lower(), len(m["indent"])
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence):
            j += 1
        code = "\n".join(
            raw[indent:] if raw[:indent].isspace() else raw for raw in lines[i + 1 : j]
        )
        where = f"{doc.name}:{i + 1}"
        directives = _directives(pending[1], where) if pending else {}
        if tag in CODE_TAGS:
            blocks.append(Block(doc, i + 1, CODE_TAGS[tag], code + "\n", directives))
        elif pending is not None:
            raise BlockFailure(
                f"{where}: a test directive before a block that is not code ({tag or 'untagged'})"
            )
        pending = None
        i = j + 1
    return blocks


def _workspace(root: Path) -> Path:
    """A folder that stands where the repository root would, with ../shared beside it."""
    work = root / "work"
    work.mkdir()
    for entry in REPO.iterdir():
        if entry.name.startswith(".") and entry.name != ".ci":
            continue
        (work / entry.name).symlink_to(entry)
    shared = REPO.parent / "shared"
    if shared.exists():
        (root / "shared").symlink_to(shared)
    bin_dir = root / "bin"
    bin_dir.mkdir()
    for name, target in (("hybrid-pk", "-m hybrid_pk.cli.main"), ("python", ""), ("python3", "")):
        script = bin_dir / name
        script.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} {target} "$@"\n')
        script.chmod(0o755)
    return work


def _environment(root: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{root / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = str(REPO) + (
        os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""
    )
    env.setdefault("OMP_NUM_THREADS", "1")
    env["MPLBACKEND"] = "Agg"
    return env


def _run(argv: list[str], cwd: Path, env: dict, timeout: float, what: str) -> str:
    try:
        proc = subprocess.run(
            argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired as exc:
        raise BlockFailure(f"{what}: no result after {timeout:g} s") from exc
    output = proc.stdout + proc.stderr
    if proc.returncode != 0:
        raise BlockFailure(f"{what}: exit code {proc.returncode}; last output:\n{output[-3000:]}")
    return output


def _run_block(block: Block, work: Path, env: dict, state: Path) -> str:
    cwd = work / block.get("cd")[-1] if block.get("cd") else work
    timeout = float(block.get("timeout")[-1]) if block.get("timeout") else 600.0
    for command in block.get("setup"):
        _run(
            ["bash", "-e", "-o", "pipefail", "-c", command],
            work,
            env,
            timeout,
            f"{block.where} setup `{command}`",
        )
    code = block.source()
    what = f"{block.where} ({block.lang} block)"
    if block.lang == "python":
        script = state.parent / f"block_{block.line}.py"
        script.write_text(code, encoding="utf-8")
        output = _run([sys.executable, str(script)], cwd, env, timeout, what)
    else:
        names = " ".join(assigned_names(code))  # one not set (a branch not taken) is skipped
        keep = f"\n{{ declare -p {names} 2>/dev/null || true; }} >> {shlex.quote(str(state))}\n"
        keep = keep if names else ""
        script = f"source {shlex.quote(str(state))}\n{code}{keep}"
        output = _run(["bash", "-e", "-o", "pipefail", "-c", script], cwd, env, timeout, what)
    for name in " ".join(block.get("creates")).split():
        if not (cwd / name).exists():
            raise BlockFailure(f"{what}: did not create {name}; output:\n{output[-2000:]}")
    for text in block.get("expect"):
        if text not in output:
            raise BlockFailure(f"{what}: output lacks {text!r}; output:\n{output[-2000:]}")
    return output


def run_document(
    doc: str | Path, *, long: bool = False, log=None
) -> list[tuple[Block, str, float]]:
    """Run the blocks of ``doc`` in order in a fresh folder.

    Args:
        doc: the Markdown file.
        long: also run the blocks marked ``long`` (the test suite does not).
        log: called with one line per block (``print`` for the command line).

    Returns:
        ``(block, "ran" | "skipped" | "long", seconds)`` for every code block.

    Raises:
        BlockFailure: at the first block that fails, naming it.
    """
    doc = Path(doc).resolve()
    blocks = parse_blocks(doc)
    done = []
    with tempfile.TemporaryDirectory(prefix="docblocks_") as tmp:
        root = Path(tmp)
        work = _workspace(root)
        env = _environment(root)
        state = root / "shell_state.sh"
        state.write_text("")
        for block in blocks:
            if block.get("skip"):
                done.append((block, "skipped", 0.0))
                continue
            if block.get("long") and not long:
                block.source()  # a stale sub fails even when the block does not run
                done.append((block, "long", 0.0))
                continue
            start = time.perf_counter()
            _run_block(block, work, env, state)
            done.append((block, "ran", time.perf_counter() - start))
            if log is not None:
                log(f"ok {block.where} ({done[-1][2]:.1f} s)")
    return done


def run_block_as_written(
    doc: str | Path, line: int, folder: str | Path, timeout: float = 600.0
) -> str:
    """Run the block of ``doc`` that opens at ``line`` exactly as written (no directive
    applied) in ``folder``, e.g. the README's Python example in a demo's output folder.

    Returns:
        Its output. Raises :class:`BlockFailure` if it fails.
    """
    block = next((b for b in parse_blocks(Path(doc).resolve()) if b.line == line), None)
    if block is None:
        raise BlockFailure(f"{Path(doc).name}:{line} opens no code block")
    with tempfile.TemporaryDirectory(prefix="docblocks_") as tmp:
        root = Path(tmp)
        _workspace(root)
        plain = Block(block.doc, block.line, block.lang, block.code, {"timeout": [str(timeout)]})
        state = root / "shell_state.sh"
        state.write_text("")  # no earlier block: nothing carried over
        return _run_block(plain, Path(folder).resolve(), _environment(root), state)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run the code blocks of Markdown documents.")
    parser.add_argument("docs", nargs="+", help="Markdown files")
    parser.add_argument("--long", action="store_true", help="also run the blocks marked long")
    parser.add_argument(
        "--block", type=int, metavar="LINE", help="run only the block opening at LINE, as written"
    )
    parser.add_argument("--in", dest="folder", metavar="DIR", help="with --block: run it in DIR")
    parser.add_argument("--timeout", type=float, default=600.0, help="with --block: seconds")
    args = parser.parse_args(argv)
    if args.block is not None:
        try:
            out = run_block_as_written(args.docs[0], args.block, args.folder or ".", args.timeout)
            print(out, end="")
        except BlockFailure as exc:
            print(f"FAILED {exc}", file=sys.stderr)
            return 1
        return 0
    for doc in args.docs:
        try:
            run_document(doc, long=args.long, log=print)
        except BlockFailure as exc:
            print(f"FAILED {exc}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

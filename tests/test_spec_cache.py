"""A robot read before loads from the per-user cache of chain specs (hybrid_pk.robot.
spec_cache): the same numbers to the last bit, without importing the URDF readers; a
changed URDF is read again; the cache can be turned off or be unwritable."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from hybrid_pk.robot.chain_spec import _read_chain_spec, _Tree, load_chain_spec, resolve_urdf
from hybrid_pk.robot.spec_cache import ENV

ARM7 = Path(__file__).resolve().parent / "data" / "arm7_generic.urdf"


def _same(a, b) -> bool:
    """Field by field, arrays bit for bit (NaN-free), the branch bodies likewise."""
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "branches":
            if len(x) != len(y) or not all(_same(p, q) for p, q in zip(x, y, strict=True)):
                return False
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if x.dtype != y.dtype or x.shape != y.shape or not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv(ENV, raising=False)
    return tmp_path / "cache" / "hybrid_pk" / "spec"


@pytest.mark.parametrize(
    ("urdf", "end"), [("ur10", None), ("rx160", None), ("column_arm", "tool0"), (ARM7, "tool0")]
)
def test_a_kept_spec_is_the_read_one_bit_for_bit(cache, urdf, end):
    path = resolve_urdf(urdf)
    read = _read_chain_spec(_Tree(path), end)
    first = load_chain_spec(urdf, end)  # read, and kept
    assert len(list(cache.glob("*.json"))) == 1
    kept = load_chain_spec(urdf, end)  # from the cache
    assert _same(first, read)
    assert _same(kept, read)
    assert kept.urdf_path == str(path)


def test_a_kept_spec_needs_no_urdf_reader(cache):
    load_chain_spec("ur10")
    code = (
        "import sys; from hybrid_pk import Robot; r = Robot.from_urdf('ur10'); "
        "print(r.dof, 'pytorch_kinematics' in sys.modules, 'yourdfpy' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True,
        env={**os.environ, "XDG_CACHE_HOME": str(cache.parents[1])},
    )  # fmt: skip
    assert out.stdout.split() == ["6", "False", "False"]


def test_a_changed_urdf_is_read_again(cache, tmp_path):
    text = resolve_urdf("ur10").read_text()
    path = tmp_path / "arm.urdf"
    path.write_text(text)
    before = load_chain_spec(path)
    old = '<origin xyz="0 0.220941 0" rpy="0 1.57079632679 0"/>'
    assert text.count(old) == 1
    longer = text.replace(old, '<origin xyz="0 0.230941 0" rpy="0 1.57079632679 0"/>')
    path.write_text(longer)
    after = load_chain_spec(path)
    assert not _same(before, after)
    assert _same(after, _read_chain_spec(_Tree(path), None))
    assert len(list(cache.glob("*.json"))) == 2


def test_the_cache_off_or_unwritable_reads_the_urdf(cache, tmp_path, monkeypatch):
    monkeypatch.setenv(ENV, "off")
    off = load_chain_spec("rx160")
    assert not cache.exists() or not list(cache.glob("*.json"))
    monkeypatch.delenv(ENV)
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the cache folder would be")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocked))
    before = set(Path(tempfile.gettempdir()).glob("hybrid_pk_spec_*"))
    assert _same(load_chain_spec("rx160"), off)  # read again, nothing kept
    assert set(Path(tempfile.gettempdir()).glob("hybrid_pk_spec_*")) == before


def test_a_damaged_kept_spec_is_read_again(cache):
    first = load_chain_spec("ur10")
    (kept,) = cache.glob("*.json")
    kept.write_text('{"name": "ur10", "cut off')
    assert _same(load_chain_spec("ur10"), first)

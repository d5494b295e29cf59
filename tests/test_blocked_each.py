"""The blocked score of many candidates at once (``Blocked.each``) is the score of each
alone (``Blocked.of``), to round-off: the batch only gathers and solves together what
the one-at-a-time score computes apart. (To the last bit on some CPUs; on others the
batched products sum in another order, 1 ulp apart: 894.7074043224883 against ...882.)
Campaign drawn per run (``tests.helpers.run_rng``)."""

from __future__ import annotations

import math

import torch

from hybrid_pk.calibration.diagnosis.blocked import Blocked, Folds
from hybrid_pk.calibration.problem import ParamBlock
from tests.helpers import run_rng


def _blocked(rng) -> tuple[Blocked, list[str]]:
    """Two files with frames of their own (a held-out file leaves its frame columns
    unseen by the training rows), three regions each, effects of 1-3 columns."""
    n, files, regions = int(rng.integers(300, 500)), 2, 3
    file = torch.as_tensor(rng.integers(0, files, n))
    cell = file * regions + torch.as_tensor(rng.integers(0, regions, n))
    frames = [ParamBlock(f"base_frame.translation[{f}]", f"f{f}", 3, 1.0, "m") for f in (0, 1)]
    sizes = [int(s) for s in rng.integers(1, 4, 8)]
    effects = [ParamBlock(f"effect_{i}:j{i}", f"e{i}", s, 1.0, "m") for i, s in enumerate(sizes)]
    blocks = (*frames, *effects)
    p = sum(b.size for b in blocks)
    J = torch.as_tensor(rng.normal(size=(2, n, p)))
    for f in (0, 1):  # a file's frame columns: its rows only
        J[:, file != f, 3 * f : 3 * f + 3] = 0.0
    r = torch.as_tensor(rng.normal(size=(2, n)))
    grams = torch.zeros(2, files * regions, p + 1, p + 1, dtype=J.dtype)
    for ch in (0, 1):
        M = torch.cat([J[ch], r[ch][:, None]], 1)
        for c in range(files * regions):
            grams[ch, c] = M[cell == c].T @ M[cell == c]
    by_region = tuple(tuple(f * regions + g for f in range(files)) for g in range(regions))
    by_file = tuple(tuple(range(f * regions, (f + 1) * regions)) for f in range(files))
    folds = Folds(cell, files * regions, by_region + by_file, {})
    values = torch.as_tensor(rng.normal(size=p))
    b = Blocked(grams[0], grams[1], folds, blocks, values, (0.02, 1e-4))
    return b, [e.label for e in effects]


def _same(a: list, b: list) -> bool:
    """Scores equal but for round-off (1e-12 relative), the row counts exactly."""

    def flat(x):
        if isinstance(x, (tuple, list)):
            return [y for item in x for y in flat(item)]
        if hasattr(x, "per_fold"):
            return flat([x.total, x.position, x.rotation, x.rows, x.per_fold])
        return [x]

    fa, fb = flat(a), flat(b)
    return len(fa) == len(fb) and all(
        x == y if isinstance(x, int) or x is None else math.isclose(x, y, rel_tol=1e-12)
        for x, y in zip(fa, fb, strict=True)
    )


def test_each_is_every_candidate_scored_alone():
    b, labels = _blocked(run_rng("blocked-each"))
    current, extras = labels[:3], labels[3:]
    assert _same(b.each(current, extras), [b.of([*current, x]) for x in extras])
    # one effect of the model set to zero (its columns held at minus their values); an
    # extra that is that effect frees its columns again and is scored as such
    rest, removed = current[1:], current[:1]
    each = b.each(rest, [*extras, removed[0]], removed)
    assert _same(each, [b.of([*rest, x], removed) for x in [*extras, removed[0]]])
    # the held-out files leave their frame columns unseen: those folds are in the batch
    assert len(each[0].per_fold) == 5

"""hybrid_pk.geometry.broadcast_shapes: torch.broadcast_shapes' rule, checked against it
on random shapes, without importing sympy (torch's version costs 0.4-0.8 s on its
first call in every command)."""

from __future__ import annotations

import random
import subprocess
import sys

import pytest
import torch

from hybrid_pk.geometry import broadcast_shapes


def _random_shape(rng: random.Random) -> tuple[int, ...]:
    return tuple(rng.choice([0, 1, 1, 2, 3]) for _ in range(rng.randint(0, 4)))


def test_same_shape_or_error_as_torch():
    rng = random.Random(0)
    agreed = failed = 0
    for _ in range(2000):
        shapes = [_random_shape(rng) for _ in range(rng.randint(1, 3))]
        try:
            want = torch.broadcast_shapes(*shapes)
        except RuntimeError:
            with pytest.raises(RuntimeError, match="cannot be broadcast"):
                broadcast_shapes(*shapes)
            failed += 1
            continue
        assert broadcast_shapes(*shapes) == want
        agreed += 1
    assert agreed > 200  # both outcomes exercised
    assert failed > 200
    assert broadcast_shapes(3, (2, 1)) == torch.broadcast_shapes(3, (2, 1))  # ints: 1-D
    assert broadcast_shapes() == torch.Size([])


def test_fk_and_a_diagnosis_import_no_sympy():
    """The first batch check of a command no longer loads sympy (a fresh process)."""
    code = (
        "import sys, torch, hybrid_pk as hpk\n"
        "from hybrid_pk.simulate import simulate_campaign\n"
        "r = hpk.Robot.from_urdf('rx160')\n"
        "r.fk(r.sample_q(4, torch.Generator().manual_seed(0)))\n"
        "d, _ = simulate_campaign(r, 60, 'joint_offset:joint_2=1e-3', noise_mm=0.01, seed=0)\n"
        "hpk.diagnose(r, d, max_causes=1)\n"
        "print('sympy' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False"

"""Shared test helpers: pose/quaternion comparisons, gradient checks, batch shapes, and the
per-run seed of the hidden-effect tests.

Comparisons are computed here from first principles (not with ``hybrid_pk.geometry``),
so a bug in the library cannot hide itself in the check.
"""

from __future__ import annotations

import math
import os
import signal
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from hybrid_pk.hybrid.builder import HybridSettings
from hybrid_pk.simulate.unmodelled import smooth_field as smooth_field

# Leading batch shapes every batched function is tested with (jaxlie style).
BATCH_SHAPES: list[tuple[int, ...]] = [(), (1,), (3, 2)]

# Hidden-effect tests draw the effect, joint and magnitude from this seed. It is pinned,
# so that a failure in CI is the same failure on every rerun and gets investigated, not
# redrawn; ``HYBRID_PK_TEST_SEED=N`` runs draw N (pytest's header prints the seed, and every
# failure message of those tests names it). New draws are the sweep's job:
# ``python -m pytest -m sweep`` (tests/test_seed_sweep.py).
PINNED_SEED = 12345  # an arbitrary fixed draw, chosen before any run of it was seen
RUN_SEED: int = int(os.environ.get("HYBRID_PK_TEST_SEED", PINNED_SEED))


def run_rng(salt: str) -> np.random.Generator:
    """A generator seeded by ``RUN_SEED`` and ``salt`` (one independent stream per test)."""
    return np.random.default_rng([RUN_SEED, sum(map(ord, salt))])


def _f64(x: Tensor | np.ndarray) -> Tensor:
    return torch.as_tensor(x).detach().to("cpu", torch.float64)


def _worst(err: Tensor) -> str:
    """Where and how large the largest entry of ``err (*B,)`` is."""
    if err.ndim == 0:
        return f"{err.item():.3e}"
    flat = int(err.argmax())
    index = tuple(int(i) for i in np.unravel_index(flat, tuple(err.shape)))
    return f"{err.reshape(-1)[flat].item():.3e} at batch index {index}"


def rotation_distance(R_a: Tensor | np.ndarray, R_b: Tensor | np.ndarray) -> Tensor:
    """Angle [rad] of ``R_a^T R_b`` for rotations ``(*B, 3, 3)``, float64, shape ``(*B,)``.

    Uses ``||R_a - R_b||_F = 2 sqrt(2) sin(theta / 2)``: accurate for small angles,
    which is where tolerances live.
    """
    frob = torch.linalg.matrix_norm(_f64(R_a) - _f64(R_b))
    return 2 * torch.asin((frob / (2 * math.sqrt(2))).clamp(max=1.0))


def assert_transforms_close(
    T_a: Tensor | np.ndarray,
    T_b: Tensor | np.ndarray,
    atol_pos: float,
    atol_rot: float,
) -> None:
    """Assert two batches of rigid transforms ``(*B, 4, 4)`` are the same poses.

    Args:
        T_a: transforms; translations in the unit of ``atol_pos``.
        T_b: transforms with the same shape.
        atol_pos: largest allowed translation distance (unit of the translations).
        atol_rot: largest allowed rotation angle between the two [rad].
    """
    A, B = _f64(T_a), _f64(T_b)
    assert A.shape == B.shape, f"shapes differ: {tuple(A.shape)} vs {tuple(B.shape)}"
    assert A.shape[-2:] == (4, 4), f"expected (*B, 4, 4) transforms, got {tuple(A.shape)}"
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    for name, T in (("T_a", A), ("T_b", B)):
        off = (T[..., 3, :] - bottom).abs().amax(-1)
        assert bool((off == 0).all()), f"{name}: bottom row is not [0, 0, 0, 1]: {_worst(off)}"
    dpos = torch.linalg.vector_norm(A[..., :3, 3] - B[..., :3, 3], dim=-1)
    assert bool((dpos <= atol_pos).all()), (
        f"translations differ by {_worst(dpos)} > atol_pos={atol_pos:.1e}"
    )
    drot = rotation_distance(A[..., :3, :3], B[..., :3, :3])
    assert bool((drot <= atol_rot).all()), (
        f"rotations differ by {_worst(drot)} rad > atol_rot={atol_rot:.1e}"
    )


def assert_quats_close(q_a: Tensor | np.ndarray, q_b: Tensor | np.ndarray, atol: float) -> None:
    """Assert unit quaternions ``(*B, 4)`` are the same rotations.

    ``q`` and ``-q`` are the same rotation (double cover), so the distance is
    ``min(||q_a - q_b||, ||q_a + q_b||)``. Component order does not matter as long as it
    is the same for both.
    """
    a, b = _f64(q_a), _f64(q_b)
    assert a.shape == b.shape, f"shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}"
    assert a.shape[-1] == 4, f"expected (*B, 4) quaternions, got {tuple(a.shape)}"
    dist = torch.minimum(
        torch.linalg.vector_norm(a - b, dim=-1), torch.linalg.vector_norm(a + b, dim=-1)
    )
    assert bool((dist <= atol).all()), f"quaternions differ by {_worst(dist)} > atol={atol:.1e}"


def check_gradients(
    fn: Callable[..., Tensor | tuple[Tensor, ...]],
    *inputs: object,
    eps: float = 1e-6,
    atol: float = 1e-6,
    rtol: float = 1e-4,
    gradgrad: bool = False,
    require_all_used: bool = True,
) -> None:
    """Check autograd of ``fn`` against finite differences, in float64.

    Floating-point tensor inputs are cloned to float64 leaves that require grad (so
    ``fn``'s own tensors, e.g. module parameters, must be float64 too); other inputs
    are passed as they are. Raises on the first mismatch (``raise_exception=True``).

    Args:
        fn: function of ``inputs`` returning a tensor or a tuple of tensors.
        *inputs: arguments of ``fn``.
        eps: finite-difference step.
        atol: absolute tolerance of the Jacobian comparison.
        rtol: relative tolerance of the Jacobian comparison.
        gradgrad: also check second derivatives with ``gradgradcheck``.
        require_all_used: also fail when an input gets no gradient at all (unused or
            detached inside ``fn``), which plain ``gradcheck`` accepts when the finite
            differences are zero too. Turn off for inputs that legitimately have zero
            gradient at the test point.
    """
    args = tuple(
        x.detach().to(torch.float64).clone().requires_grad_(True)
        if isinstance(x, Tensor) and x.is_floating_point()
        else x
        for x in inputs
    )
    differentiable = [i for i, x in enumerate(args) if isinstance(x, Tensor) and x.requires_grad]
    assert differentiable, "check_gradients: no floating-point tensor among the inputs"
    torch.autograd.gradcheck(fn, args, eps=eps, atol=atol, rtol=rtol, raise_exception=True)
    if gradgrad:
        torch.autograd.gradgradcheck(fn, args, eps=eps, atol=atol, rtol=rtol, raise_exception=True)
    if require_all_used:
        out = fn(*args)
        outs = out if isinstance(out, tuple) else (out,)
        gen = torch.Generator().manual_seed(0)
        # A random weighting of the outputs, so that gradients cannot cancel by symmetry.
        total = sum((o * torch.rand(o.shape, generator=gen, dtype=o.dtype)).sum() for o in outs)
        grads = torch.autograd.grad(total, [args[i] for i in differentiable], allow_unused=True)
        for i, g in zip(differentiable, grads, strict=True):
            where = f"check_gradients: input {i} (shape {tuple(args[i].shape)})"
            assert g is not None, f"{where} is not used by fn or is detached inside it"
            assert bool((g != 0).any()), f"{where} gets an all-zero gradient"


def is_periodic(kind: str) -> bool:
    """Is effect ``kind`` a periodic joint-angle error (an eccentricity or a cyclic error
    of some order)? Those fit each other's shapes closely, so tests that compare two
    diagnoses, or a found amplitude with the truth, treat them alike. (A classification
    of the library's own effect classes, not a computed quantity.)"""
    from hybrid_pk.effects import EFFECTS
    from hybrid_pk.effects.joint import JointEccentricity

    return issubclass(EFFECTS[kind], JointEccentricity)


# Tiny networks for tests of how hybrid stages combine (not of what they learn).
SMALL_STAGES = HybridSettings(
    position_net="mlp:8x2",
    orientation_net="mlp:8x2",
    refine_net="mlp:8x2",
    local_net="mlp:4x1",
    zero_init=False,
)


def middle_q(robot, n: int, seed: int, share: float = 1 / 3) -> Tensor:
    """``n`` joint vectors of ``robot`` from the middle ``share`` of each joint's range."""
    lo, hi = robot.joint_limits
    mid = (lo + hi) / 2
    return mid + (robot.sample_q(n, torch.Generator().manual_seed(seed)) - mid) * share


def banded_poses(robot, rng, orders: tuple[int, int], band: float):
    """The poses of a cyclic campaign whose order the rows may not resolve: joint ``j``
    (the shoulder lift or the elbow), an order drawn in ``orders``, 1,500-2,500 poses
    with joint ``j`` held in ``band`` rad about a random angle in [-2, 2] rad, and a
    noise level of 0.01-0.03 mm. Returns ``(j, order, noise_mm, q)``."""
    j = int(rng.choice([1, 2]))
    order = int(rng.integers(*orders))
    n = int(rng.integers(1500, 2500))
    noise = float(rng.uniform(0.01, 0.03))
    g = torch.Generator().manual_seed(int(rng.integers(1 << 30)))
    q = robot.sample_q(n, g)
    centre = float(rng.uniform(-2.0, 2.0))
    q[:, j] = centre + band * (torch.rand(n, generator=g, dtype=q.dtype) - 0.5)
    return j, order, noise, q


def cyclic_campaign(robot, q: Tensor, j: int, order: int, levels, noise_mm: float, rng):
    """A campaign of ``robot`` at poses ``q`` with a cyclic error of ``order`` per turn at
    joint ``j``, moving the point by an RMS displacement of ``levels`` (a range, drawn
    from ``rng``) noise levels of ``noise_mm`` (3-D noise sqrt(3) sigma: the amplitude
    over the joint's median lever arm), at a random phase. Returns ``(data, label,
    amplitude [rad])``."""
    from hybrid_pk.effects import make_effect
    from hybrid_pk.simulate import simulate_campaign

    with torch.no_grad():  # the joint's median lever arm [m/rad]
        dq = torch.zeros_like(q)
        dq[:, j] = 1e-6
        lever = float(((robot.fk(q + dq) - robot.fk(q))[:, :3, 3] / 1e-6).norm(dim=1).median())
    amp = float(rng.uniform(*levels)) * noise_mm * 1e-3 * math.sqrt(2) / lever
    phase = float(rng.uniform(0, 2 * math.pi))
    label = f"cyclic_error_{order}:{robot.joint_names[j]}"
    effect = make_effect(robot, label, [amp * math.cos(phase), amp * math.sin(phase)])
    data, _ = simulate_campaign(
        robot, None, [effect], poses=q, noise_mm=noise_mm, noise_deg=noise_mm / 10,
        seed=int(rng.integers(1 << 30)),
    )  # fmt: skip
    return data, label, amp


def default_sigint() -> None:
    """``preexec_fn`` of a child that a test interrupts: SIGINT at its default, as a
    terminal's foreground command has it. A shell starts a background job (``pytest ...
    &``) with SIGINT ignored, and a child would inherit that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)

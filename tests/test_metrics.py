"""Tests of hybrid_pk.evaluation.metrics: eq. 1/eq. 2 metrics, residuals, evaluate JSON."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from hybrid_pk.evaluation.metrics import (
    ErrorStats,
    PoseError,
    error_stats,
    evaluate_json,
    ik_cost,
    pose_error,
    pose_residual,
    position_error_mm,
)
from hybrid_pk.geometry import so3_exp, transform, transform_inverse
from tests.helpers import BATCH_SHAPES, check_gradients

DTYPES = [torch.float32, torch.float64]
AXIS = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])


def _random_poses(shape: tuple[int, ...], seed: int) -> torch.Tensor:
    """Poses ``(*shape, 4, 4)`` float64, positions within about 1 m of the origin."""
    gen = torch.Generator().manual_seed(seed)
    w = 2 * torch.rand(*shape, 3, generator=gen, dtype=torch.float64) - 1
    p = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    return transform(so3_exp(2.5 * w), p)


def _rot(angle_deg: float, axis: np.ndarray = AXIS) -> torch.Tensor:
    return torch.as_tensor(Rotation.from_rotvec(math.radians(angle_deg) * axis).as_matrix())


def _perturbed(
    T: torch.Tensor, angle_deg: float, shift_m: tuple[float, float, float]
) -> torch.Tensor:
    """``T`` rotated by ``angle_deg`` about AXIS (in the base frame, about its own point)
    and moved by ``shift_m``."""
    R = _rot(angle_deg).to(T.dtype) @ T[..., :3, :3]
    return transform(R, T[..., :3, 3] + torch.tensor(shift_m, dtype=T.dtype))


# --- eq. 1: pose_error ------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_pure_translation_of_1mm(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    T_model = _random_poses(shape, seed=0)
    T_measured = _perturbed(T_model, 0.0, (0.0, 0.0006, -0.0008))  # |shift| = 1 mm
    err = pose_error(T_measured.to(dtype), T_model.to(dtype))
    assert isinstance(err, PoseError)
    assert err.position_mm.shape == shape
    assert err.orientation_deg.shape == shape
    assert err.position_mm.dtype == dtype
    atol = {torch.float32: 1e-4, torch.float64: 1e-10}[dtype]
    torch.testing.assert_close(err.position_mm, torch.ones(shape, dtype=dtype), atol=atol, rtol=0)
    atol_deg = {torch.float32: 1e-4, torch.float64: 1e-12}[dtype]
    torch.testing.assert_close(
        err.orientation_deg, torch.zeros(shape, dtype=dtype), atol=atol_deg, rtol=0
    )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_pure_rotation_of_half_a_degree(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    T_model = _random_poses(shape, seed=1)
    T_measured = _perturbed(T_model, 0.5, (0.0, 0.0, 0.0))
    err = pose_error(T_measured.to(dtype), T_model.to(dtype))
    atol = {torch.float32: 1e-4, torch.float64: 1e-10}[dtype]
    torch.testing.assert_close(
        err.orientation_deg, torch.full(shape, 0.5, dtype=dtype), atol=atol, rtol=0
    )
    torch.testing.assert_close(err.position_mm, torch.zeros(shape, dtype=dtype), atol=atol, rtol=0)


def test_position_error_is_point_distance_not_lever_arm() -> None:
    # A point 1 m from the base, measured with 0.5 deg orientation error and no position
    # error. The literal translation of T_meas T_model^-1 is p - R_diff p, about 8.7 mm;
    # the reported position error is the point distance, 0 mm.
    T_model = transform(torch.eye(3, dtype=torch.float64), torch.tensor([1.0, 0.0, 0.0]))
    T_measured = _perturbed(T_model, 0.5, (0.0, 0.0, 0.0))
    literal_mm = 1000 * (T_measured @ transform_inverse(T_model))[:3, 3].norm()
    assert literal_mm > 5.0
    err = pose_error(T_measured, T_model)
    assert err.position_mm.item() == pytest.approx(0.0, abs=1e-12)
    # ... which is the translation norm of T_model^-1 T_meas, whatever the poses.
    T_model, T_measured = _random_poses((5,), seed=2), _random_poses((5,), seed=3)
    body_mm = 1000 * (transform_inverse(T_model) @ T_measured)[..., :3, 3].norm(dim=-1)
    torch.testing.assert_close(pose_error(T_measured, T_model).position_mm, body_mm)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rotation_of_179_9_degrees(dtype: torch.dtype) -> None:
    T_model = _random_poses((4,), seed=4)
    T_measured = _perturbed(T_model, 179.9, (0.0, 0.0, 0.0))
    err = pose_error(T_measured.to(dtype), T_model.to(dtype))
    atol = {torch.float32: 1e-3, torch.float64: 1e-9}[dtype]
    torch.testing.assert_close(
        err.orientation_deg, torch.full((4,), 179.9, dtype=dtype), atol=atol, rtol=0
    )


def test_rotation_of_exactly_180_degrees() -> None:
    T_model = torch.eye(4, dtype=torch.float64)
    R = 2 * torch.outer(torch.as_tensor(AXIS), torch.as_tensor(AXIS)) - torch.eye(3).double()
    err = pose_error(transform(R, torch.zeros(3, dtype=torch.float64)), T_model)
    assert err.orientation_deg.item() == pytest.approx(180.0, abs=1e-12)


def test_pose_error_is_symmetric_and_broadcasts() -> None:
    T_a, T_b = _random_poses((3, 2), seed=5), _random_poses((), seed=6)
    ab, ba = pose_error(T_a, T_b), pose_error(T_b, T_a)
    assert ab.position_mm.shape == (3, 2)
    torch.testing.assert_close(ab.position_mm, ba.position_mm)
    torch.testing.assert_close(ab.orientation_deg, ba.orientation_deg)
    expected_deg = [
        math.degrees(Rotation.from_matrix((T_a[i, j, :3, :3] @ T_b[:3, :3].T).numpy()).magnitude())
        for i in range(3)
        for j in range(2)
    ]
    torch.testing.assert_close(
        ab.orientation_deg.reshape(-1), torch.tensor(expected_deg, dtype=torch.float64)
    )


def test_position_error_mm() -> None:
    p = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    q = torch.tensor([[0.003, 0.004, 0.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    torch.testing.assert_close(position_error_mm(p, q), torch.tensor([5.0, 0.0]).double())


def test_shape_errors_are_reported() -> None:
    with pytest.raises(ValueError, match=r"T_model: expected homogeneous transforms"):
        pose_error(torch.eye(4), torch.eye(3))
    with pytest.raises(ValueError, match=r"p_measured: expected points \(\*B, 3\), got \(4,\)"):
        position_error_mm(torch.zeros(4), torch.zeros(3))


# --- residual ---------------------------------------------------------------------------


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_pose_residual_hand_case(shape: tuple[int, ...]) -> None:
    T_model = _random_poses(shape, seed=7)
    T_measured = _perturbed(T_model, 0.5, (0.001, -0.002, 0.0))
    r = pose_residual(T_measured, T_model)
    assert r.shape == (*shape, 6)
    expected = torch.tensor([1.0, -2.0, 0.0, *(math.radians(0.5) * AXIS)], dtype=torch.float64)
    torch.testing.assert_close(r, expected.expand(*shape, 6), atol=1e-10, rtol=0)
    err = pose_error(T_measured, T_model)
    torch.testing.assert_close(r[..., :3].norm(dim=-1), err.position_mm)
    torch.testing.assert_close(torch.rad2deg(r[..., 3:].norm(dim=-1)), err.orientation_deg)


# --- eq. 2: ik_cost ---------------------------------------------------------------------


def test_ik_cost_hand_computed() -> None:
    # T_a = I; T_b = Rz(90 deg) at (1, 2, 0) mm. Rotation part of T_a - T_b is
    # [[1, 1, 0], [-1, 1, 0], [0, 0, 0]] -> 4; translation (-1, -2, 0) mm -> 5.
    T_a = torch.eye(4, dtype=torch.float64)
    R_b = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    T_b = transform(R_b, torch.tensor([0.001, 0.002, 0.0], dtype=torch.float64))
    assert ik_cost(T_a, T_b).item() == pytest.approx(9.0, abs=1e-12)
    assert ik_cost(T_b, T_a).item() == pytest.approx(9.0, abs=1e-12)
    assert ik_cost(T_a, T_b, translation_scale=1.0).item() == pytest.approx(4.000005, abs=1e-12)
    assert ik_cost(T_a, T_a).item() == 0.0


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_ik_cost_matches_elementwise_definition(shape: tuple[int, ...]) -> None:
    T_a, T_b = _random_poses(shape, seed=8), _random_poses(shape, seed=9)
    A, B = T_a.clone(), T_b.clone()
    A[..., :3, 3] *= 1000
    B[..., :3, 3] *= 1000
    e = torch.ones(4, 1, dtype=torch.float64)
    expected = (e.mT @ (A - B) ** 2 @ e)[..., 0, 0]
    cost = ik_cost(T_a, T_b)
    assert cost.shape == shape
    torch.testing.assert_close(cost, expected)


# --- gradients --------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_gradients_finite_at_zero_error(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    T = _random_poses(shape, seed=10).to(dtype)
    T_measured = T.clone().requires_grad_(True)
    T_model = T.clone().requires_grad_(True)
    err = pose_error(T_measured, T_model)
    assert (err.position_mm == 0).all()
    outputs = {
        "position_mm": err.position_mm,
        "orientation_deg": err.orientation_deg,
        "pose_residual": pose_residual(T_measured, T_model),
        "ik_cost": ik_cost(T_measured, T_model),
    }
    for name, out in outputs.items():
        grads = torch.autograd.grad(out.sum(), (T_measured, T_model), retain_graph=True)
        for g in grads:
            assert torch.isfinite(g).all(), name
    # The residual is smooth at zero: its Jacobian is +-1000 (mm) on the translations.
    (g,) = torch.autograd.grad(pose_residual(T_measured, T_model)[..., 0].sum(), T_model)
    assert torch.equal(g[..., 0, 3], torch.full(shape, -1000.0, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradients_finite_at_180_degrees(dtype: torch.dtype) -> None:
    R = 2 * torch.outer(torch.as_tensor(AXIS), torch.as_tensor(AXIS)) - torch.eye(3).double()
    T_measured = transform(R, torch.tensor([0.1, 0.2, 0.3])).to(dtype).requires_grad_(True)
    T_model = torch.eye(4, dtype=dtype, requires_grad=True)
    for out in (
        pose_error(T_measured, T_model).orientation_deg,
        pose_residual(T_measured, T_model),
    ):
        for g in torch.autograd.grad(out.sum(), (T_measured, T_model)):
            assert torch.isfinite(g).all()


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_metrics_gradcheck(shape: tuple[int, ...]) -> None:
    T_a, T_b = _random_poses(shape, seed=11), _random_poses(shape, seed=12)
    check_gradients(lambda a, b: pose_error(a, b).position_mm, T_a, T_b)
    check_gradients(lambda a, b: pose_error(a, b).orientation_deg, T_a, T_b)
    check_gradients(pose_residual, T_a, T_b)
    check_gradients(lambda a, b: ik_cost(a, b, translation_scale=1.0), T_a, T_b)
    # Costs ~1e6 mm^2: finite differences carry ~1e-4 of round-off.
    check_gradients(ik_cost, T_a, T_b, atol=1e-3)


# --- summaries and JSON -----------------------------------------------------------------


def test_error_stats_on_known_vector() -> None:
    values = np.arange(1.0, 21.0)  # 1 .. 20
    stats = error_stats(torch.as_tensor(values, dtype=torch.float32))
    assert stats.mean == pytest.approx(10.5)
    assert stats.rms == pytest.approx(math.sqrt(143.5))  # sum of squares 2870 / 20
    assert stats.p95 == pytest.approx(19.05)  # linear interpolation at rank 0.95 * 19
    assert stats.max == 20.0
    gen = np.random.default_rng(0)
    x = gen.gamma(2.0, 0.1, size=(50, 3))
    stats = error_stats(x)
    assert stats.mean == pytest.approx(np.mean(x))
    assert stats.rms == pytest.approx(np.sqrt(np.mean(x**2)))
    assert stats.p95 == pytest.approx(np.percentile(x, 95))
    assert stats.max == np.max(x)


def test_error_stats_to_dict_and_immutability() -> None:
    stats = error_stats([1.0, 2.0, 2.0])
    d = stats.to_dict()
    assert list(d) == ["mean", "rms", "p95", "max"]
    assert all(type(v) is float for v in d.values())
    with pytest.raises(dataclasses.FrozenInstanceError):
        stats.mean = 0.0  # type: ignore[misc]


def test_error_stats_rejects_empty_and_non_finite() -> None:
    with pytest.raises(ValueError, match="at least one value"):
        error_stats([])
    with pytest.raises(
        ValueError, match=r"position_mm: .*1 of 3 not finite \(first at flat index 1"
    ):
        error_stats(torch.tensor([0.1, float("nan"), 0.3]), name="position_mm")


def test_evaluate_json_full_pose() -> None:
    pos = torch.tensor([0.1, 0.2, 0.3, 0.4])
    ori = np.array([0.01, 0.02, 0.03, 0.04])
    out = evaluate_json(4, pos, ori)
    assert list(out) == ["n", "position_mm", "orientation_deg"]
    assert out["n"] == 4
    assert type(out["n"]) is int
    assert out["position_mm"] == error_stats(pos).to_dict()
    assert out["orientation_deg"] == error_stats(ori).to_dict()
    assert json.loads(json.dumps(out)) == out


def test_evaluate_json_position_only_has_null_orientation() -> None:
    out = evaluate_json(3, error_stats([1.0, 2.0, 3.0]), None)
    assert out["orientation_deg"] is None
    assert set(out["position_mm"]) == {"mean", "rms", "p95", "max"}
    assert '"orientation_deg": null' in json.dumps(out)
    assert evaluate_json(3, [1.0, 2.0, 3.0]) == out


def test_evaluate_json_rejects_inconsistent_n() -> None:
    with pytest.raises(ValueError, match=r"position_mm: expected n = 5 values, got 4"):
        evaluate_json(5, np.ones(4))
    with pytest.raises(ValueError, match=r"orientation_deg: expected n = 4 values, got 3"):
        evaluate_json(4, np.ones(4), np.ones(3))
    with pytest.raises(ValueError, match="positive integer"):
        evaluate_json(0, ErrorStats(0.0, 0.0, 0.0, 0.0))

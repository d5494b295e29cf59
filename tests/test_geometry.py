"""Tests of hybrid_pk.geometry, with scipy's Rotation as independent oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from torch.autograd.gradcheck import GradcheckError

from hybrid_pk.geometry import (
    matrix_to_quat,
    matrix_to_rpy,
    nearest_rotation,
    quat_to_matrix,
    rotation_angle,
    rpy_to_matrix,
    skew,
    so3_exp,
    so3_log,
    transform,
    transform_inverse,
)
from tests.helpers import (
    BATCH_SHAPES,
    assert_quats_close,
    assert_transforms_close,
    check_gradients,
    run_rng,
)

DTYPES = [torch.float32, torch.float64]
# Loose enough for float32 round-off through a few 3x3 products, tight for float64.
TOL = {torch.float32: 2e-6, torch.float64: 1e-12}

# Unit axes, several with negative components, for the angle-pi corner cases.
AXES = [
    (1.0, 0.0, 0.0),
    (0.0, -1.0, 0.0),
    (0.0, 0.0, 1.0),
    (1.0, -1.0, 0.0),
    (-1.0, 2.0, -2.0),
    (1.0, 1.0, 1.0),
    (-0.6, 0.0, -0.8),
    (0.3, -0.2, 0.9),
]


def _unit(axis: tuple[float, float, float]) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    return a / np.linalg.norm(a)


def _random_rotvecs(shape: tuple[int, ...], seed: int, max_angle: float = 3.0) -> torch.Tensor:
    """Rotation vectors ``(*shape, 3)`` float64 with random axes and angles < max_angle."""
    gen = torch.Generator().manual_seed(seed)
    axis = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = max_angle * torch.rand(*shape, 1, generator=gen, dtype=torch.float64)
    return axis * angle


def _scipy_matrix(rotvec: torch.Tensor) -> np.ndarray:
    flat = rotvec.detach().to(torch.float64).reshape(-1, 3).numpy()
    return Rotation.from_rotvec(flat).as_matrix().reshape(*rotvec.shape[:-1], 3, 3)


def _rotation_pi(axis: np.ndarray) -> np.ndarray:
    """Exactly symmetric rotation of pi about a unit axis: ``2 a a^T - I``."""
    return 2 * np.outer(axis, axis) - np.eye(3)


def test_skew_is_cross_product() -> None:
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(3, 2, 3, generator=gen, dtype=torch.float64)
    b = torch.randn(3, 2, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close((skew(a) @ b[..., None])[..., 0], torch.linalg.cross(a, b))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_so3_exp_matches_scipy(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    w = _random_rotvecs(shape, seed=1)
    R = so3_exp(w.to(dtype))
    assert R.shape == (*shape, 3, 3)
    assert R.dtype == dtype
    expected = torch.as_tensor(_scipy_matrix(w), dtype=dtype)
    torch.testing.assert_close(R, expected, atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_so3_log_matches_scipy(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    # Angles up to 3.1 rad cover both the regular and the near-pi branch of so3_log.
    w = _random_rotvecs(shape, seed=2, max_angle=3.1)
    R = torch.as_tensor(_scipy_matrix(w), dtype=dtype)
    w_log = so3_log(R)
    assert w_log.shape == (*shape, 3)
    expected = Rotation.from_matrix(_scipy_matrix(w).reshape(-1, 3, 3)).as_rotvec()
    torch.testing.assert_close(
        w_log,
        torch.as_tensor(expected.reshape(*shape, 3), dtype=dtype),
        atol=10 * TOL[dtype],
        rtol=0,
    )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_so3_exp_log_round_trip_random(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    w = _random_rotvecs(shape, seed=3, max_angle=3.1).to(dtype)
    torch.testing.assert_close(so3_log(so3_exp(w)), w, atol=10 * TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", [1e-9, 1e-6, 1e-4, 1.01e-4])
def test_so3_exp_log_round_trip_near_zero(angle: float, dtype: torch.dtype) -> None:
    w = torch.as_tensor(np.stack([angle * _unit(a) for a in AXES]), dtype=dtype)
    R = so3_exp(w)
    torch.testing.assert_close(
        R, torch.as_tensor(_scipy_matrix(w), dtype=dtype), atol=TOL[dtype], rtol=0
    )
    # Relative accuracy: tiny rotations must not be flushed to zero.
    rtol = {torch.float32: 1e-5, torch.float64: 1e-10}[dtype]
    torch.testing.assert_close(so3_log(R), w, atol=0, rtol=rtol)
    torch.testing.assert_close(
        rotation_angle(R), torch.full((len(AXES),), angle, dtype=dtype), atol=0, rtol=rtol
    )


def test_so3_log_of_identity_is_zero() -> None:
    for shape in BATCH_SHAPES:
        eye = torch.eye(3, dtype=torch.float64).expand(*shape, 3, 3)
        assert torch.equal(so3_log(eye), torch.zeros(*shape, 3, dtype=torch.float64))
        assert torch.equal(rotation_angle(eye), torch.zeros(shape, dtype=torch.float64))


@pytest.mark.parametrize("gap", [1e-9, 1e-6, 1e-3, 0.3])
def test_so3_exp_log_round_trip_near_pi(gap: float) -> None:
    angle = math.pi - gap
    w = torch.as_tensor(np.stack([angle * _unit(a) for a in AXES]))
    R = so3_exp(w)
    torch.testing.assert_close(R, torch.as_tensor(_scipy_matrix(w)), atol=1e-14, rtol=0)
    # Below pi the rotation vector is unique: the sign of the axis must come out right.
    torch.testing.assert_close(so3_log(R), w, atol=1e-12, rtol=0)
    torch.testing.assert_close(
        rotation_angle(R), torch.full((len(AXES),), angle, dtype=torch.float64), atol=1e-14, rtol=0
    )


def test_so3_log_near_pi_float32() -> None:
    # pi - 1e-9 is pi in float32; check the rotation, whose log is then defined up to sign.
    for gap in (1e-9, 1e-6, 1e-3):
        w = torch.as_tensor(np.stack([(math.pi - gap) * _unit(a) for a in AXES]))
        R32 = so3_exp(w).float()
        w_log = so3_log(R32)
        assert torch.isfinite(w_log).all()
        assert_transforms_close(
            transform(so3_exp(w_log), torch.zeros(3)),
            transform(R32, torch.zeros(3)),
            atol_pos=0,
            atol_rot=2e-6,
        )
        torch.testing.assert_close(
            w_log.norm(dim=-1), torch.full((len(AXES),), math.pi - gap), atol=1e-6, rtol=0
        )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("axis", AXES)
def test_so3_log_exactly_pi(axis: tuple[float, float, float], dtype: torch.dtype) -> None:
    a = _unit(axis)
    R = torch.as_tensor(_rotation_pi(a), dtype=dtype)
    w = so3_log(R)
    assert torch.isfinite(w).all()
    # Angle pi: +pi a and -pi a are the same rotation; accept either.
    expected = torch.as_tensor(math.pi * a, dtype=dtype)
    err = min((w - expected).abs().max().item(), (w + expected).abs().max().item())
    assert err < 10 * TOL[dtype]
    assert abs(rotation_angle(R).item() - math.pi) < 10 * TOL[dtype]
    torch.testing.assert_close(so3_exp(w), R, atol=10 * TOL[dtype], rtol=0)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_rotation_angle_matches_scipy(shape: tuple[int, ...]) -> None:
    w = _random_rotvecs(shape, seed=4, max_angle=math.pi)
    R = torch.as_tensor(_scipy_matrix(w))
    expected = Rotation.from_matrix(R.reshape(-1, 3, 3).numpy()).magnitude().reshape(shape)
    torch.testing.assert_close(rotation_angle(R), torch.as_tensor(expected), atol=1e-12, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_rpy_to_matrix_matches_scipy_extrinsic_xyz(
    shape: tuple[int, ...], dtype: torch.dtype
) -> None:
    gen = torch.Generator().manual_seed(5)
    rpy = (torch.rand(*shape, 3, generator=gen, dtype=torch.float64) - 0.5) * torch.tensor(
        [2 * math.pi, math.pi, 2 * math.pi], dtype=torch.float64
    )
    # scipy lowercase "xyz" = extrinsic (fixed) axes: Rz(yaw) Ry(pitch) Rx(roll), as URDF.
    expected = Rotation.from_euler("xyz", rpy.reshape(-1, 3).numpy()).as_matrix()
    R = rpy_to_matrix(rpy.to(dtype))
    assert R.shape == (*shape, 3, 3)
    torch.testing.assert_close(
        R, torch.as_tensor(expected.reshape(*shape, 3, 3), dtype=dtype), atol=TOL[dtype], rtol=0
    )
    torch.testing.assert_close(matrix_to_rpy(R), rpy.to(dtype), atol=10 * TOL[dtype], rtol=0)


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_matrix_to_rpy_round_trips_at_gimbal_lock(pitch: float) -> None:
    # scipy's matrix has rounding noise where R[2, 1], R[2, 2] should be 0; the old
    # atan2(R[2, 1], R[2, 2]) turned that noise into a wrong roll (0.02 rad off).
    R = torch.as_tensor(Rotation.from_euler("xyz", [0.3, pitch, 0.2]).as_matrix())
    rpy = matrix_to_rpy(R)
    assert abs(rpy[1].item() - pitch) < 1e-7
    torch.testing.assert_close(rpy_to_matrix(rpy), R, atol=1e-12, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_matrix_to_quat_matches_scipy(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    w = _random_rotvecs(shape, seed=6, max_angle=math.pi)
    R = torch.as_tensor(_scipy_matrix(w), dtype=dtype)
    q = matrix_to_quat(R)
    assert q.shape == (*shape, 4)
    assert (q[..., 0] >= 0).all()
    xyzw = Rotation.from_matrix(_scipy_matrix(w).reshape(-1, 3, 3)).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1).reshape(*shape, 4)
    assert_quats_close(q, wxyz, atol=10 * TOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_quat_round_trip_with_double_cover(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(7)
    q = torch.randn(*shape, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    R = quat_to_matrix(q.to(dtype))
    # -q is the same rotation.
    torch.testing.assert_close(quat_to_matrix(-q.to(dtype)), R, atol=TOL[dtype], rtol=0)
    xyzw = np.concatenate([q[..., 1:].numpy(), q[..., :1].numpy()], axis=-1).reshape(-1, 4)
    expected = Rotation.from_quat(xyzw).as_matrix().reshape(*shape, 3, 3)
    torch.testing.assert_close(R, torch.as_tensor(expected, dtype=dtype), atol=TOL[dtype], rtol=0)
    q_back = matrix_to_quat(R)
    assert (q_back[..., 0] >= 0).all()
    assert_quats_close(q_back, q, atol=10 * TOL[dtype])
    # The canonical sign: equal to q where w > 0, to -q where w < 0.
    torch.testing.assert_close(
        q_back, torch.where(q[..., :1] < 0, -q, q).to(dtype), atol=10 * TOL[dtype], rtol=0
    )


@pytest.mark.parametrize("axis", AXES)
def test_matrix_to_quat_half_turn(axis: tuple[float, float, float]) -> None:
    a = _unit(axis)
    q = matrix_to_quat(torch.as_tensor(_rotation_pi(a)))
    assert_quats_close(q, np.concatenate([[0.0], a]), atol=1e-14)


def test_quat_to_matrix_normalises() -> None:
    q = torch.tensor([2.0, 0.0, 0.0, 2.0], dtype=torch.float64)  # 90 deg about z, norm 2.8
    expected = torch.tensor(
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    torch.testing.assert_close(quat_to_matrix(q), expected, atol=1e-15, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_transform_inverse(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(8)
    R = torch.as_tensor(_scipy_matrix(_random_rotvecs(shape, seed=9)), dtype=dtype)
    p = torch.randn(*shape, 3, generator=gen, dtype=torch.float64).to(dtype)
    T = transform(R, p)
    assert T.shape == (*shape, 4, 4)
    assert torch.equal(T[..., :3, :3], R)
    assert torch.equal(T[..., :3, 3], p)
    assert torch.equal(T[..., 3, :], torch.tensor([0, 0, 0, 1], dtype=dtype).expand(*shape, 4))
    T_inv = transform_inverse(T)
    torch.testing.assert_close(T_inv, torch.linalg.inv(T), atol=10 * TOL[dtype], rtol=0)
    eye = torch.eye(4, dtype=dtype).expand(*shape, 4, 4)
    assert_transforms_close(T @ T_inv, eye, atol_pos=10 * TOL[dtype], atol_rot=10 * TOL[dtype])
    assert_transforms_close(T_inv @ T, eye, atol_pos=10 * TOL[dtype], atol_rot=10 * TOL[dtype])


def test_transform_broadcasts_rotation_and_translation() -> None:
    R = torch.eye(3, dtype=torch.float64)
    p = torch.arange(6, dtype=torch.float64).reshape(2, 3)
    T = transform(R, p)
    assert T.shape == (2, 4, 4)
    assert torch.equal(T[:, :3, 3], p)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_nearest_rotation_matches_scipy(shape: tuple[int, ...]) -> None:
    """Noisy rotations: scipy's ``from_matrix`` (Bar-Itzhack's quaternion method, the
    nearest orthogonal matrix with det +1) is the oracle."""
    gen = torch.Generator().manual_seed(21)
    R = so3_exp(_random_rotvecs(shape, seed=20))
    M = R + 0.2 * torch.randn(*shape, 3, 3, generator=gen, dtype=torch.float64)
    expected = Rotation.from_matrix(M.reshape(-1, 3, 3).numpy()).as_matrix()
    got = nearest_rotation(M)
    assert got.shape == (*shape, 3, 3)
    np.testing.assert_allclose(got.reshape(-1, 3, 3).numpy(), expected, atol=1e-12)


def test_nearest_rotation_keeps_rotations_and_removes_stretch() -> None:
    R = so3_exp(_random_rotvecs((5,), seed=22))
    torch.testing.assert_close(nearest_rotation(R), R, atol=1e-13, rtol=0)
    S = torch.diag(torch.tensor([3.0, 0.5, 1.5], dtype=torch.float64))  # symmetric > 0
    torch.testing.assert_close(nearest_rotation(R @ S), R, atol=1e-13, rtol=0)
    assert nearest_rotation(R.float()).dtype == torch.float32


def test_nearest_rotation_of_a_reflection_is_a_local_optimum() -> None:
    """det(M) < 0 (scipy refuses it): still a rotation, and no rotation near it is closer."""
    gen = torch.Generator().manual_seed(23)
    flip = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    M = so3_exp(_random_rotvecs((), seed=24)) @ flip + 0.1 * torch.randn(
        3, 3, generator=gen, dtype=torch.float64
    )
    R = nearest_rotation(M)
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-13, rtol=0)
    assert abs(float(torch.linalg.det(R)) - 1) < 1e-13
    nearby = R @ so3_exp(1e-3 * torch.randn(200, 3, generator=gen, dtype=torch.float64))
    assert bool(((nearby - M).norm(dim=(-2, -1)) >= (R - M).norm()).all())


# --- gradients -------------------------------------------------------------------------


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_so3_exp_gradcheck(shape: tuple[int, ...]) -> None:
    check_gradients(so3_exp, _random_rotvecs(shape, seed=10))


@pytest.mark.parametrize("angle", [1e-7, 1e-3, math.pi - 1e-3, math.pi])
def test_so3_exp_gradcheck_special_angles(angle: float) -> None:
    check_gradients(so3_exp, torch.as_tensor(np.stack([angle * _unit(a) for a in AXES[3:6]])))


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_so3_log_gradcheck(shape: tuple[int, ...]) -> None:
    R = torch.as_tensor(_scipy_matrix(_random_rotvecs(shape, seed=11, max_angle=3.0)))
    check_gradients(so3_log, R)


@pytest.mark.parametrize("angle", [1e-7, 1e-3, 2.8, math.pi - 1e-3])
def test_so3_log_gradcheck_special_angles(angle: float) -> None:
    # Not at exactly pi, where the log jumps between +pi a and -pi a. Axes without two
    # equal |a_k|: there the near-pi branch (angle > ~154 deg) switches the column it
    # reads the axis from, so its extension off SO(3) has a kink (on SO(3) it has none;
    # see the perturbation check below and test_so3_log_exp_jacobian_is_identity).
    axes = [(0.0, -1.0, 0.0), (-0.6, 0.0, -0.8), (0.3, -0.2, 0.9)]
    w = torch.as_tensor(np.stack([angle * _unit(a) for a in axes]))
    check_gradients(so3_log, so3_exp(w))


@pytest.mark.parametrize("angle", [1e-7, 2.8, math.pi - 1e-3])
def test_so3_log_gradcheck_on_manifold_perturbation(angle: float) -> None:
    # d log(exp(d) R0) / dd at d = 0, for every axis including those with tied |a_k|.
    R0 = so3_exp(torch.as_tensor(np.stack([angle * _unit(a) for a in AXES])))
    check_gradients(lambda d: so3_log(so3_exp(d) @ R0), torch.zeros(len(AXES), 3))


@pytest.mark.parametrize("angle", [0.0, 1e-7, 1e-3, 1.0, 2.8, math.pi - 1e-3])
def test_so3_log_exp_jacobian_is_identity(angle: float) -> None:
    # log(exp(w)) = w below pi, so its Jacobian is I: checks the on-manifold derivatives of
    # so3_log in every branch against an exact answer, not just against finite differences.
    for axis in AXES:
        w = torch.as_tensor(angle * _unit(axis))
        J = torch.autograd.functional.jacobian(lambda v: so3_log(so3_exp(v)), w)
        torch.testing.assert_close(J, torch.eye(3, dtype=torch.float64), atol=1e-8, rtol=0)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_rotation_angle_gradcheck(shape: tuple[int, ...]) -> None:
    R = torch.as_tensor(_scipy_matrix(_random_rotvecs(shape, seed=12, max_angle=3.0)))
    check_gradients(rotation_angle, R)


def test_rotation_angle_gradient_is_unit_direction() -> None:
    # angle(exp(w)) = |w|, whose gradient is w / |w|.
    w = torch.tensor([0.3, -1.2, 0.5], dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(rotation_angle(so3_exp(w)), w)
    torch.testing.assert_close(grad, w.detach() / w.detach().norm(), atol=1e-12, rtol=0)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_rpy_and_quat_gradcheck(shape: tuple[int, ...]) -> None:
    gen = torch.Generator().manual_seed(13)
    rpy = torch.rand(*shape, 3, generator=gen, dtype=torch.float64) - 0.5
    check_gradients(rpy_to_matrix, rpy)
    check_gradients(matrix_to_rpy, rpy_to_matrix(rpy))
    q = torch.randn(*shape, 4, generator=gen, dtype=torch.float64)
    check_gradients(quat_to_matrix, q)
    check_gradients(matrix_to_quat, quat_to_matrix(q))


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_transform_inverse_gradcheck(shape: tuple[int, ...]) -> None:
    gen = torch.Generator().manual_seed(14)
    R = torch.as_tensor(_scipy_matrix(_random_rotvecs(shape, seed=15)))
    p = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    check_gradients(lambda R, p: transform_inverse(transform(R, p)), R, p)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_no_nan_gradients_at_identity(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    w = torch.zeros(*shape, 3, dtype=dtype, requires_grad=True)
    (g,) = torch.autograd.grad(so3_log(so3_exp(w)).sum(), w)
    torch.testing.assert_close(g, torch.ones_like(g))  # d log(exp(w)) / dw = I at 0
    eye = torch.eye(3, dtype=dtype).expand(*shape, 3, 3).clone().requires_grad_(True)
    for fn in (so3_log, rotation_angle, matrix_to_quat, matrix_to_rpy):
        (g,) = torch.autograd.grad(fn(eye).sum(), eye)
        assert torch.isfinite(g).all(), fn.__name__
    q = torch.zeros(*shape, 4, dtype=dtype)
    q[..., 0] = 1
    q.requires_grad_(True)
    (g,) = torch.autograd.grad(quat_to_matrix(q).sum(), q)
    assert torch.isfinite(g).all()


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("axis", AXES[:5])
def test_no_nan_gradients_at_exactly_pi(
    axis: tuple[float, float, float], dtype: torch.dtype
) -> None:
    R = torch.as_tensor(_rotation_pi(_unit(axis)), dtype=dtype).requires_grad_(True)
    for fn in (so3_log, rotation_angle, matrix_to_quat):
        (g,) = torch.autograd.grad(fn(R).sum(), R)
        assert torch.isfinite(g).all(), fn.__name__


# --- the shared helpers themselves --------------------------------------------------------


def test_assert_transforms_close_detects_small_rotation_and_translation() -> None:
    T = transform(so3_exp(torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64)), torch.ones(3))
    R_off = so3_exp(torch.tensor([0.0, 0.0, 1e-4], dtype=torch.float64))
    T_rot = transform(R_off @ T[:3, :3], T[:3, 3])
    assert_transforms_close(T, T_rot, atol_pos=1e-12, atol_rot=1.01e-4)
    with pytest.raises(AssertionError, match="rotations differ"):
        assert_transforms_close(T, T_rot, atol_pos=1e-12, atol_rot=0.99e-4)
    T_pos = transform(T[:3, :3], T[:3, 3] + torch.tensor([0.0, 2e-3, 0.0], dtype=torch.float64))
    with pytest.raises(AssertionError, match="translations differ"):
        assert_transforms_close(T, T_pos, atol_pos=1e-3, atol_rot=1e-12)


def test_assert_quats_close_accepts_double_cover() -> None:
    q = torch.tensor([0.5, -0.5, 0.5, 0.5], dtype=torch.float64)
    assert_quats_close(q, -q, atol=1e-15)
    with pytest.raises(AssertionError, match="quaternions differ"):
        assert_quats_close(q, q.roll(1), atol=1e-3)


class _WrongBackward(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        return x * x

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        return grad  # should be 2 x grad


def test_check_gradients_catches_wrong_and_missing_gradients() -> None:
    x, y = torch.rand(3, dtype=torch.float64), torch.rand(3, dtype=torch.float64)
    with pytest.raises(GradcheckError):
        check_gradients(_WrongBackward.apply, x)
    with pytest.raises(AssertionError, match="input 1"):
        check_gradients(lambda a, b: a + 0 * b.detach(), x, y)
    check_gradients(lambda a, b: a * b, x, y, gradgrad=True)


def test_twist_swing_takes_a_rotation_apart_about_an_axis():
    """``R = exp(s u) exp(t a)`` with ``u`` perpendicular to ``a``: the twist about ``a``
    is ``t`` and the swing ``s``, for random axes and angles over their whole ranges."""
    from hybrid_pk.geometry import twist_swing

    gen = torch.Generator().manual_seed(int(run_rng("twist-swing").integers(1 << 31)))
    for _ in range(200):
        a = torch.randn(3, generator=gen, dtype=torch.float64)
        a = a / a.norm()
        u = torch.linalg.cross(a, torch.randn(3, generator=gen, dtype=torch.float64))
        u = u / u.norm()
        t = (2 * torch.rand((), generator=gen, dtype=torch.float64) - 1) * math.pi * 0.999
        s = torch.rand((), generator=gen, dtype=torch.float64) * math.pi * 0.999
        R = so3_exp(u * s) @ so3_exp(a * t)
        twist, swing = twist_swing(R, a)
        assert float(twist) == pytest.approx(float(t), abs=1e-9)
        assert float(swing) == pytest.approx(float(s), abs=1e-7)

"""capture.quat: the project's one quaternion module, checked against scipy's Rotation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture.quat import (
    cross,
    quat_canonical,
    quat_conj,
    quat_exp,
    quat_from_axis_angle,
    quat_from_matrix,
    quat_log,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_slerp,
    quat_to_matrix,
    quat_to_matrix_components,
)


def random_quats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    n = int(np.prod(shape))
    xyzw = Rotation.random(n, random_state=int(rng.integers(1 << 31))).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1).reshape((*shape, 4))


def same_rotation(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> bool:
    """Quaternions equal up to sign."""
    return bool(np.all(np.abs(np.abs(np.sum(a * b, axis=-1)) - 1.0) < tol))




def test_quaternion_helpers_agree_with_scipy() -> None:
    rng = np.random.default_rng(1)
    a, b = random_quats(rng, (50,)), random_quats(rng, (50,))
    ra, rb = (Rotation.from_quat(q[:, [1, 2, 3, 0]]) for q in (a, b))
    ab = quat_mul(a, b)
    assert same_rotation(ab, (ra * rb).as_quat()[:, [3, 0, 1, 2]])
    v = rng.normal(size=(50, 3))
    np.testing.assert_allclose(quat_rotate(a, v), ra.apply(v), atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(a), ra.as_matrix(), atol=1e-12)
    assert same_rotation(quat_from_matrix(ra.as_matrix()), a)
    assert np.all(quat_from_matrix(ra.as_matrix())[:, 0] >= 0)
    np.testing.assert_allclose(quat_mul(a, quat_conj(a)), np.tile([1.0, 0, 0, 0], (50, 1)), atol=1e-12)
    # the many-quaternion path of quat_to_matrix (component-wise) matches the small one
    big = random_quats(rng, (400,))
    np.testing.assert_allclose(quat_to_matrix(big), Rotation.from_quat(big[:, [1, 2, 3, 0]]).as_matrix(),
                               atol=1e-12)


def test_quat_from_matrix_near_half_turns_and_identity() -> None:
    for axis in np.eye(3):
        for angle in (0.0, np.pi, np.pi - 1e-9, np.pi / 2):
            m = Rotation.from_rotvec(axis * angle).as_matrix()
            q = quat_from_matrix(m)
            np.testing.assert_allclose(quat_to_matrix(q), m, atol=1e-12)


def test_slerp_ends_midpoint_and_shorter_path() -> None:
    a = np.array([1.0, 0, 0, 0])
    b = quat_from_axis_angle([0, 1, 0], np.pi / 2)
    np.testing.assert_allclose(quat_slerp(a, b, 0.0), a, atol=1e-12)
    np.testing.assert_allclose(quat_slerp(a, b, 1.0), b, atol=1e-12)
    np.testing.assert_allclose(quat_slerp(a, b, 0.5), quat_from_axis_angle([0, 1, 0], np.pi / 4), atol=1e-12)
    # -b is the same rotation: slerp must still take the 45 degree way, not the long one
    mid = quat_slerp(a, -b, 0.5)
    assert same_rotation(mid, quat_from_axis_angle([0, 1, 0], np.pi / 4))
    # nearly equal inputs do not divide by zero
    c = quat_normalize(a + 1e-9)
    assert np.all(np.isfinite(quat_slerp(a, c, 0.3)))


def test_quat_normalize_rejects_zero() -> None:
    with pytest.raises(ValueError, match="non-zero"):
        quat_normalize(np.zeros(4))
    with pytest.raises(ValueError, match="non-zero"):
        quat_from_axis_angle([0.0, 0.0, 0.0], 1.0)


def test_exp_and_log_agree_with_rotation_vectors() -> None:
    rng = np.random.default_rng(3)
    rv = rng.normal(size=(100, 3))
    rv *= (np.minimum(np.linalg.norm(rv, axis=1), 3.0) / np.linalg.norm(rv, axis=1))[:, None]
    q = quat_exp(rv)
    assert same_rotation(q, Rotation.from_rotvec(rv).as_quat()[:, [3, 0, 1, 2]])
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(quat_log(q), rv, atol=1e-10)
    # the log takes the w >= 0 sign, so -q has the same log; tiny angles use the series
    np.testing.assert_allclose(quat_log(-q), rv, atol=1e-10)
    np.testing.assert_allclose(quat_log(quat_exp([1e-9, 0.0, 0.0])), [1e-9, 0.0, 0.0], atol=1e-18)


def test_normalize_keeps_the_sign_and_canonical_picks_w_positive() -> None:
    q = np.array([[-2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 3.0, 0.0], [-1.0, 1.0, 0.0, 0.0]])
    n = quat_normalize(q)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    assert n[0, 0] == -1.0
    c = quat_canonical(q)
    assert np.all(c[:, 0] >= 0) and same_rotation(c, n)
    with pytest.raises(ValueError, match="finite"):
        quat_canonical([np.nan, 0.0, 0.0, 1.0])


def test_component_first_matrices_and_cross_products() -> None:
    rng = np.random.default_rng(4)
    q = random_quats(rng, (7, 5))
    m = quat_to_matrix_components(np.moveaxis(q, -1, 0))
    np.testing.assert_allclose(np.moveaxis(m, (0, 1), (-2, -1)), quat_to_matrix(q), atol=1e-12)
    a, b = rng.normal(size=(2, 9, 3))
    np.testing.assert_allclose(cross(a, b), np.cross(a, b), atol=1e-12)

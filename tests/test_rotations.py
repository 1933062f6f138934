"""Quaternions without SciPy at start-up: bit for bit SciPy's Rotation for orthonormal
matrices (so trees keep their bytes), and a round trip through both directions."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from usdforest.grow.placement import frames_from_directions
from usdforest.rotations import matrix_from_quat, quat_from_matrix, quat_multiply


def test_quaternions_are_scipys_bit_for_bit():
    rng = np.random.default_rng(7)
    rot = Rotation.random(20_000, random_state=3).as_matrix()
    # every branch of Shepperd's method: each diagonal entry and the trace the largest
    rot = np.concatenate([rot, np.eye(3)[None], np.diag([1.0, -1, -1])[None],
                          np.diag([-1.0, 1, -1])[None], np.diag([-1.0, -1, 1])[None]])  # fmt: skip
    np.testing.assert_array_equal(quat_from_matrix(rot), Rotation.from_matrix(rot).as_quat())
    d = rng.normal(size=(5_000, 3))
    frames = frames_from_directions(d, rng.uniform(0, 2 * np.pi, 5_000))
    q = quat_from_matrix(frames)
    np.testing.assert_array_equal(q, Rotation.from_matrix(frames).as_quat())
    np.testing.assert_array_equal(matrix_from_quat(q), Rotation.from_quat(q).as_matrix())


def test_round_trip():
    rot = Rotation.random(1_000, random_state=5).as_matrix()
    np.testing.assert_allclose(matrix_from_quat(quat_from_matrix(rot)), rot, atol=1e-14)
    q = quat_from_matrix(rot)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    # an unnormalised quaternion is normalised first
    np.testing.assert_allclose(matrix_from_quat(3 * q), rot, atol=1e-14)


def test_quaternion_products_compose_rotations_as_scipy_does():
    rng = np.random.default_rng(7)
    a, b = Rotation.random(50, random_state=rng), Rotation.random(50, random_state=rng)
    q = quat_multiply(a.as_quat(), b.as_quat())
    np.testing.assert_allclose(matrix_from_quat(q), (a * b).as_matrix(), atol=1e-12)

"""Rotation matrices and unit quaternions (x, y, z, w), vectorised with numpy.

The same arithmetic as SciPy's ``Rotation.from_matrix`` / ``as_matrix`` for orthonormal
matrices (Shepperd's method: the quaternion's largest component is formed from the
diagonal, the others from off-diagonal sums), without building per-call rotation objects or
importing SciPy at start-up.
"""

from __future__ import annotations

import numpy as np


def quat_from_matrix(rot: np.ndarray) -> np.ndarray:
    """``(n, 4)`` unit quaternions (x, y, z, w) of ``(n, 3, 3)`` column-vector rotations."""
    m = np.asarray(rot, dtype=np.float64)
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    choice = np.argmax(np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], trace], axis=1), axis=1)
    q = np.empty((len(m), 4))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        sel = np.flatnonzero(choice == i)
        q[sel, i] = 1 - trace[sel] + 2 * m[sel, i, i]
        q[sel, j] = m[sel, j, i] + m[sel, i, j]
        q[sel, k] = m[sel, k, i] + m[sel, i, k]
        q[sel, 3] = m[sel, k, j] - m[sel, j, k]
    sel = np.flatnonzero(choice == 3)
    q[sel, 0] = m[sel, 2, 1] - m[sel, 1, 2]
    q[sel, 1] = m[sel, 0, 2] - m[sel, 2, 0]
    q[sel, 2] = m[sel, 1, 0] - m[sel, 0, 1]
    q[sel, 3] = 1 + trace[sel]
    return q / _norm4(q)[:, None]


def matrix_from_quat(quat: np.ndarray) -> np.ndarray:
    """``(n, 3, 3)`` column-vector rotations of ``(n, 4)`` quaternions (x, y, z, w),
    normalised first."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / _norm4(q)[:, None]
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    m = np.empty((len(q), 3, 3))
    m[:, 0, 0] = x2 - y2 - z2 + w2
    m[:, 0, 1] = 2 * (xy - zw)
    m[:, 0, 2] = 2 * (xz + yw)
    m[:, 1, 0] = 2 * (xy + zw)
    m[:, 1, 1] = -x2 + y2 - z2 + w2
    m[:, 1, 2] = 2 * (yz - xw)
    m[:, 2, 0] = 2 * (xz - yw)
    m[:, 2, 1] = 2 * (yz + xw)
    m[:, 2, 2] = -x2 - y2 + z2 + w2
    return m


def _norm4(q: np.ndarray) -> np.ndarray:
    return np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a b`` of ``(..., 4)`` quaternions (x, y, z, w): the rotation ``b``
    followed by ``a`` (column vectors: ``R(a b) = R(a) R(b)``)."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=float), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=float), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )

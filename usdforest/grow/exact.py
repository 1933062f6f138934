"""Arithmetic whose result does not depend on the machine's CPU.

Products and inverses of small vectors and matrices in a fixed order of operations: numpy
hands ``@``, ``np.dot`` and ``np.linalg.inv`` of float arrays to BLAS and LAPACK, whose
kernel is chosen for the machine's CPU (OpenBLAS: ``OPENBLAS_CORETYPE``): kernels sum in
other orders and fuse multiply-adds, so the same forest came out a last bit apart under two
kernels (a collider's position, the thumbnail). What usdforest writes goes through these
instead: element-wise multiplications and additions, each rounded as IEEE 754 says, in the
order written here, the same on every machine. They are for the small inner dimensions of
geometry (2, 3 or 4), where BLAS gains nothing.

Elementary functions (:func:`exp`, :func:`log`, :func:`power`, :func:`arctan2`...) through
the C library's scalar ``libm`` (Python's :mod:`math`), one element at a time. numpy picks
its own SIMD loops for these by the CPU it runs on (``np.show_runtime()``: AVX2, AVX-512...),
and they round differently: on an AVX-512 machine ``np.exp``, ``np.log``, ``np.power`` and
``np.arctan2`` differ in their last bit from the same numpy on an AVX2 machine, so a
forest's trunk colliders did. The C library picks one code path for every CPU with FMA (all
x86-64 since 2013, every arm64), so the same glibc gives the same bits there. They cost
0.1-0.3 µs an element: they are for per-tree, per-branch and per-leaf arrays, not per pixel.
Outside the build (the sensors' rays, ``fit``'s likelihood, ``stats``) numpy's own are used.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` (numpy's broadcasting; ``b`` a vector: a matrix-vector product), the inner
    dimension summed from its first term to its last."""
    a, b = np.asarray(a, dtype=np.result_type(a, b, np.float32)), np.asarray(b)
    if b.ndim == 1:
        return dot(a, b)
    if a.ndim == 1:
        return matmul(a[None, :], b)[..., 0, :]
    k = a.shape[-1]
    if b.shape[-2] != k:
        raise ValueError(f"matmul: inner dimensions {a.shape} and {b.shape} differ")
    out = a[..., :, 0, None] * b[..., 0, None, :]
    for j in range(1, k):
        out = out + a[..., :, j, None] * b[..., j, None, :]
    return out


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The sum over the last axis of ``a * b`` (broadcast), from its first term to its last."""
    a, b = np.asarray(a), np.asarray(b)
    k = np.broadcast_shapes(a.shape[-1:], b.shape[-1:])[0]
    a = np.broadcast_to(a, (*a.shape[:-1], k))
    b = np.broadcast_to(b, (*b.shape[:-1], k))
    out = a[..., 0] * b[..., 0]
    for j in range(1, k):
        out = out + a[..., j] * b[..., j]
    return out


def det3(m: np.ndarray) -> np.ndarray:
    """The determinants of ``(..., 3, 3)`` matrices, expanded along the first row."""
    m = np.asarray(m, dtype=float)
    return (
        m[..., 0, 0] * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
        + m[..., 0, 1] * (m[..., 1, 2] * m[..., 2, 0] - m[..., 1, 0] * m[..., 2, 2])
        + m[..., 0, 2] * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0])
    )


def norm(v: np.ndarray) -> np.ndarray:
    """The lengths of vectors along the last axis (:func:`dot` of each with itself)."""
    return np.sqrt(dot(v, v))


def inv3(m: np.ndarray) -> np.ndarray:
    """The inverses of ``(..., 3, 3)`` matrices: the adjugate over the determinant."""
    m = np.asarray(m, dtype=float)
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    d, e, f = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    g, h, i = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    co = np.stack(
        [
            np.stack([e * i - f * h, c * h - b * i, b * f - c * e], axis=-1),
            np.stack([f * g - d * i, a * i - c * g, c * d - a * f], axis=-1),
            np.stack([d * h - e * g, b * g - a * h, a * e - b * d], axis=-1),
        ],
        axis=-2,
    )
    det = a * co[..., 0, 0] + b * co[..., 1, 0] + c * co[..., 2, 0]
    return co / det[..., None, None]


def inv_affine(m: np.ndarray) -> np.ndarray:
    """The inverses of ``(..., 4, 4)`` row-vector affine transforms (USD's: the last column
    0, 0, 0, 1): the linear part inverted (:func:`inv3`), the translation taken back."""
    m = np.asarray(m, dtype=float)
    if not np.array_equal(m[..., :, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], m.shape[:-1])):
        raise ValueError("inv_affine: not a row-vector affine transform")
    out = np.zeros_like(m)
    r = inv3(m[..., :3, :3])
    out[..., :3, :3] = r
    out[..., 3, :3] = -matmul(m[..., 3:4, :3], r)[..., 0, :]
    out[..., 3, 3] = 1.0
    return out


def _libm(fn: Callable[..., float], *args, valid: np.ndarray | None = None, fill=np.nan):
    """``fn`` of each element of the broadcast ``args`` (floats), where ``valid`` (else
    ``fill``); a 0-d result as a numpy float, like a ufunc's."""
    xs = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in args))
    shape = xs[0].shape
    out = np.full(shape, fill, dtype=float)
    if valid is None:
        valid = np.ones(shape, dtype=bool)
    picked = [x[valid].tolist() for x in xs]
    out[valid] = np.fromiter(map(fn, *picked), dtype=float, count=len(picked[0]))
    return out[()] if out.ndim == 0 else out


def exp(x) -> np.ndarray:
    """``np.exp``, the same bits on every CPU; ``inf`` beyond float64's range."""
    return _libm(_exp, x)


def _exp(x: float) -> float:
    try:
        return math.exp(x)
    except OverflowError:
        return math.inf


def log(x) -> np.ndarray:
    """``np.log``, the same bits on every CPU: ``-inf`` at 0, ``nan`` below."""
    return _logarithm(math.log, x, 0.0)


def log1p(x) -> np.ndarray:
    """``np.log1p``, the same bits on every CPU: ``-inf`` at -1, ``nan`` below."""
    return _logarithm(math.log1p, x, -1.0)


def log2(x) -> np.ndarray:
    """``np.log2``, the same bits on every CPU: ``-inf`` at 0, ``nan`` below."""
    return _logarithm(math.log2, x, 0.0)


def _logarithm(fn: Callable[[float], float], x, pole: float) -> np.ndarray:
    """``fn`` above its ``pole``, ``-inf`` at it, ``nan`` below (where ``math`` raises)."""
    x = np.asarray(x, dtype=float)
    out = np.where(x == pole, -np.inf, _libm(fn, x, valid=x > pole))
    return out[()] if out.ndim == 0 else out


def power(x, y) -> np.ndarray:
    """``x ** y`` elementwise (``np.power`` of floats), the same bits on every CPU: ``nan``
    for a negative base and a fractional exponent, ``inf`` past float64's range."""
    return _libm(_pow, x, y)


def _pow(x: float, y: float) -> float:
    try:
        return math.pow(x, y)
    except ValueError:  # 0 ** negative, or a negative base and a fractional exponent
        return math.inf if x == 0 else math.nan
    except OverflowError:
        return math.inf if x > 0 or (float(y).is_integer() and y % 2 == 0) else -math.inf


def arctan2(y, x) -> np.ndarray:
    """``np.arctan2``, the same bits on every CPU."""
    return _libm(math.atan2, y, x)


def arcsin(x) -> np.ndarray:
    """``np.arcsin``, the same bits on every CPU: ``nan`` outside [-1, 1]."""
    x = np.asarray(x, dtype=float)
    return _libm(math.asin, x, valid=np.abs(x) <= 1)


def arccos(x) -> np.ndarray:
    """``np.arccos``, the same bits on every CPU: ``nan`` outside [-1, 1]."""
    x = np.asarray(x, dtype=float)
    return _libm(math.acos, x, valid=np.abs(x) <= 1)


def cbrt(x) -> np.ndarray:
    """``np.cbrt``, the same bits on every CPU."""
    return _libm(math.cbrt, x)

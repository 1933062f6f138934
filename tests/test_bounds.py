"""Exact instance bounds (:func:`usdforest.grow.bounds.instances_bounds`) against transforming
every vertex of every instance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from usdforest.grow.bounds import instances_bounds, yawed_extent
from usdforest.rotations import matrix_from_quat


def _brute(hulls, proto, rows, translate):
    # vertex by vertex, in the same arithmetic as the writer (so the same floats)
    return np.concatenate(
        [np.einsum("cj,jk->ck", hulls[k], rows[i]) + translate[i] for i, k in enumerate(proto)]
    )


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 3000),
    spread=st.sampled_from([0.1, 1.0, 20.0]),
    anisotropic=st.booleans(),
)
def test_bounds_equal_every_vertex_transformed(seed, n, spread, anisotropic):
    rng = np.random.default_rng(seed)
    hulls = [rng.normal(size=(rng.integers(4, 30), 3)) * [1.0, 0.3, 0.05] for _ in range(3)]
    proto = rng.integers(0, 3, n)
    rot = matrix_from_quat(rng.normal(size=(n, 4)))
    scale = rng.uniform(0.2, 2.0, (n, 3 if anisotropic else 1)) * np.ones((n, 3))
    rows = np.transpose(rot, (0, 2, 1)) * scale[:, :, None]
    translate = rng.normal(size=(n, 3)) * spread * [1.0, 1.0, 0.5]
    b = instances_bounds(hulls, proto, rows, translate)
    pts = _brute(hulls, proto, rows, translate)
    # the same points, so the same float extremes
    np.testing.assert_array_equal(b.extent, [pts.min(axis=0), pts.max(axis=0)])
    # the footprint is the hull of the points' x, y: same area, and it holds them all
    fp = ConvexHull(b.footprint)
    assert fp.volume == pytest.approx(ConvexHull(pts[:, :2]).volume, rel=1e-12)
    assert (pts[:, :2] @ fp.equations[:, :2].T + fp.equations[:, 2]).max() <= 1e-9


def test_a_million_leaves_transform_only_those_near_the_boundary(monkeypatch):
    import usdforest.grow.bounds as bounds

    rng = np.random.default_rng(1)
    n = 200_000
    hull = rng.normal(size=(20, 3)) * [0.05, 0.02, 0.001]
    d = rng.normal(size=(n, 3))
    translate = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0, 3, (n, 1)) ** (1 / 3)
    rows = np.repeat(np.eye(3)[None], n, axis=0)
    seen = []
    real = bounds._transformed
    monkeypatch.setattr(
        bounds,
        "_transformed",
        lambda h, p, r, t, which: seen.append(len(which)) or real(h, p, r, t, which),
    )
    b = instances_bounds([hull], np.zeros(n, dtype=int), rows, translate)
    pts = (hull[None] + translate[:, None]).reshape(-1, 3)
    np.testing.assert_array_equal(b.extent, [pts.min(axis=0), pts.max(axis=0)])
    assert sum(seen) < n // 5  # a shell, not the ball


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5000))
def test_yawed_extent_equals_every_footprint_vertex_turned(seed, n):
    rng = np.random.default_rng(seed)
    feet = [rng.normal(size=(rng.integers(3, 40), 2)) * rng.uniform(0.5, 5) for _ in range(4)]
    z_ranges = np.sort(rng.normal(size=(4, 2)) * 5, axis=1)
    proto = rng.integers(0, 4, n)
    xy = rng.uniform(0, rng.choice([5.0, 100.0, 1000.0]), (n, 2))
    yaw = rng.uniform(0, 2 * np.pi, n)
    scale = rng.lognormal(0, 0.2, n)
    base = rng.normal(size=n)
    e = yawed_extent(feet, z_ranges, proto, xy, (np.cos(yaw), np.sin(yaw)), scale, base)
    x, y, z = [], [], []
    for i in range(n):  # one tree at a time, in the same arithmetic
        f, c, s = feet[proto[i]], np.cos(yaw[i]), np.sin(yaw[i])
        x.append((c * f[:, 0] - s * f[:, 1]) * scale[i] + xy[i, 0])
        y.append((s * f[:, 0] + c * f[:, 1]) * scale[i] + xy[i, 1])
        z.append(z_ranges[proto[i]] * scale[i] + base[i])
    x, y, z = (np.concatenate(v) for v in (x, y, z))
    np.testing.assert_array_equal(e, [[x.min(), y.min(), z.min()], [x.max(), y.max(), z.max()]])


def test_rounding_of_a_rank_one_map_is_allowed_for():
    """A map of rank one and a two-point hull: the transformed points round away from their
    anchor by an ulp; the filter's reach leaves room for it (found by a review fuzzer)."""
    rng = np.random.default_rng(5)
    for _ in range(200_000):  # an instance whose top point rounds above anchor + reach
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        c = rng.normal(size=3) * rng.choice([1, 100, 1e4])
        r = rng.uniform(0.1, 3)
        hull = np.stack([c - r * u, c + r * u])
        rows = np.zeros((1, 3, 3))
        rows[0, :, 2] = u * rng.uniform(0.3, 3)
        shift = np.array([[0.0, 0.0, rng.normal() * 10]])
        top = (np.einsum("cj,njk->nck", hull, rows) + shift[:, None])[0, :, 2].max()
        anchor = (hull.mean(axis=0) @ rows[0] + shift[0])[2]
        if anchor + np.linalg.norm(rows[0]) * r < np.nextafter(top, -np.inf):
            break
    below = np.nextafter(top, -np.inf)
    n = 21_000  # enough to take the filtered path, all but one reaching exactly `below`
    hulls = [hull, np.zeros((1, 3))]
    proto = np.r_[0, np.ones(n, dtype=int)]
    maps = np.concatenate([rows, np.repeat(np.eye(3)[None], n, axis=0)])
    t = np.zeros((n + 1, 3))
    t[0] = shift[0]
    a = rng.uniform(0, 2 * np.pi, n)
    t[1:, 0], t[1:, 1] = 1e3 * np.cos(a), 1e3 * np.sin(a)
    t[1:, 2] = rng.uniform(-1e3, below - 1, n)
    t[1, 2] = below
    b = instances_bounds(hulls, proto, maps, t)
    assert b.extent[1, 2] == top


def test_yawed_extent_with_negative_and_zero_scales():
    rng = np.random.default_rng(3)
    feet = [rng.normal(size=(12, 2)) * 3 for _ in range(2)]
    z_ranges = np.array([[0.0, 10.0], [-1.0, 4.0]])
    n = 400
    proto = rng.integers(0, 2, n)
    xy = rng.uniform(0, 50, (n, 2))
    yaw = rng.uniform(0, 2 * np.pi, n)
    scale = rng.lognormal(0, 0.3, n) * rng.choice([-1.0, 1.0], n)
    scale[:20] = 0.0
    base = rng.normal(size=n)
    e = yawed_extent(feet, z_ranges, proto, xy, (np.cos(yaw), np.sin(yaw)), scale, base)
    x = np.concatenate(
        [
            (np.cos(yaw[i]) * feet[proto[i]][:, 0] - np.sin(yaw[i]) * feet[proto[i]][:, 1])
            * scale[i]
            + xy[i, 0]
            for i in range(n)
        ]
    )
    y = np.concatenate(
        [
            (np.sin(yaw[i]) * feet[proto[i]][:, 0] + np.cos(yaw[i]) * feet[proto[i]][:, 1])
            * scale[i]
            + xy[i, 1]
            for i in range(n)
        ]
    )
    z = np.concatenate([z_ranges[proto[i]] * scale[i] + base[i] for i in range(n)])
    np.testing.assert_array_equal(e, [[x.min(), y.min(), z.min()], [x.max(), y.max(), z.max()]])

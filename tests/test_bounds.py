"""Exact instance bounds (:func:`usdforest.bounds.instances_bounds`) against transforming
every vertex of every instance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from usdforest.bounds import instances_bounds
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
    import usdforest.bounds as bounds

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

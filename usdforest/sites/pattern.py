"""Summary statistics of a stand's stem pattern: is it clustered, random or regular, and at
what distances? The estimators are those of Baddeley, Rubak and Turner (2015), *Spatial
Point Patterns: Methodology and Applications with R* (spatstat), for a rectangular window:

* Ripley's K with the translation edge correction (Ohser and Stoyan 1981): each pair
  ``(i, j)`` at distance ``d`` counts ``|W| / |W ∩ (W + x_i - x_j)|``, and
  ``K(r) = |W|^2 / (n (n - 1)) * sum_{i != j, d_ij <= r} 1 / |W ∩ W_ij|``;
* Besag's ``L(r) = sqrt(K(r) / pi)`` (``L(r) - r`` is 0 for a Poisson pattern);
* the pair-correlation function ``g(r)`` by an Epanechnikov kernel of half-width ``h``
  over the same translation-corrected pairs, ``g = K' / (2 pi r)``;
* the Clark-Evans ratio ``R`` of the mean nearest-neighbour distance to Poisson's
  ``0.5 / sqrt(lambda)``, with Donnelly's (1978) edge correction for a rectangle;
* pointwise envelopes of any of them from patterns of complete spatial randomness (CSR)
  with the same number of points (``nsim`` simulations: the ``2 / (nsim + 1)`` test).

Under CSR, ``K(r) = pi r^2``, ``g = 1`` and ``R = 1``; clustering raises K and g above them
and lowers R, inhibition the reverse.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from usdforest.errors import UsdForestError

Bounds = tuple[float, float, float, float]


def _checked(xy: np.ndarray, bounds: Bounds) -> tuple[np.ndarray, float, float, float]:
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)
    x0, y0, x1, y1 = (float(v) for v in bounds)
    w, h = x1 - x0, y1 - y0
    if not (w > 0 and h > 0):
        raise UsdForestError(f"window: bounds {list(bounds)} are empty")
    if len(pts) < 2:
        raise UsdForestError(f"a pattern needs at least 2 points, got {len(pts)}")
    inside = (pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)
    if not inside.all():
        raise UsdForestError(
            f"{int((~inside).sum())} point(s) lie outside the window {list(bounds)}"
        )
    return pts, w, h, w * h


def _pairs(
    pts: np.ndarray, w: float, h: float, rmax: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unordered pairs within ``rmax`` (``(m, 2)`` indices), their distances and their
    translation weights ``1 / |W ∩ W_ij|`` (a rectangle: ``(w - |dx|)(h - |dy|)``)."""
    ij = cKDTree(pts).query_pairs(rmax, output_type="ndarray").reshape(-1, 2)
    d = pts[ij[:, 0]] - pts[ij[:, 1]]
    overlap = (w - np.abs(d[:, 0])) * (h - np.abs(d[:, 1]))
    return ij, np.hypot(d[:, 0], d[:, 1]), 1.0 / overlap


def k_function(xy: np.ndarray, bounds: Bounds, r: np.ndarray) -> np.ndarray:
    """Ripley's K at distances ``r`` (translation correction); ``r`` at most half the
    window's shorter side, as the correction needs."""
    pts, _, _, area = _checked(xy, bounds)
    n = len(pts)
    # the homogeneous estimator: every lambda_i lambda_j is n (n - 1) / |W|^2
    return inhomogeneous_k(pts, bounds, r, np.full(n, math.sqrt(n * (n - 1)) / area))


def inhomogeneous_k(xy: np.ndarray, bounds: Bounds, r: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """K with each pair weighted by ``1 / (lambda_i lambda_j)`` at the trees' intensities
    ``lam`` and the translation correction (Baddeley, Møller and Waagepetersen 2000)."""
    pts, w, h, _ = _checked(xy, bounds)
    r = np.asarray(r, dtype=float)
    _check_r(r, w, h)
    ij, d, e = _pairs(pts, w, h, float(r.max()) if r.size else 0.0)
    weight = e / (lam[ij[:, 0]] * lam[ij[:, 1]])
    order = np.argsort(d)
    cum = np.concatenate([[0.0], np.cumsum(weight[order])])
    return 2.0 * cum[np.searchsorted(d[order], r, side="right")]  # each unordered pair twice


def l_function(xy: np.ndarray, bounds: Bounds, r: np.ndarray) -> np.ndarray:
    """Besag's L = sqrt(K / pi) at ``r``."""
    return np.sqrt(k_function(xy, bounds, r) / math.pi)


def pair_correlation(
    xy: np.ndarray, bounds: Bounds, r: np.ndarray, bandwidth: float | None = None
) -> np.ndarray:
    """g(r) by an Epanechnikov kernel of half-width ``bandwidth`` (default Stoyan's rule,
    ``0.15 / sqrt(lambda)``) over translation-corrected pairs; ``r > 0``."""
    pts, w, h, area = _checked(xy, bounds)
    r = np.asarray(r, dtype=float)
    _check_r(r, w, h)
    if np.any(r <= 0):
        raise UsdForestError("g(r) needs r > 0")
    n = len(pts)
    bw = 0.15 / math.sqrt(n / area) if bandwidth is None else float(bandwidth)
    _, d, e = _pairs(pts, w, h, float(r.max()) + bw)
    out = np.empty(len(r))
    for k, rk in enumerate(r):
        u = (rk - d) / bw
        near = np.abs(u) < 1
        kern = 0.75 / bw * (1 - u[near] ** 2)
        out[k] = (kern * e[near]).sum() * 2.0 / (2 * math.pi * rk)
    return area**2 / (n * (n - 1)) * out


def clark_evans(xy: np.ndarray, bounds: Bounds) -> float:
    """Clark and Evans' R: the mean nearest-neighbour distance over its expectation under
    CSR with Donnelly's correction for a rectangle's edge,
    ``0.5 sqrt(A / n) + (0.0514 + 0.041 / sqrt(n)) P / n``."""
    pts, w, h, area = _checked(xy, bounds)
    n = len(pts)
    nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
    expected = 0.5 * math.sqrt(area / n) + (0.0514 + 0.041 / math.sqrt(n)) * 2 * (w + h) / n
    return float(nn.mean() / expected)


PAIR_BUDGET = 10_000_000  # pairs within rmax held at once: about 0.6 GB with their weights


def pair_rmax(n: int, w: float, h: float, cap: float, budget: int = PAIR_BUDGET) -> float:
    """The largest distance of a K or g estimate: ``cap`` (a quarter of the window's shorter
    side), or less where that would hold more than ``budget`` pairs of ``n`` points (a random
    pattern has ``n^2 pi r^2 / (2 |W|)`` within ``r``): 100,000 trees on 1 km² would hold 1e9
    pairs within 250 m (24 GB), 1e7 within 25 m."""
    if n < 2:
        return cap
    return min(cap, math.sqrt(2.0 * w * h * budget / (math.pi * n * n)))


def _check_r(r: np.ndarray, w: float, h: float) -> None:
    if r.size and (np.any(r < 0) or r.max() > min(w, h) / 2):
        raise UsdForestError(
            f"r must be within 0 and half the window's shorter side ({min(w, h) / 2:g} m)"
        )


@dataclass(frozen=True)
class Envelope:
    """A statistic of the data and its pointwise CSR envelope at ``r``."""

    r: np.ndarray
    observed: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    theory: np.ndarray
    nsim: int

    @property
    def outside(self) -> np.ndarray:
        """Where the data leave the envelope (the pointwise 2/(nsim+1) test at each r)."""
        return (self.observed < self.lo) | (self.observed > self.hi)


def csr_envelope(
    xy: np.ndarray,
    bounds: Bounds,
    r: np.ndarray,
    statistic: Callable[[np.ndarray, Bounds, np.ndarray], np.ndarray] = l_function,
    nsim: int = 99,
    seed: int = 0,
    progress: Callable[[str, int, int], None] | None = None,
) -> Envelope:
    """``statistic`` of the pattern and its min-max envelope over ``nsim`` patterns of CSR
    with as many points in the same window (binomial processes), theory for CSR alongside
    (``pi r^2`` for K, ``r`` for L, 1 for g); ``progress(stage, done, nsim)`` after each."""
    pts, *_ = _checked(xy, bounds)
    r = np.asarray(r, dtype=float)
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = bounds
    tick = progress or (lambda stage, done, total: None)
    runs = []
    for k in range(nsim):
        sim = np.column_stack([rng.uniform(x0, x1, len(pts)), rng.uniform(y0, y1, len(pts))])
        runs.append(statistic(sim, bounds, r))
        tick("CSR envelope", k + 1, nsim)
    sims = np.array(runs).reshape(nsim, len(r))
    theory = {k_function: math.pi * r**2, l_function: r, pair_correlation: np.ones_like(r)}
    return Envelope(
        r,
        statistic(pts, bounds, r),
        sims.min(axis=0),
        sims.max(axis=0),
        theory.get(statistic, np.full_like(r, np.nan)),
        nsim,
    )


def read_rows(path: str | Path, replicate: int = 0) -> tuple[set[str], list[dict]]:
    """The columns and rows of a CSV of trees with ``x`` and ``y`` (a stem map, a forest's
    ``trees.csv``, or ``usdforest sample``'s output, of which only ``replicate``), read as
    every table of trees is (:func:`usdforest.sites.stemmap.read_table`)."""
    from usdforest.sites.stemmap import read_table

    cols, rows = read_table(path, ("x", "y"), replicate=replicate)
    return set(cols), rows


def points_of(rows: list[dict], path: str | Path) -> np.ndarray:
    """``(n, 2)`` positions of :func:`read_rows`' rows, each finite and within range."""
    from usdforest.paths import shown
    from usdforest.sites.stemmap import position

    name = shown(path)
    return np.array([position(row, name) for row in rows], dtype=float).reshape(-1, 2)


def read_points(path: str | Path, replicate: int = 0) -> np.ndarray:
    """``(n, 2)`` tree positions from a CSV with ``x`` and ``y`` columns (:func:`read_rows`)."""
    return points_of(read_rows(path, replicate)[1], path)


def describe(
    xy: np.ndarray,
    bounds: Bounds,
    *,
    rmax: float | None = None,
    steps: int = 50,
    nsim: int = 39,
    seed: int = 0,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict:
    """A stand's pattern in one dict: trees, stems/ha, nearest-neighbour distances,
    Clark-Evans R and, at ``steps`` distances up to ``rmax`` (default a quarter of the
    window's shorter side, at most 25 m and :func:`pair_rmax`), L(r) - r and g(r) with their
    CSR envelopes (``nsim`` simulations: the pointwise 2/(nsim + 1) test)."""
    pts, w, h, area = _checked(xy, bounds)
    top = pair_rmax(len(pts), w, h, min(min(w, h) / 4, 25.0)) if rmax is None else float(rmax)
    r = np.linspace(top / steps, top, steps)
    nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
    env_l = csr_envelope(pts, bounds, r, l_function, nsim, seed, progress)
    env_g = csr_envelope(pts, bounds, r, pair_correlation, nsim, seed, progress)
    return {
        "trees": len(pts),
        "window": [float(v) for v in bounds],
        "stems_per_ha": len(pts) / area * 1e4,
        "nearest_neighbour_mean": float(nn.mean()),
        "nearest_neighbour_min": float(nn.min()),
        "clark_evans": clark_evans(pts, bounds),
        "nsim": nsim,
        "r": r.tolist(),
        "l_minus_r": (env_l.observed - r).tolist(),
        "l_minus_r_lo": (env_l.lo - r).tolist(),
        "l_minus_r_hi": (env_l.hi - r).tolist(),
        "g": env_g.observed.tolist(),
        "g_lo": env_g.lo.tolist(),
        "g_hi": env_g.hi.tolist(),
    }

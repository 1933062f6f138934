"""Clustered stands: Neyman-Scott cluster processes (Thomas and Matérn cluster), made
inhomogeneous by independent thinning.

Parents form a Poisson process of intensity ``kappa``; each has a Poisson number of offspring
of mean ``offspring``, displaced from it by an isotropic Gaussian of standard deviation
``scale`` (Thomas 1949) or uniformly in a disc of radius ``scale`` (Matérn 1960). The parents
are not part of the pattern. Its intensity is ``kappa * offspring`` and, relative to Poisson,
its K function rises by a term that depends only on the cluster shape (Illian et al. 2008,
*Statistical Analysis and Modelling of Spatial Point Patterns*, section 6.3; spatstat's
``rThomas`` and ``rMatClust``):

* Thomas: ``K(r) = pi r^2 + (1 - exp(-r^2 / (4 scale^2))) / kappa``;
* Matérn cluster: ``K(r) = pi r^2 + h(r / (2 scale)) / kappa`` with
  ``h(z) = 2 + ((8 z^2 - 4) acos z - 2 asin z + 4 z sqrt((1 - z^2)^3) - 6 z sqrt(1 - z^2)) / pi``
  for ``z <= 1`` and 1 beyond.

A recipe's ``[clusters]`` keeps its ``[intensity]``: clusters are drawn at the intensity's
bound ``lambda*`` (``kappa = lambda* / offspring``), then each tree is kept with probability
``lambda(x) / lambda*``, which gives intensity ``lambda(x)`` and leaves the pair-correlation
function of the homogeneous process unchanged (the inhomogeneous cluster process of
Waagepetersen 2007, Biometrics 63:252).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import RecipeError

KINDS = ("thomas", "matern")
MAX_SCALE = 100.0  # metres: a cluster reaches at most 4 x this (Thomas) from its parent


@dataclass(frozen=True)
class Clusters:
    """A cluster process's shape: ``kind`` (thomas, matern), ``scale`` in metres (the
    Gaussian's standard deviation, or the disc's radius) and the mean ``offspring`` of a
    parent before any thinning."""

    kind: str
    scale: float
    offspring: float

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise RecipeError(f"clusters.kind: {self.kind!r} is not one of {', '.join(KINDS)}")
        if not (math.isfinite(self.scale) and 0 < self.scale <= MAX_SCALE):
            raise RecipeError(
                f"clusters.scale: expected metres in (0, {MAX_SCALE:g}], got {self.scale:g}"
            )
        if not (math.isfinite(self.offspring) and 0 < self.offspring <= 10_000):
            raise RecipeError(
                f"clusters.offspring: expected a mean in (0, 10000], got {self.offspring:g}"
            )

    @property
    def reach(self) -> float:
        """How far a tree can stand from its parent (Thomas: 4 standard deviations, where
        the Gaussian has lost all but 0.03 % of its trees; they are dropped)."""
        return 4.0 * self.scale if self.kind == "thomas" else self.scale

    def displacements(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, 2)`` offsets of trees from their parents."""
        if self.kind == "thomas":
            d = rng.normal(0.0, self.scale, size=(n, 2))
            far = np.hypot(d[:, 0], d[:, 1]) > self.reach
            d[far] = np.nan  # beyond the reach: dropped, so every cell sees the same trees
            return d
        radius = self.scale * np.sqrt(rng.uniform(size=n))
        angle = rng.uniform(0.0, 2 * math.pi, size=n)
        return np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])

    def k_function(self, r: np.ndarray, kappa: float) -> np.ndarray:
        """The theoretical K of the homogeneous process with parent intensity ``kappa``."""
        r = np.asarray(r, dtype=float)
        if self.kind == "thomas":
            extra = 1 - np.exp(-(r**2) / (4 * self.scale**2))
        else:
            z = np.minimum(r / (2 * self.scale), 1.0)
            extra = (
                2
                + (
                    (8 * z**2 - 4) * np.arccos(z)
                    - 2 * np.arcsin(z)
                    + 4 * z * np.sqrt((1 - z**2) ** 3)
                    - 6 * z * np.sqrt(1 - z**2)
                )
                / math.pi
            )
        return math.pi * r**2 + extra / kappa

    def describe(self) -> dict:
        return {"kind": self.kind, "scale": self.scale, "offspring": self.offspring}


def family(
    clusters: Clusters, kappa: float, box: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The trees of the parents that fall in ``box``: ``(n, 2)`` positions (anywhere: they
    may leave the box) and ``n`` uniforms for thinning them, in draw order."""
    x0, y0, x1, y1 = box
    n_par = int(rng.poisson(kappa * (x1 - x0) * (y1 - y0)))
    parents = np.column_stack([rng.uniform(x0, x1, n_par), rng.uniform(y0, y1, n_par)])
    counts = rng.poisson(clusters.offspring, size=n_par)
    n = int(counts.sum())
    pts = np.repeat(parents, counts, axis=0) + clusters.displacements(rng, n)
    u = rng.uniform(size=n)
    ok = np.isfinite(pts[:, 0])
    return pts[ok], u[ok]


def simulate(
    clusters: Clusters, kappa: float, bounds: tuple[float, float, float, float],
    rng: np.random.Generator,
) -> np.ndarray:  # fmt: skip
    """A homogeneous cluster pattern in the rectangle ``bounds``, its parents drawn in the
    rectangle grown by the clusters' reach (no edge deficit)."""
    x0, y0, x1, y1 = bounds
    g = clusters.reach
    pts, _ = family(clusters, kappa, (x0 - g, y0 - g, x1 + g, y1 + g), rng)
    inside = (pts[:, 0] >= x0) & (pts[:, 0] < x1) & (pts[:, 1] >= y0) & (pts[:, 1] < y1)
    return pts[inside]

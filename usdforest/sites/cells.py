"""Sites sampled cell by cell: the same forest whatever the tiles, workers or task order.

Every recipe's region is cut into square cells of ``CELL`` metres from its south-west corner;
each cell thins its own candidates, draws its sites' Matérn birth times and marks from its
own random streams (seed, replicate and the cell's column and row), so a cell's sites never
depend on which task samples it. A task samples a block of cells; a hard core looks into the
cells around it (a ring as deep as the hard-core distance), where the same streams give the
same neighbours, so a site is kept or dropped exactly as it would be in one pass over the
whole region. The sites come back in cell order (row by row from the south), and within a
cell in the order drawn (their ``rank``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.seeds import stream
from usdforest.sites.pointprocess import draw_marks, matern_keep, thin
from usdforest.sites.table import Sites

CELL = 250.0  # metres: fixed, so the sites never depend on the tile size


@dataclass(frozen=True)
class _CellRegion:
    """A cell's box of a region: candidates drawn in the box, kept where the region is."""

    region: object
    bounds: tuple[float, float, float, float]

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.region.contains(x, y)


@dataclass(frozen=True, eq=False)
class CellSites:
    """Sites with their ``cell`` (row-major index on the grid) and ``rank`` in it."""

    sites: Sites
    cell: np.ndarray
    rank: np.ndarray


def grid_shape(bounds: tuple[float, float, float, float], side: float) -> tuple[int, int]:
    """Columns and rows of squares of ``side`` from the south-west corner of ``bounds``
    that cover them (at least one each)."""
    x0, y0, x1, y1 = bounds
    return max(1, math.ceil((x1 - x0) / side)), max(1, math.ceil((y1 - y0) / side))


def grid(recipe) -> tuple[int, int]:
    """Columns and rows of cells over the recipe's region."""
    return grid_shape(recipe.region.bounds, CELL)


def cell_of(recipe, xy: np.ndarray) -> np.ndarray:
    """The cell (row-major index) holding each point (points outside: the nearest edge's)."""
    x0, y0, _, _ = recipe.region.bounds
    nx, ny = grid(recipe)
    ij = np.floor((np.asarray(xy, dtype=float).reshape(-1, 2) - [x0, y0]) / CELL)
    ij = np.clip(ij, 0, [nx - 1, ny - 1]).astype(np.int64)
    return ij[:, 1] * nx + ij[:, 0]


def cells_meeting(recipe, box: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
    """``(i0, j0, i1, j1)``: the half-open range of cells that meet the closed ``box``."""
    x0, y0, _, _ = recipe.region.bounds
    nx, ny = grid(recipe)
    bx0, by0, bx1, by1 = box
    eps = 1e-6  # metres: a box edge this close to a cell edge takes the cell beyond too
    i0 = min(max(math.floor((bx0 - x0 - eps) / CELL), 0), nx - 1)
    j0 = min(max(math.floor((by0 - y0 - eps) / CELL), 0), ny - 1)
    i1 = min(max(math.floor((bx1 - x0 + eps) / CELL) + 1, i0 + 1), nx)
    j1 = min(max(math.floor((by1 - y0 + eps) / CELL) + 1, j0 + 1), ny)
    return i0, j0, i1, j1


def _cell_sites(
    recipe, replicate: int, i: int, j: int, lam_star: float, families: dict | None = None
) -> np.ndarray:
    if recipe.inhibition is not None:
        return _inhibited_cell_sites(recipe, replicate, i, j)
    if recipe.clusters is not None:
        return _cluster_cell_sites(recipe, replicate, i, j, lam_star, {} if families is None
                                   else families)  # fmt: skip
    x0, y0, x1, y1 = recipe.region.bounds
    box = (x0 + i * CELL, y0 + j * CELL, min(x0 + (i + 1) * CELL, x1), min(y0 + (j + 1) * CELL, y1))
    rng = stream(recipe.seed, "sites", replicate, "cell", i, j)
    return thin(_CellRegion(recipe.region, box), recipe.intensity, rng, bound=lam_star)


def _inhibited_cell_sites(recipe, replicate: int, i: int, j: int) -> np.ndarray:
    """The trees of a Strauss pattern (simulated over the whole region once per process:
    :mod:`usdforest.sites.inhibition`) that stand in cell ``(i, j)``, in the pattern's order."""
    from usdforest.sites.inhibition import recipe_sites

    pts, cell = recipe_sites(recipe, replicate, cell_of)
    c = j * grid(recipe)[0] + i
    lo, hi = np.searchsorted(cell, [c, c + 1])
    return np.array(pts[lo:hi])


def _cluster_cell_sites(
    recipe, replicate: int, i: int, j: int, lam_star: float, families: dict
) -> np.ndarray:
    """The trees of a cluster process that land in cell ``(i, j)``: the families of the
    parents of every cell within the clusters' reach (their own streams, so a cell's trees
    never depend on who samples it), kept where the region is and with probability
    ``lambda(x) / lambda*`` (:mod:`usdforest.sites.clusters`)."""
    from usdforest.sites.clusters import family
    from usdforest.sites.pointprocess import _refuse

    c = recipe.clusters
    x0, y0, _, _ = recipe.region.bounds
    kappa = lam_star / c.offspring
    reach = math.ceil(c.reach / CELL)
    out = []
    for pj in range(j - reach, j + reach + 1):
        for pi in range(i - reach, i + reach + 1):
            key = (pi, pj)
            if key not in families:
                box = (x0 + pi * CELL, y0 + pj * CELL, x0 + (pi + 1) * CELL, y0 + (pj + 1) * CELL)
                rng = stream(recipe.seed, "clusters", replicate, "cell", pi, pj)
                families[key] = family(c, kappa, box, rng)
            pts, u = families[key]
            mine = (np.floor((pts[:, 0] - x0) / CELL) == i) & (
                np.floor((pts[:, 1] - y0) / CELL) == j
            )
            pts, u = pts[mine], u[mine]
            inside = recipe.region.contains(pts[:, 0], pts[:, 1])
            pts, u = pts[inside], u[inside]
            lam = recipe.intensity.evaluate(pts[:, 0], pts[:, 1])
            if len(lam) and not (lam.min() >= 0 and lam.max() <= lam_star * (1 + 1e-9)):
                _refuse(pts[:, 0], pts[:, 1], lam, lam_star)
            out.append(pts[u * lam_star < lam])
    return np.concatenate(out) if out else np.zeros((0, 2))


def sample_cells(
    recipe, replicate: int, block: tuple[int, int, int, int], ring: int = 0
) -> CellSites:
    """The sites of the cells of ``block`` (``(i0, j0, i1, j1)``, half-open) and of ``ring``
    more cells around it, exactly as one pass over the whole region would give them."""
    i0, j0, i1, j1 = block
    nx, ny = grid(recipe)
    lam_star = recipe.intensity.bound(recipe.region)
    hc_ring = math.ceil(recipe.hard_core / CELL) if recipe.hard_core > 0 else 0
    reach = ring + hc_ring
    cells = [
        (i, j)
        for j in range(max(j0 - reach, 0), min(j1 + reach, ny))
        for i in range(max(i0 - reach, 0), min(i1 + reach, nx))
    ]
    families: dict = {}  # a cluster process's parents, drawn once per call
    xy = [_cell_sites(recipe, replicate, i, j, lam_star, families) for i, j in cells]
    wanted = np.concatenate(
        [
            np.full(len(p), i0 - ring <= i < i1 + ring and j0 - ring <= j < j1 + ring)
            for p, (i, j) in zip(xy, cells, strict=True)
        ]
        or [np.zeros(0, dtype=bool)]
    )
    cell = np.concatenate(
        [np.full(len(p), j * nx + i, dtype=np.int64) for p, (i, j) in zip(xy, cells, strict=True)]
        or [np.zeros(0, dtype=np.int64)]
    )
    pts = np.concatenate(xy).reshape(-1, 2) if xy else np.zeros((0, 2))
    keep = np.ones(len(pts), dtype=bool)
    if hc_ring:
        birth = np.concatenate(
            [
                stream(recipe.seed, "hard-core", replicate, "cell", i, j).uniform(size=len(p))
                for p, (i, j) in zip(xy, cells, strict=True)
            ]
        )
        keep = matern_keep(pts, recipe.hard_core, birth)
    sel = wanted & keep
    pts, cell = pts[sel], cell[sel]
    uniq, start, count = np.unique(cell, return_index=True, return_counts=True)
    rank = np.arange(len(cell)) - np.repeat(start, count)
    names = recipe.species_names
    marks = [
        draw_marks(
            pts[a : a + n],
            [w for _, w in recipe.mix],
            [recipe.variants[n_] for n_ in names],
            recipe.scale.as_tuple(),
            stream(recipe.seed, "marks", replicate, "cell", int(c % nx), int(c // nx)),
            recipe.ground["field"].height if recipe.ground is not None else None,
            names,
            recipe.region.bounds,
        )
        for c, a, n in zip(uniq, start, count, strict=True)
    ]

    def column(f, dtype):
        parts = [getattr(m, f) for m in marks]
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)

    sites = Sites(
        names,
        pts,
        column("species", np.int32),
        column("variant", np.int32),
        column("yaw", float),
        column("scale", float),
    )
    return CellSites(sites, cell, rank)

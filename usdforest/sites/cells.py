"""Sites sampled cell by cell: the same forest whatever the tiles, workers or task order.

A tiled recipe's region is cut into square cells of ``CELL`` metres from its south-west
corner; each cell thins its own candidates, draws its sites' Matérn birth times and marks
from its own random streams (seed, replicate and the cell's column and row), so a cell's
sites never depend on which task samples it. Tasks take blocks of cells; a hard core looks
into the cells around a block (a halo as deep as the hard-core distance), where the same
streams give the same neighbours, so a site is kept or dropped exactly as it would be in one
pass over the whole region. The sites come back in cell order (row by row from the south),
and within a cell in the order drawn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.seeds import stream
from usdforest.sites.pointprocess import draw_marks, matern_keep, thin
from usdforest.sites.table import Sites

CELL = 250.0  # metres: fixed, so the sites never depend on the tile size
BLOCK = 4  # cells per side of a sampling task


@dataclass(frozen=True)
class _CellRegion:
    """A cell's box of a region: candidates drawn in the box, kept where the region is."""

    region: object
    bounds: tuple[float, float, float, float]

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.region.contains(x, y)


def grid(recipe) -> tuple[int, int]:
    """Columns and rows of cells over the recipe's region."""
    x0, y0, x1, y1 = recipe.region.bounds
    return max(1, math.ceil((x1 - x0) / CELL)), max(1, math.ceil((y1 - y0) / CELL))


def blocks(recipe) -> list[tuple[int, int, int, int]]:
    """The sampling tasks: ``(i0, j0, i1, j1)`` ranges of cell columns and rows."""
    nx, ny = grid(recipe)
    return [
        (i, j, min(i + BLOCK, nx), min(j + BLOCK, ny))
        for j in range(0, ny, BLOCK)
        for i in range(0, nx, BLOCK)
    ]


def _cell_sites(recipe, replicate: int, i: int, j: int, lam_star: float) -> np.ndarray:
    x0, y0, x1, y1 = recipe.region.bounds
    box = (x0 + i * CELL, y0 + j * CELL, min(x0 + (i + 1) * CELL, x1), min(y0 + (j + 1) * CELL, y1))
    rng = stream(recipe.seed, "sites", replicate, "cell", i, j)
    return thin(_CellRegion(recipe.region, box), recipe.intensity, rng, bound=lam_star)


def sample_block(recipe, replicate: int, block: tuple[int, int, int, int]) -> dict:
    """The sites of a block's cells (a task): ``cell`` (each site's cell, row-major),
    ``xy`` and the marks."""
    i0, j0, i1, j1 = block
    nx, ny = grid(recipe)
    lam_star = recipe.intensity.bound(recipe.region)
    ring = math.ceil(recipe.hard_core / CELL) if recipe.hard_core > 0 else 0
    cells = [
        (i, j)
        for j in range(max(j0 - ring, 0), min(j1 + ring, ny))
        for i in range(max(i0 - ring, 0), min(i1 + ring, nx))
    ]
    xy = [_cell_sites(recipe, replicate, i, j, lam_star) for i, j in cells]
    own = np.concatenate(
        [
            np.full(len(p), i0 <= i < i1 and j0 <= j < j1)
            for p, (i, j) in zip(xy, cells, strict=True)
        ]
    )
    cell = np.concatenate(
        [np.full(len(p), j * nx + i) for p, (i, j) in zip(xy, cells, strict=True)]
    )
    pts = np.concatenate(xy) if xy else np.zeros((0, 2))
    keep = np.ones(len(pts), dtype=bool)
    if ring:
        birth = np.concatenate(
            [
                stream(recipe.seed, "hard-core", replicate, "cell", i, j).uniform(size=len(p))
                for p, (i, j) in zip(xy, cells, strict=True)
            ]
        )
        keep = matern_keep(pts, recipe.hard_core, birth)
    sel = own & keep
    pts, cell = pts[sel], cell[sel]
    names = recipe.species_names
    marks = []
    for c in np.unique(cell):
        at = cell == c
        marks.append(
            draw_marks(
                pts[at],
                [w for _, w in recipe.mix],
                [recipe.variants[n] for n in names],
                recipe.scale.as_tuple(),
                stream(recipe.seed, "marks", replicate, "cell", int(c % nx), int(c // nx)),
                recipe.ground["field"].height if recipe.ground is not None else None,
            )
        )
    out = {"cell": cell, "xy": pts}
    for f in ("species", "variant", "yaw", "scale"):
        parts = [getattr(m, f) for m in marks]
        out[f] = np.concatenate(parts) if parts else np.zeros(0)
    out["species"] = out["species"].astype(np.int32)
    out["variant"] = out["variant"].astype(np.int32)
    return out


def sample_cells(recipe, replicate: int = 0, client=None):
    """All the recipe's sites, block by block (as tasks on a dask.distributed ``client``,
    or here), in cell order."""
    jobs = blocks(recipe)
    if client is None:
        parts = [sample_block(recipe, replicate, b) for b in jobs]
    else:
        shared = client.scatter(recipe, broadcast=True)
        parts = client.gather(
            [client.submit(sample_block, shared, replicate, b, pure=False) for b in jobs]
        )
    cell = np.concatenate([p["cell"] for p in parts])
    order = np.argsort(cell, kind="stable")
    cols = {f: np.concatenate([p[f] for p in parts])[order] for f in parts[0] if f != "cell"}
    return Sites(
        recipe.species_names,
        cols["xy"].reshape(-1, 2),
        cols["species"],
        cols["variant"],
        cols["yaw"],
        cols["scale"],
    )

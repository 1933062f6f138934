"""Tiles: a forest cut into square tiles, each its own layer loaded as a payload.

The sites are sampled once for the whole region (they depend on the recipe and its seed,
never on the tile size); each tile takes those in its square, stores them about its own
south-west corner (the tile prim's translate, in double precision) and gets an
``extentsHint``, so a stage opened with payloads unloaded still knows where every tile is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Gf, Sdf, Vt

from usdforest.usd.layers import T, attr, extents, prim


@dataclass(frozen=True, eq=False)
class Tile:
    """Tile ``(i, j)`` (east, north) of a grid from ``corner``: the sites ``index`` it holds
    and its south-west ``origin`` (layer frame)."""

    i: int
    j: int
    index: np.ndarray
    origin: np.ndarray

    @property
    def name(self) -> str:
        return f"Tile_{self.i}_{self.j}"


def partition(
    xy: np.ndarray, corner: np.ndarray, size: float, shape: tuple[int, int], *, empty: bool
) -> list[Tile]:
    """The tiles of side ``size`` from ``corner`` on a grid of ``shape`` (columns, rows)
    holding the sites ``xy``, row by row from the south; each site in exactly one (the tile
    whose half-open square holds it; a site on the region's east or north edge in the last
    one). ``empty``: also the tiles that hold no site."""
    nx, ny = shape
    ij = np.floor((np.asarray(xy).reshape(-1, 2) - corner) / size).astype(np.int64)
    ij = np.clip(ij, 0, [nx - 1, ny - 1])
    key = ij[:, 1] * nx + ij[:, 0]
    order = np.argsort(key, kind="stable")
    bounds = np.searchsorted(key[order], np.arange(nx * ny + 1))
    tiles = []
    for k in range(nx * ny):
        idx = np.sort(order[bounds[k] : bounds[k + 1]])
        if len(idx) or empty:
            i, j = k % nx, k // nx
            tiles.append(Tile(i, j, idx, corner + np.array([i, j], dtype=float) * size))
    return tiles


def author_tiles(forest: Sdf.PrimSpec, tiles: list[tuple[Tile, str, np.ndarray]]) -> None:
    """``<forest>/Tiles/<Tile_i_j>``: a payload of each tile's layer (``asset``), moved to
    its origin, with the tile's extent (tile-local) as its ``extentsHint``."""
    group = prim(forest, "Tiles", "Xform")
    group.kind = "group"
    for tile, asset, extent in tiles:
        spec = prim(group, tile.name, "Xform")
        spec.kind = "group"
        spec.payloadList.prependedItems = [Sdf.Payload(asset)]
        attr(spec, "xformOp:translate", T.Double3, Gf.Vec3d(*map(float, tile.origin), 0.0))
        attr(spec, "xformOpOrder", T.TokenArray, Vt.TokenArray(["xformOp:translate"]), uniform=True)
        attr(spec, "extentsHint", T.Float3Array, extents(extent))

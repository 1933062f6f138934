"""Tiles: a forest cut into square tiles, each its own layer loaded as a payload.

Each tile's trees are placed by its own task (:mod:`usdforest.usd.landscape`; they depend on
the recipe and its seed, never on the tile size); each tile stores them about its own
south-west corner (the tile prim's translate, in double precision) and gets an
``extentsHint``, so a stage opened with payloads unloaded still knows where every tile is.
"""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Vt

from usdforest.usd.layers import T, attr, extents, prim


def author_tiles(
    forest: Sdf.PrimSpec, tiles: list[tuple[str, tuple[float, float], str, np.ndarray]]
) -> None:
    """``<forest>/Tiles/<Tile_i_j>``: for each ``(name, origin, asset, extent)``, a payload
    of the tile's layer (``asset``), moved to its ``origin``, with its extent (tile-local)
    as its ``extentsHint``."""
    group = prim(forest, "Tiles", "Xform")
    group.kind = "group"
    for name, origin, asset, extent in tiles:
        spec = prim(group, name, "Xform")
        spec.kind = "group"
        spec.payloadList.prependedItems = [Sdf.Payload(asset)]
        attr(spec, "xformOp:translate", T.Double3, Gf.Vec3d(*map(float, origin), 0.0))
        attr(spec, "xformOpOrder", T.TokenArray, Vt.TokenArray(["xformOp:translate"]), uniform=True)
        attr(spec, "extentsHint", T.Float3Array, extents(extent))

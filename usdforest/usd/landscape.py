"""A tiled forest written tile by tile: each task places its own trees and writes them.

Every tile task gets the recipe, the :class:`~usdforest.sites.local.Plan` and what it needs of
the tree prototypes (:class:`TileKit`, sent to each worker once), places its square's trees
(:func:`usdforest.sites.local.place`), reads their ground heights, and writes
``tiles/Tile_i_j.usdc`` (its trees about its corner, their trunk colliders, its ground) and
``tiles/Tile_i_j.csv``. It returns a :class:`TileSummary` (counts and extent), from which the
root's payloads and the ``tiles.csv`` index are written: no tree travels back to the client.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Sdf

from usdforest.cluster import Progress, run_tasks
from usdforest.errors import UsdForestError
from usdforest.grow.bounds import Bounds
from usdforest.grow.colliders import Capsules
from usdforest.recipe import Recipe
from usdforest.sites.local import Plan, Square, place, survey
from usdforest.sites.table import Sites
from usdforest.sites.terrain import HeightField
from usdforest.usd.ground import add_ground
from usdforest.usd.instances import (
    ProtoSizes,
    instancer_layer,
    level_extent,
    shifted,
    write_trees_csv,
)
from usdforest.usd.layers import prim, save_layer
from usdforest.usd.physics import author_capsules, instance_capsules


@dataclass(frozen=True, eq=False)
class Proto:
    """What a tile needs of a tree prototype: its levels' bounds and its colliders."""

    bounds: Mapping[str, Bounds]
    colliders: Capsules


@dataclass(frozen=True, eq=False)
class TileKit:
    """What every tile task shares: the recipe, the plan, the prototypes (their names,
    bounds and colliders, sizes for ``trees.csv`` and asset paths seen from ``tiles/``) and
    the layers' anchor."""

    recipe: Recipe
    plan: Plan
    prototypes: tuple[tuple[str, int], ...]
    protos: tuple[Proto, ...]
    proto_sizes: ProtoSizes
    assets: tuple[str, ...]
    anchor: np.ndarray


@dataclass(frozen=True)
class TileSummary:
    """A written tile: its name, south-west ``origin`` (layers' frame), trees per species,
    its ``extent`` (tile-local, trees and ground) and its trees' alone."""

    name: str
    origin: tuple[float, float]
    by_species: tuple[int, ...]
    extent: np.ndarray
    tree_extent: np.ndarray

    @property
    def trees(self) -> int:
        return sum(self.by_species)


def survey_task(square: Square, recipe: Recipe):
    """:func:`usdforest.sites.local.survey` as a task (the shared argument last)."""
    return survey(recipe, square)


def tile_ground(recipe: Recipe, anchor: np.ndarray, square: Square) -> HeightField:
    """The ground under a tile, about its corner: the cells of the forest's ground that meet
    its square (the same triangles its trees stand on), out to the ground's edge for a tile
    on the region's edge (the margin)."""
    ground = shifted(recipe.ground["field"], anchor)
    x0, y0, x1, y1 = (np.array(recipe.region.bounds) - np.tile(anchor, 2)).tolist()
    size = square.size
    ox, oy = (float(v) for v in square.origin - anchor)
    box = (
        -np.inf if ox <= x0 else ox,
        -np.inf if oy <= y0 else oy,
        np.inf if ox + size >= x1 else ox + size,
        np.inf if oy + size >= y1 else oy + size,
    )
    part = ground.window(box)
    bx0, by0, bx1, by1 = part.bounds
    return HeightField(part.z, (bx0 - ox, by0 - oy, bx1 - ox, by1 - oy))


def tile_task(folder: Path, square: Square, kit: TileKit) -> TileSummary | None:
    """Place one tile's trees and write its layer and CSV (a task); None for a tile with
    neither trees nor ground (nothing written)."""
    if not folder.is_dir():  # never create it: on a worker that does not share the disk,
        # or after the build was stopped and its staging folder removed
        raise UsdForestError(f"{folder} is not there on this worker (a shared disk is needed)")
    recipe, anchor = kit.recipe, kit.anchor
    placed = place(recipe, square, kit.plan)
    rows = placed.sites
    if len(rows) == 0 and recipe.ground is None:
        return None
    origin = square.origin - anchor
    xy = rows.xy - anchor
    z = np.zeros(len(rows), dtype=np.float32)
    if recipe.ground is not None:
        z = shifted(recipe.ground["field"], anchor).height(xy[:, 0], xy[:, 1]).astype(np.float32)
    local = Sites(rows.names, xy - origin, rows.species, rows.variant, rows.yaw, rows.scale)
    extent = tree_extent = level_extent(local, placed.proto_index, list(kit.protos), recipe.lod, z)
    ground = tile_ground(recipe, anchor, square) if recipe.ground is not None else None
    if ground is not None:  # the tile's hint holds its ground too
        gx0, gy0, gx1, gy1 = ground.bounds
        box = np.array([[gx0, gy0, ground.z.min()], [gx1, gy1, ground.z.max()]])
        extent = np.stack([np.minimum(extent[0], box[0]), np.maximum(extent[1], box[1])])
    layer = instancer_layer(
        local,
        kit.prototypes,
        placed.proto_index,
        z,
        extent,
        list(kit.assets),
        recipe.lod,
        root="Tile",
        ids=placed.ids,
    )
    if recipe.colliders != "none":
        caps, names = instance_capsules(
            [p.colliders for p in kit.protos],
            placed.proto_index,
            np.column_stack([local.xy, z]),
            local.yaw,
            local.scale,
        )
        with Sdf.ChangeBlock():
            author_capsules(prim(layer.GetPrimAtPath("/Tile"), "Colliders", "Scope"), caps, names)
    if ground is not None:
        with Sdf.ChangeBlock():
            add_ground(
                layer.GetPrimAtPath("/Tile"),
                ground,
                color=recipe.ground["color"],
                litter=recipe.groundcover is not None and recipe.groundcover.litter,
            )
    save_layer(layer, folder / f"{square.name}.usdc")
    write_trees_csv(
        folder / f"{square.name}.csv", rows, kit.proto_sizes, placed.proto_index, z, placed.ids
    )
    counts = np.bincount(rows.species, minlength=len(rows.names))
    return TileSummary(
        square.name,
        (float(origin[0]), float(origin[1])),
        tuple(int(c) for c in counts),
        extent,
        tree_extent,
    )


def write_tiles(
    folder: Path, squares: Sequence[Square], kit: TileKit, client, tick: Progress
) -> list[TileSummary]:
    """Every tile (tasks on ``client``, or here), the written ones' summaries in tile
    order."""
    folder.mkdir()
    done = run_tasks(
        client, tile_task, [(folder, sq) for sq in squares], kit, tick, "writing tiles"
    )
    written = [t for t in done if t is not None]
    missing = [t.name for t in written if not (folder / f"{t.name}.usdc").is_file()]
    if missing:  # a worker wrote somewhere this process cannot see
        raise UsdForestError(
            f"tiles {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''} were not "
            f"written to {folder}: the Dask workers must share this disk"
        )
    return written


def write_tiles_index(path: Path, tiles: Sequence[TileSummary], anchor: np.ndarray) -> None:
    """``tiles.csv``, the index of a tiled forest's trees: one row per tile (its layer and
    CSV under ``tiles/``, its trees, its south-west corner and its extent in recipe
    coordinates)."""
    ax, ay = (float(a) for a in anchor)
    lines = ["tile,layer,csv,trees,x0,y0,min_x,min_y,min_z,max_x,max_y,max_z"]
    for t in tiles:
        ox, oy = t.origin[0] + ax, t.origin[1] + ay
        lo = t.extent[0] + [ox, oy, 0.0]
        hi = t.extent[1] + [ox, oy, 0.0]
        box = ",".join(f"{v:.3f}" for v in (*lo, *hi))
        lines.append(
            f"{t.name},tiles/{t.name}.usdc,tiles/{t.name}.csv,{t.trees},{ox:.4f},{oy:.4f},{box}"
        )
    path.write_text("\n".join(lines) + "\n")

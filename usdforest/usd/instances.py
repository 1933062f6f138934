"""The forest's trees as USD: a PointInstancer over tree assets, its exact extent, and the
ground truth ``trees.csv`` (shared by untiled forests and each tile of a tiled one)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Sdf, Vt

from usdforest.grow.architecture import BREAST_HEIGHT
from usdforest.grow.bounds import yawed_extent
from usdforest.recipe import Recipe
from usdforest.sites.table import Sites
from usdforest.sites.terrain import HeightField
from usdforest.usd.layers import T, attr, extents, new_layer, prim, vec3f
from usdforest.usd.tree import TreeBuild


def prototype_name(species: str, variant: int) -> str:
    """A valid prim name: ``paper-rule-1``, 2 -> ``Paper_rule_1_2``."""
    base = re.sub(r"[^A-Za-z0-9_]", "_", species) or "Tree"
    if base[0].isdigit():
        base = "T_" + base
    return f"{base[0].upper()}{base[1:]}_{variant}"


@dataclass(frozen=True, eq=False)
class ForestBuild:
    """What a build produced (numbers for the CLI, tests and benchmarks)."""

    # the trees (an untiled build; a tiled one's stay in its tiles: None)
    sites: Sites | None
    prototypes: tuple[tuple[str, int], ...]  # (species, variant) per prototype index
    proto_index: np.ndarray | None
    trees: dict[tuple[str, int], TreeBuild]
    extent: np.ndarray  # of the trees at the level the forest selects and of their proxies
    out: Path
    assets: Path
    ground_z: np.ndarray | None  # (n,) the ground's height under each tree (0 on a plane)
    trees_by_species: dict[str, int]
    # recipe x, y at the layers' origin: (0, 0), or for a recipe in a projected CRS its
    # region's south-west corner in whole metres, so float32 positions keep their millimetres
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(2))
    n_tiles: int = 0  # payload tiles (0: one instancer layer)

    @property
    def n_trees(self) -> int:
        return sum(self.trees_by_species.values())


def instancer_extent(
    sites: Sites,
    proto_index: np.ndarray,
    trees: Sequence[TreeBuild],
    level: str,
    ground_z: np.ndarray,
) -> np.ndarray:
    """Exact extent of the yawed, scaled instances of ``trees`` (one per prototype) at level
    of detail ``level``, from each tree's footprint (the hull of its points on the ground)."""
    b = [t.bounds[level] for t in trees]
    # the turn a reader computes from the stored half-precision quaternion (0, 0, k, r)
    q = yaw_quaternions(sites.yaw).astype(np.float16).astype(np.float64)
    k, r = q[:, 2], q[:, 3]
    return yawed_extent(
        [x.footprint for x in b],
        np.array([x.extent[:, 2] for x in b]),
        proto_index,
        sites.xy.astype(np.float32).astype(np.float64),
        (1.0 - 2.0 * k * k, 2.0 * k * r),
        sites.scale.astype(np.float32).astype(np.float64),
        ground_z.astype(np.float32).astype(np.float64),
    )


def yaw_quaternions(yaw_deg: np.ndarray) -> np.ndarray:
    """``(n, 4)`` quaternions (x, y, z, w) for rotations by ``yaw`` degrees about +Z."""
    half = np.radians(yaw_deg) / 2
    q = np.zeros((len(yaw_deg), 4))
    q[:, 2] = np.sin(half)
    q[:, 3] = np.cos(half)
    return q


def instancer_layer(
    sites: Sites,
    prototypes: Sequence[tuple[str, int]],
    proto_index: np.ndarray,
    ground_z: np.ndarray,
    extent: np.ndarray,
    tree_assets: list[str],
    lod: str = "full",
    *,
    root: str = "Forest",
    ids: np.ndarray | None = None,
) -> Sdf.Layer:
    """``/<root>/Trees`` PointInstancer over the sites (standing at ``ground_z``, bounded
    by ``extent``), one prototype per tree asset, each selecting the tree's ``lod`` variant
    (switch it on a prototype without rebuilding); ``ids``: the trees' ids in ``trees.csv``
    (default 0..n-1)."""
    layer = new_layer(root, comment="usdforest forest instances")
    n = len(sites)
    with Sdf.ChangeBlock():
        forest = prim(layer, root, "Xform")
        forest.kind = "assembly" if root == "Forest" else "group"
        trees = prim(forest, "Trees", "PointInstancer")
        trees.kind = "group"
        protos = prim(trees, "Prototypes", "Scope")
        protos.kind = "group"
        targets = []
        for (species, variant), asset in zip(prototypes, tree_assets, strict=True):
            p = prim(protos, prototype_name(species, variant), "Xform")
            p.referenceList.prependedItems = [Sdf.Reference(asset)]
            p.variantSelections["lod"] = lod
            targets.append(p.path)
        r = Sdf.RelationshipSpec(trees, "prototypes", custom=False)
        r.targetPathList.explicitItems = targets
        pos = np.zeros((n, 3), dtype=np.float32)
        pos[:, :2] = sites.xy
        pos[:, 2] = ground_z
        attr(trees, "positions", T.Point3fArray, vec3f(pos))
        attr(
            trees,
            "orientations",
            T.QuathArray,
            Vt.QuathArray.FromNumpy(yaw_quaternions(sites.yaw).astype(np.float16)),
        )
        attr(trees, "scales", T.Float3Array, vec3f(np.repeat(sites.scale[:, None], 3, axis=1)))
        attr(
            trees,
            "protoIndices",
            T.IntArray,
            Vt.IntArray.FromNumpy(np.asarray(proto_index, dtype=np.int32)),
        )
        # (a copy: an array unpickled from a Dask task's buffers has a format Vt refuses)
        ids = np.arange(n, dtype=np.int64) if ids is None else np.array(ids, dtype=np.int64)
        attr(trees, "ids", T.Int64Array, Vt.Int64Array.FromNumpy(ids))
        attr(trees, "extent", T.Float3Array, extents(extent))
    return layer


def anchor_of(recipe: Recipe) -> np.ndarray:
    """Where the layers' origin is in recipe coordinates (see :class:`ForestBuild`)."""
    if recipe.crs is None:
        return np.zeros(2)
    x0, y0, _, _ = recipe.region.bounds
    return np.floor([x0, y0])


def shifted(ground: HeightField, anchor: np.ndarray) -> HeightField:
    """``ground`` with its bounds moved to the layers' frame."""
    if not anchor.any():
        return ground
    x0, y0, x1, y1 = ground.bounds
    ax, ay = (float(a) for a in anchor)
    return HeightField(ground.z, (x0 - ax, y0 - ay, x1 - ax, y1 - ay))


def level_extent(
    sites: Sites, proto_index: np.ndarray, trees: list[TreeBuild], lod: str, ground_z: np.ndarray
) -> np.ndarray:
    """The instancer extent of ``sites`` at level ``lod`` and their proxies (see
    :func:`instancer_extent`)."""
    proxy = instancer_extent(sites, proto_index, trees, "proxy", ground_z)
    if lod == "proxy" or len(sites) == 0:
        return proxy
    selected = instancer_extent(sites, proto_index, trees, lod, ground_z)
    return np.stack([np.minimum(selected[0], proxy[0]), np.maximum(selected[1], proxy[1])])


@dataclass(frozen=True, eq=False)
class ProtoSizes:
    """What ``trees.csv`` reads of each prototype: its ``height`` as grown (P,), the girth
    tape on its stem (``girths``: an object whose ``dbh(scale)`` gives the DBH of the
    prototype scaled by ``scale``; see :mod:`usdforest.usd.trunk`) and its stem's direction
    (``axes`` (P, 3), +Z for an upright one)."""

    height: np.ndarray
    girths: tuple
    axes: np.ndarray

    def dbh(self, proto_index: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """Each tree's DBH: its prototype's girth tape 1.3 m up its scaled stem."""
        out = np.full(len(proto_index), np.nan)
        for k, girth in enumerate(self.girths):
            at = np.flatnonzero(proto_index == k)
            if len(at) and girth is not None:
                out[at] = girth.dbh(scale[at])
        return out


def write_trees_csv(
    path: Path,
    sites: Sites,
    sizes: ProtoSizes,
    proto_index: np.ndarray,
    z: np.ndarray,
    ids: np.ndarray | None = None,
) -> None:
    """``trees.csv``: one row per tree: where its stem meets the ground (x, y, z), its
    height (its scale times its prototype's), its DBH (a girth tape 1.3 m up its stem,
    perpendicular to it: :class:`ProtoSizes`) and where the stem's axis passes 1.3 m up it
    (``x_bh, y_bh, z_bh``: the stem leans)."""
    from usdforest import csvtext

    height = sizes.height[proto_index] * sites.scale
    dbh = sizes.dbh(proto_index, sites.scale)
    q = yaw_quaternions(sites.yaw).astype(np.float16).astype(np.float64)  # as stored
    c, s_ = 1.0 - 2.0 * q[:, 2] ** 2, 2.0 * q[:, 2] * q[:, 3]  # cos, sin of the yaw
    a = sizes.axes[proto_index] * BREAST_HEIGHT
    bh = np.stack([c * a[:, 0] - s_ * a[:, 1], s_ * a[:, 0] + c * a[:, 1], a[:, 2]], axis=1)
    with path.open("wb") as f:
        f.write(b"id,x,y,z,species,variant,yaw,scale,height,dbh,x_bh,y_bh,z_bh\n")
        csvtext.write_rows(
            f,
            len(sites),
            lambda i: [
                csvtext.integers(np.arange(i.start, i.stop) if ids is None else ids[i]),
                csvtext.fixed(sites.xy[i, 0], 4),
                csvtext.fixed(sites.xy[i, 1], 4),
                csvtext.fixed(z[i], 4),
                csvtext.labels(sites.species[i], sites.names),
                csvtext.integers(sites.variant[i]),
                csvtext.fixed(sites.yaw[i], 3),
                csvtext.fixed(sites.scale[i], 4),
                csvtext.fixed(height[i], 3),
                csvtext.fixed(dbh[i], 4),
                csvtext.fixed(sites.xy[i, 0] + bh[i, 0], 4),
                csvtext.fixed(sites.xy[i, 1] + bh[i, 1], 4),
                csvtext.fixed(z[i] + bh[i, 2], 4),
            ],
        )

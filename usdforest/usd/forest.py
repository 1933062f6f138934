"""The forest: an interface layer, a PointInstancer layer, tree assets and ground truth.

::

    forest.usda                 /Forest  Xform, kind assembly, defaultPrim; sublayers instances,
                                colliders and ground; /Forest/PhysicsScene only if asked
    forest_assets/
      instances.usdc            /Forest/Trees  PointInstancer (kind group) with positions,
                                orientations (quath), scales, protoIndices, ids (int64), extent
                                /Forest/Trees/Prototypes (Scope, kind group)/<Species>_<k>
                                    -> trees/<species>_<k>.usdc
      trees/<species>_<k>.usdc  tree assets (/Tree, kind component)
      templates/<name>.usdc     the CAD templates the trees reference
      colliders.usdc            /Forest/Colliders: one capsule per trunk where the tree stands
      ground.usdc               /Forest/Ground: the plane or height field (collider, label)
      trees.csv                 ground truth, one row per instance
      pipeline.toml             the resolved recipe (seed included)
    forest_assets/thumbnail.png a 256x256 thumbnail (customLayerData.thumbnail)
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import tomli_w
from pxr import Gf, Sdf, Vt

from usdforest.atomic import publish, refuse_overwrite, staging_folder
from usdforest.errors import UsdForestError
from usdforest.grow.architecture import scaled_dbh
from usdforest.grow.bounds import EMPTY_EXTENT, Bounds, yawed_extent
from usdforest.grow.colliders import Capsules
from usdforest.recipe import Recipe, resolved_toml
from usdforest.sites.sampling import Sites, sample_sites
from usdforest.sites.terrain import HeightField
from usdforest.usd.ground import add_ground, ground_layer
from usdforest.usd.layers import T, attr, extents, new_layer, prim, save_layer, vec3f
from usdforest.usd.physics import (
    add_physics_scene,
    author_capsules,
    collision_layer,
    instance_capsules,
)
from usdforest.usd.tiles import author_tiles, partition
from usdforest.usd.tree import TreeBuild, build_tree, copy_templates, tree_layer

THUMBNAIL = "thumbnail.png"  # inside the assets folder

Progress = Callable[[str, int, int], None]


def prototype_name(species: str, variant: int) -> str:
    """A valid prim name: ``paper-rule-1``, 2 -> ``Paper_rule_1_2``."""
    base = re.sub(r"[^A-Za-z0-9_]", "_", species) or "Tree"
    if base[0].isdigit():
        base = "T_" + base
    return f"{base[0].upper()}{base[1:]}_{variant}"


@dataclass(frozen=True, eq=False)
class ForestBuild:
    """What a build produced (numbers for the CLI, tests and benchmarks)."""

    sites: Sites
    prototypes: tuple[tuple[str, int], ...]  # (species, variant) per prototype index
    proto_index: np.ndarray
    trees: dict[tuple[str, int], TreeBuild]
    extent: np.ndarray  # of the trees at the level the forest selects and of their proxies
    out: Path
    assets: Path
    ground_z: np.ndarray  # (n,) the ground's height under each tree (0 on a plane)
    # recipe x, y at the layers' origin: (0, 0), or for a recipe in a projected CRS its
    # region's south-west corner in whole metres, so float32 positions keep their millimetres
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(2))
    n_tiles: int = 0  # payload tiles (0: one instancer layer)

    @property
    def n_trees(self) -> int:
        return len(self.sites)


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
    build: ForestBuild,
    tree_assets: list[str],
    lod: str = "full",
    *,
    root: str = "Forest",
    ids: np.ndarray | None = None,
) -> Sdf.Layer:
    """``/<root>/Trees`` PointInstancer over the sites, one prototype per tree asset, each
    selecting the tree's ``lod`` variant (switch it on a prototype without rebuilding);
    ``ids``: the trees' ids in ``trees.csv`` (default 0..n-1)."""
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
        for (species, variant), asset in zip(build.prototypes, tree_assets, strict=True):
            p = prim(protos, prototype_name(species, variant), "Xform")
            p.referenceList.prependedItems = [Sdf.Reference(asset)]
            p.variantSelections["lod"] = lod
            targets.append(p.path)
        r = Sdf.RelationshipSpec(trees, "prototypes", custom=False)
        r.targetPathList.explicitItems = targets
        pos = np.zeros((n, 3), dtype=np.float32)
        pos[:, :2] = sites.xy
        pos[:, 2] = build.ground_z
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
            Vt.IntArray.FromNumpy(build.proto_index.astype(np.int32)),
        )
        # (a copy: an array unpickled from a Dask task's buffers has a format Vt refuses)
        ids = np.arange(n, dtype=np.int64) if ids is None else np.array(ids, dtype=np.int64)
        attr(trees, "ids", T.Int64Array, Vt.Int64Array.FromNumpy(ids))
        attr(trees, "extent", T.Float3Array, extents(build.extent))
    return layer


def interface_layer(
    build: ForestBuild,
    recipe: Recipe,
    sublayers: list[str],
    thumbnail: str | None = None,
    tiles: list | None = None,
) -> Sdf.Layer:
    """``forest.usda``: ``/Forest`` (assembly) over the instancer and collision sublayers
    (or the ``tiles``' payloads, see :func:`usdforest.usd.tiles.author_tiles`), with a
    physics scene only when the recipe asks for one."""
    layer = new_layer("Forest", comment="usdforest forest")
    for sub in sublayers:
        layer.subLayerPaths.append(sub)
    data = {}
    if thumbnail:
        data["thumbnail"] = Sdf.AssetPath(thumbnail)
    if recipe.crs:  # where the stage's origin is on the map
        data["crs"] = recipe.crs
        data["crsOrigin"] = Gf.Vec2d(*(float(v) for v in _stage_origin(build, recipe)))
    if data:
        layer.customLayerData = data
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        forest.assetInfo = {
            "name": build.out.stem,
            "identifier": Sdf.AssetPath(f"./{build.out.name}"),
        }
        if recipe.origin == "centre":
            # recipe coordinates stay in trees.csv; the stage puts the plot's centre at 0, 0
            cx, cy = _stage_origin(build, recipe) - build.anchor
            attr(forest, "xformOp:translate", T.Double3, Gf.Vec3d(-cx, -cy, 0))
            attr(
                forest,
                "xformOpOrder",
                T.TokenArray,
                Vt.TokenArray(["xformOp:translate"]),
                uniform=True,
            )
        counts = np.bincount(build.sites.species, minlength=len(build.sites.names))
        forest.customData = {
            "usdforest": {
                "seed": recipe.seed,
                "trees": build.n_trees,
                "treesBySpecies": {
                    n: int(c) for n, c in zip(build.sites.names, counts, strict=True)
                },
                "prototypes": len(build.prototypes),
                "regionBounds": Vt.DoubleArray([float(b) for b in recipe.region.bounds]),
                "regionArea": round(float(recipe.region.area), 3),
                "pipeline": "./" + f"{build.assets.name}/pipeline.toml",
            }
        }
        attr(forest, "extentsHint", T.Float3Array, extents(_extents_hint(build, recipe)))
        if tiles:
            author_tiles(forest, tiles)
        if recipe.physics_scene:
            add_physics_scene(forest)
    return layer


def _stage_origin(build: ForestBuild, recipe: Recipe) -> np.ndarray:
    """The recipe x, y at the stage's origin: the plot's centre (``origin = "centre"``), else
    the layers' anchor (the recipe's own origin, or a georeferenced region's corner)."""
    if recipe.origin == "centre":
        x0, y0, x1, y1 = recipe.region.bounds
        return np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    return np.asarray(build.anchor, dtype=float)


def _anchor(recipe: Recipe) -> np.ndarray:
    """Where the layers' origin is in recipe coordinates (see :class:`ForestBuild`)."""
    if recipe.crs is None:
        return np.zeros(2)
    x0, y0, _, _ = recipe.region.bounds
    return np.floor([x0, y0])


def _shifted(ground: HeightField, anchor: np.ndarray) -> HeightField:
    """``ground`` with its bounds moved to the layers' frame."""
    if not anchor.any():
        return ground
    x0, y0, x1, y1 = ground.bounds
    ax, ay = (float(a) for a in anchor)
    return HeightField(ground.z, (x0 - ax, y0 - ay, x1 - ax, y1 - ay))


def _extents_hint(build: ForestBuild, recipe: Recipe) -> np.ndarray:
    """``/Forest``'s extentsHint: one box, for the default purpose, holding the ground and
    the trees (``/Forest/Trees`` is a default-purpose prim: its whole extent, proxies
    included, counts there, as ``UsdGeomModelAPI.ComputeExtentsHint`` finds)."""
    boxes = []
    if recipe.ground is not None:
        ground = _shifted(recipe.ground["field"], build.anchor)
        x0, y0, x1, y1 = ground.bounds
        boxes.append(np.array([[x0, y0, ground.z.min()], [x1, y1, ground.z.max()]]))
    if build.n_trees:
        boxes.append(build.extent)
    if not boxes:
        return EMPTY_EXTENT
    return np.stack([np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)])


@dataclass(frozen=True, eq=False)
class _Proto:
    """What a tile needs of a tree prototype: its levels' bounds and its colliders."""

    bounds: Mapping[str, Bounds]
    colliders: Capsules


def _write_tiles(
    staged: Path,
    build: ForestBuild,
    recipe: Recipe,
    csv_sites: Sites,
    proto_sizes: np.ndarray,
    tree_assets: list[str],
    trees: list[TreeBuild],
    client=None,
    tick: Progress | None = None,
) -> list:
    """Each tile's layer (``tiles/Tile_i_j.usdc``: its trees about its corner, their trunk
    colliders) and CSV, as tasks on ``client`` (a dask.distributed Client) or one after
    another; returns ``(tile, asset, extent)`` for the root's payloads, in tile order."""
    folder = staged / "tiles"
    folder.mkdir()
    x0, y0, _, _ = recipe.region.bounds
    corner = np.array([x0, y0]) - build.anchor
    assets = ["." + a for a in tree_assets]  # ./trees/x.usdc, seen from tiles/
    protos = [_Proto(t.bounds, t.colliders) for t in trees]
    x1, y1 = recipe.region.bounds[2:]
    shape = (
        max(1, math.ceil((x1 - x0) / recipe.tiles)),
        max(1, math.ceil((y1 - y0) / recipe.tiles)),
    )
    # with a ground, every tile carries its part of it, trees or none
    tiles = partition(build.sites.xy, corner, recipe.tiles, shape, empty=recipe.ground is not None)
    jobs = []
    for tile in tiles:
        i = tile.index
        s, c = build.sites, csv_sites
        local = Sites(
            s.names, s.xy[i] - tile.origin, s.species[i], s.variant[i], s.yaw[i], s.scale[i]
        )
        part = replace(
            build,
            sites=local,
            proto_index=build.proto_index[i],
            ground_z=build.ground_z[i],
            trees={},
        )
        rows = Sites(c.names, c.xy[i], c.species[i], c.variant[i], c.yaw[i], c.scale[i])
        ground = None
        if recipe.ground is not None:
            ground = (_tile_ground(recipe, build, tile), recipe.ground["color"])
        jobs.append(
            (folder, tile, part, rows, proto_sizes, assets, recipe.lod, recipe.colliders, ground)
        )
    tick = tick or (lambda stage, done, total: None)
    if client is None:
        extents = []
        for k, job in enumerate(jobs):
            tick("writing tiles", k, len(jobs))
            extents.append(_tile_job(*job, protos))
    else:
        extents = _run_tasks(client, _tile_job, jobs, protos, tick)
    missing = [t.name for t in tiles if not (folder / f"{t.name}.usdc").is_file()]
    if missing:  # a worker wrote somewhere this process cannot see
        raise UsdForestError(
            f"tiles {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''} were not "
            f"written to {folder}: the Dask workers must share this disk"
        )
    tick("writing tiles", len(jobs), len(jobs))
    return [
        (tile, f"./{build.assets.name}/tiles/{tile.name}.usdc", extent)
        for tile, extent in zip(tiles, extents, strict=True)
    ]


def _tile_job(
    folder: Path,
    tile,
    part: ForestBuild,
    rows: Sites,
    proto_sizes: np.ndarray,
    assets: list[str],
    lod: str,
    colliders: str,
    ground: tuple[HeightField, Sequence[float]] | None,
    protos: list[_Proto],
) -> np.ndarray:
    """Write one tile's layer and CSV (a task: every input travels with it); its extent,
    trees and ground."""
    if not folder.is_dir():  # never create it: on a worker that does not share the disk,
        # or after the build was stopped and its staging folder removed
        raise UsdForestError(f"{folder} is not there on this worker (a shared disk is needed)")
    local, z = part.sites, part.ground_z
    extent = _level_extent(local, part.proto_index, protos, lod, z)
    if ground is not None:  # the tile's hint holds its ground too
        gx0, gy0, gx1, gy1 = ground[0].bounds
        gz = ground[0].z
        box = np.array([[gx0, gy0, gz.min()], [gx1, gy1, gz.max()]])
        extent = np.stack([np.minimum(extent[0], box[0]), np.maximum(extent[1], box[1])])
    part = replace(part, extent=extent)
    layer = instancer_layer(local, part, assets, lod, root="Tile", ids=tile.index)
    if colliders != "none":
        caps, names = instance_capsules(
            [p.colliders for p in protos],
            part.proto_index,
            np.column_stack([local.xy, z]),
            local.yaw,
            local.scale,
        )
        with Sdf.ChangeBlock():
            author_capsules(prim(layer.GetPrimAtPath("/Tile"), "Colliders", "Scope"), caps, names)
    if ground is not None:
        with Sdf.ChangeBlock():
            add_ground(layer.GetPrimAtPath("/Tile"), ground[0], color=ground[1])
    save_layer(layer, folder / f"{tile.name}.usdc")
    _write_csv(folder / f"{tile.name}.csv", rows, proto_sizes, part.proto_index, z, ids=tile.index)
    return extent


def _tile_ground(recipe: Recipe, build: ForestBuild, tile) -> HeightField:
    """The ground under a tile, about its corner: the cells of the forest's ground that meet
    its square (the same triangles its trees stand on), out to the ground's edge for a tile
    on the region's edge (the margin)."""
    ground = _shifted(recipe.ground["field"], build.anchor)
    x0, y0, x1, y1 = (np.array(recipe.region.bounds) - np.tile(build.anchor, 2)).tolist()
    size = recipe.tiles
    ox, oy = (float(v) for v in tile.origin)
    box = (
        -np.inf if ox <= x0 else ox,
        -np.inf if oy <= y0 else oy,
        np.inf if ox + size >= x1 else ox + size,
        np.inf if oy + size >= y1 else oy + size,
    )
    part = ground.window(box)
    bx0, by0, bx1, by1 = part.bounds
    return HeightField(part.z, (bx0 - ox, by0 - oy, bx1 - ox, by1 - oy))


def _run_tasks(client, fn, jobs: list[tuple], shared_arg, tick: Progress) -> list:
    """``fn(*job, shared_arg)`` for every job on ``client``, results in job order. The first
    failure stops the rest and is reported as the task's error; so does an interruption,
    after the running tasks have finished (they write into the staging folder)."""
    from distributed import as_completed

    shared = client.scatter(shared_arg, broadcast=True)
    futures = [client.submit(fn, *job, shared, pure=False) for job in jobs]
    try:
        for k, f in enumerate(as_completed(futures)):
            tick("writing tiles", k, len(jobs))
            if f.status == "error":
                exc = f.exception()
                if isinstance(exc, UsdForestError):
                    raise exc
                raise UsdForestError(f"a tile task failed: {type(exc).__name__}: {exc}")
        return client.gather(futures)
    except BaseException:
        client.cancel(futures, force=True)
        _settle(client)
        raise


def _settle(client, timeout: float = 30.0) -> None:
    """Wait (up to ``timeout`` s) until no worker is running a task."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            busy = client.run(lambda dask_worker: len(dask_worker.state.executing))
        except Exception:
            return
        if not any(busy.values()):
            return
        time.sleep(0.1)


@contextmanager
def _dask_client(workers: int, scheduler: str | None):
    """A dask.distributed client for a tiled build: the cluster at ``scheduler``, a local
    cluster of ``workers`` processes, or None (tiles written here) for one worker."""
    if scheduler is None and workers <= 1:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise UsdForestError(
            "building tiles on Dask needs dask.distributed: pip install 'usdforest[dask]'"
        ) from None
    import logging
    import os

    logging.getLogger("distributed").setLevel(logging.ERROR)
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")  # (the workers too)
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, ValueError, TypeError) as exc:
            raise UsdForestError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        with client:
            yield client
        return
    with (
        LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def _sized_sites(recipe: Recipe, sites: Sites) -> tuple[Sites, dict, np.ndarray]:
    """Allometric species' trees sized one by one and grouped into size classes
    (:mod:`usdforest.sites.stand`): the sites with each tree's class as its variant and its height
    over the class's as its scale, the class targets by species and the direction each
    tree's crown grows away from its neighbours (NaN: none)."""
    from usdforest.sites.stand import stand_sizes, with_sizes

    allometric = {n for n in sites.names if recipe.species[n].species.allometry is not None}
    if not allometric or len(sites) == 0:
        return sites, {}, np.full(len(sites), np.nan)
    n = len(sites)
    given = {k: np.full(n, np.nan) for k in ("dbh", "height", "crown_radius")}
    yawed = np.zeros(n, dtype=bool)
    if recipe.sites is not None:
        for i, row in enumerate(recipe.sites):
            yawed[i] = "yaw" in row
            for k in given:
                if k in row:
                    given[k][i] = row[k]
    sizes = stand_sizes(
        {name: recipe.species[name].species for name in sites.names},
        {name: e.stand for name, e in recipe.species.items() if e.stand is not None},
        sites.names,
        sites.species,
        sites.xy,
        given["dbh"],
        given["height"],
        given["crown_radius"],
        float(recipe.region.area),
        {name: recipe.variants[name] for name in sites.names},
        recipe.seed,
    )
    # a tree whose yaw the inventory gives keeps it
    return with_sizes(sites, sizes, allometric), sizes.classes, np.where(yawed, np.nan, sizes.away)


def _turned_away(
    sites: Sites, away: np.ndarray, trees: list[TreeBuild], proto_index: np.ndarray
) -> Sites:
    """Each tree pressed by neighbours turned so that its prototype's one-sided crown (the
    mean of its leaves' xy, measured on the grown tree) points ``away`` from them."""
    pressed = np.isfinite(away)
    if not pressed.any():
        return sites
    lean = np.array(
        [
            np.degrees(np.arctan2(*t.placement.leaf_position[:, 1::-1].mean(axis=0)))
            if t.size is not None and t.size.asymmetry > 0 and len(t.placement.leaf_position)
            else np.nan
            for t in trees
        ]
    )
    turn = np.round(away - lean[proto_index], 3) % 360.0
    ok = pressed & np.isfinite(turn)
    return replace(sites, yaw=np.where(ok, turn, sites.yaw))


def _level_extent(
    sites: Sites, proto_index: np.ndarray, trees: list[TreeBuild], lod: str, ground_z: np.ndarray
) -> np.ndarray:
    """The instancer extent of ``sites`` at level ``lod`` and their proxies (see
    :func:`instancer_extent`)."""
    proxy = instancer_extent(sites, proto_index, trees, "proxy", ground_z)
    if lod == "proxy" or len(sites) == 0:
        return proxy
    selected = instancer_extent(sites, proto_index, trees, lod, ground_z)
    return np.stack([np.minimum(selected[0], proxy[0]), np.maximum(selected[1], proxy[1])])


def _write_csv(
    path: Path,
    sites: Sites,
    proto_sizes: np.ndarray,
    proto_index: np.ndarray,
    z: np.ndarray,
    ids: np.ndarray | None = None,
) -> None:
    """``trees.csv``: one row per tree; ``proto_sizes`` (P, 3) holds each prototype's height, and
    an allometric prototype's DBH and target height (NaN for others): a tree's height is its
    scale times its prototype's, its DBH measured at 1.3 m on the scaled trunk."""
    from usdforest import csvtext

    height = proto_sizes[proto_index, 0] * sites.scale
    dbh = scaled_dbh(proto_sizes[proto_index, 1], proto_sizes[proto_index, 2], sites.scale)
    with path.open("wb") as f:
        f.write(b"id,x,y,z,species,variant,yaw,scale,height,dbh\n")
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
            ],
        )


def write_forest(
    recipe: Recipe,
    out: str | Path,
    *,
    force: bool = False,
    progress: Progress | None = None,
    thumbnail: bool = True,
    workers: int = 1,
    scheduler: str | None = None,
    untiled: bool = False,
) -> ForestBuild:
    """Build the forest of ``recipe`` at ``out`` (see the module docstring for the layout).

    Everything is written into a temporary folder beside ``out`` and moved into place at the
    end; a failure leaves nothing behind. Refuses to overwrite without ``force``. A tiled
    recipe samples and writes its tiles as tasks on Dask (``workers`` local processes, or the
    cluster at ``scheduler``) when asked, else here: the same bytes either way. ``untiled``
    writes a tiled recipe's trees (the same sites) as one instancer layer.
    """
    out = Path(out)
    if out.suffix != ".usda":
        raise UsdForestError(f"{out}: the forest's interface layer must end in .usda")
    refuse_overwrite(out, out.parent / f"{out.stem}_assets", force=force)
    tiled = recipe.tiles is not None
    with _dask_client(workers, scheduler) if tiled else nullcontext() as client:
        return _write_forest(recipe, out, progress, thumbnail, client, tiled and not untiled)


def _write_forest(
    recipe: Recipe,
    out: Path,
    progress: Progress | None,
    thumbnail: bool,
    client,
    tiled: bool,
) -> ForestBuild:
    assets = out.parent / f"{out.stem}_assets"
    tick = progress or (lambda stage, done, total: None)

    tick("sampling sites", 0, 1)
    sites = sample_sites(recipe, 0, client)
    tick("sampling sites", 1, 1)

    sites, classes, away = _sized_sites(recipe, sites)
    counts = {
        n: len(classes[n]) if n in classes else recipe.variants[n] for n in recipe.species_names
    }
    prototypes = [(n, v) for n in recipe.species_names for v in range(counts[n])]
    proto_of = {p: i for i, p in enumerate(prototypes)}
    lookup = np.array(
        [
            [proto_of.get((n, v), -1) for v in range(max([1, *counts.values()]))]
            for n in recipe.species_names
        ]
    )
    proto_index = lookup[sites.species, sites.variant].astype(np.int32)

    trees: dict[tuple[str, int], TreeBuild] = {}
    for k, (name, variant) in enumerate(prototypes):
        tick("growing trees", k, len(prototypes))
        entry = recipe.species[name]
        trees[(name, variant)] = build_tree(
            entry.species,
            recipe.seed,
            variant,
            template_base=entry.template_base,
            colliders=recipe.colliders,
            target=classes[name][variant] if name in classes else None,
        )
    tick("growing trees", len(prototypes), len(prototypes))
    sites = _turned_away(sites, away, [trees[p] for p in prototypes], proto_index)

    proto_extent = np.stack([trees[p].extent for p in prototypes])
    # per prototype: its height and (allometric trees) its DBH; a tree's are its scale times
    proto_sizes = np.stack(
        [
            proto_extent[:, 1, 2] - proto_extent[:, 0, 2],
            [trees[p].size.dbh if trees[p].size is not None else np.nan for p in prototypes],
            [trees[p].size.height if trees[p].size is not None else np.nan for p in prototypes],
        ],
        axis=1,
    ).reshape(-1, 3)
    ordered = [trees[p] for p in prototypes]
    # each tree stands on the ground mesh (its height on the mesh's triangles, float32 as
    # positions store it)
    # the layers are written about an anchor (see ForestBuild); trees.csv keeps the recipe's
    # coordinates
    anchor = _anchor(recipe)
    csv_sites, sites = sites, replace(sites, xy=sites.xy - anchor)
    ground = _shifted(recipe.ground["field"], anchor) if recipe.ground is not None else None
    ground_z = (
        ground.height(sites.xy[:, 0], sites.xy[:, 1]).astype(np.float32)
        if ground is not None
        else np.zeros(len(sites), dtype=np.float32)
    ) + np.float32(0.0)
    # a PointInstancer's extent bounds its prototypes' default, render and proxy purposes:
    # the selected level and, beside a full or medium tree, its proxy
    extent = _level_extent(sites, proto_index, ordered, recipe.lod, ground_z)
    build = ForestBuild(
        sites,
        tuple(prototypes),
        proto_index,
        trees,
        extent,
        out,
        assets,
        ground_z,
        anchor,
    )

    with staging_folder(out) as tmp:
        staged = tmp / assets.name
        (staged / "trees").mkdir(parents=True)
        (staged / "templates").mkdir()
        tree_assets = []
        for k, key in enumerate(prototypes):
            tick("writing trees", k, len(prototypes))
            tb = trees[key]
            refs = copy_templates(tb, staged / "templates", "../templates/")
            stem = f"{re.sub(r'[^A-Za-z0-9_.-]', '_', key[0])}_{key[1]}"
            layer = tree_layer(tb, refs, asset_name=stem, identifier=f"./{stem}.usdc")
            save_layer(layer, staged / "trees" / f"{stem}.usdc")
            tree_assets.append(f"./trees/{stem}.usdc")
        tick("writing trees", len(prototypes), len(prototypes))
        tick("writing instances", 0, 1)
        sublayers, tiles = [], None
        if tiled:
            tiles = _write_tiles(
                staged,
                build,
                recipe,
                csv_sites,
                proto_sizes,
                tree_assets,
                [trees[k] for k in prototypes],
                client,
                tick,
            )
        else:
            save_layer(
                instancer_layer(sites, build, tree_assets, recipe.lod), staged / "instances.usdc"
            )
            sublayers.append(f"./{assets.name}/instances.usdc")
        if recipe.colliders != "none" and not tiled:
            caps, names = instance_capsules(
                [trees[key].colliders for key in prototypes],
                proto_index,
                np.column_stack([sites.xy, ground_z]),
                sites.yaw,
                sites.scale,
            )
            save_layer(collision_layer(caps, names), staged / "colliders.usdc")
            sublayers.append(f"./{assets.name}/colliders.usdc")
        if recipe.ground is not None and not tiled:  # (tiled: each tile has its own)
            save_layer(
                ground_layer(ground, recipe.ground["color"]),
                staged / "ground.usdc",
            )
            sublayers.append(f"./{assets.name}/ground.usdc")
        # the ground truth is written while the thumbnail renders (numpy lets go of the GIL);
        # leaving the block waits for it, also on an error
        with ThreadPoolExecutor(1) as pool:
            csv = pool.submit(
                _write_csv, staged / "trees.csv", csv_sites, proto_sizes, proto_index, ground_z
            )
            (staged / "pipeline.toml").write_text(
                "# The resolved recipe of this forest: usdforest build OUT.usda --pipeline this\n"
                + tomli_w.dumps(resolved_toml(recipe, assets))
            )
            save_layer(
                interface_layer(
                    build,
                    recipe,
                    sublayers,
                    f"./{assets.name}/{THUMBNAIL}" if thumbnail else None,
                    tiles,
                ),
                tmp / out.name,
            )
            tick("writing instances", 1, 1)
            if thumbnail:
                from usdforest.view.preview import preview

                tick("thumbnail", 0, 1)
                # the thumbnail lives in the assets folder, so it moves (and packs) with the
                # forest
                preview(
                    tmp / out.name, staged / THUMBNAIL, view="iso", size=(256, 256), annotate=False
                )
                tick("thumbnail", 1, 1)
            csv.result()
        publish(tmp, out, tmp / out.name, [(staged, assets)])
    return replace(build, n_tiles=len(tiles or ()))

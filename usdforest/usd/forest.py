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
                                (T_<id>) and per piece of dead wood (D_<id>)
      deadwood.usdc             /Forest/DeadWood: snags, stumps, logs, fallen branches (a
                                PointInstancer of CAD templates), when the recipe has [deadwood]
      deadwood.csv              its ground truth, one row per piece
      groundcover.usdc          /Forest/GroundVegetation: grass, herb, fern and moss patches
                                (a PointInstancer of CAD templates), when the recipe has
                                [groundcover]
      groundcover.csv           its ground truth, one row per patch
      understorey.usdc          /Forest/Understorey: shrubs and young trees (a PointInstancer
                                of tree assets in trees/), when the recipe has [shrubs] or
                                [regeneration]
      understorey.csv           its ground truth, one row per plant
      ground.usdc               /Forest/Ground: the plane or height field (collider, label)
      physics.usda              colliders and ground alone (no visual meshes), for physics
                                engines; /Forest/PhysicsScene when the forest has one
      wind.usdc                 over /Forest/Trees: the trees' sway as time samples of their
                                orientations, when the recipe has [wind] (the strongest
                                sublayer; :mod:`usdforest.usd.wind`)
      trees.csv                 ground truth, one row per instance
      pipeline.toml             the resolved recipe (seed included)
    forest_assets/thumbnail.png a 256x256 thumbnail (customLayerData.thumbnail)
"""

from __future__ import annotations

import re
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np
import tomli_w
from pxr import Gf, Sdf, Vt

from usdforest.atomic import output_lock, publish, staging_folder
from usdforest.cluster import Progress, dask_client, run_tasks
from usdforest.errors import UsdForestError
from usdforest.grow import exact
from usdforest.grow.bounds import EMPTY_EXTENT
from usdforest.grow.stems import lean_matrix
from usdforest.paths import claim_outputs, require_output
from usdforest.recipe import Recipe, recipe_inputs, resolved_toml
from usdforest.sites.local import Plan, classes_for, first_ids, place, squares, whole
from usdforest.sites.stand import merge_sums
from usdforest.sites.terrain import HeightField
from usdforest.usd.beneath import has_beneath, litter, write_beneath
from usdforest.usd.ground import ground_layer
from usdforest.usd.instances import (
    ForestBuild,
    ProtoSizes,
    anchor_of,
    instancer_layer,
    level_extent,
    shifted,
    write_trees_csv,
)
from usdforest.usd.landscape import (
    Proto,
    TileKit,
    survey_task,
    write_tiles,
    write_tiles_index,
)
from usdforest.usd.layers import T, attr, extents, new_layer, prim, save_layer
from usdforest.usd.physics import (
    add_physics_scene,
    collision_layer,
    instance_capsules,
    join_capsules,
)
from usdforest.usd.tiles import author_tiles
from usdforest.usd.tree import TreeBuild, build_tree, copy_templates, tree_layer

THUMBNAIL = "thumbnail.png"  # inside the assets folder


def _place_origin(forest: Sdf.PrimSpec, build: ForestBuild, recipe: Recipe) -> None:
    """With ``origin = "centre"`` the stage puts the plot's centre at 0, 0 (recipe
    coordinates stay in trees.csv)."""
    if recipe.origin != "centre":
        return
    cx, cy = _stage_origin(build, recipe) - build.anchor
    attr(forest, "xformOp:translate", T.Double3, Gf.Vec3d(-cx, -cy, 0))
    attr(forest, "xformOpOrder", T.TokenArray, Vt.TokenArray(["xformOp:translate"]), uniform=True)


def physics_layer(sublayers: list[str], build: ForestBuild, recipe: Recipe) -> Sdf.Layer:
    """``physics.usda`` in the assets folder: the collision and ground layers without the
    trees' visual meshes, so a physics engine loads 380 capsules and a plane rather than
    composing millions of leaves to find them (newton's ``add_usd`` on the default forest
    took 637 s); with the forest's physics scene when it has one."""
    layer = new_layer("Forest", comment="usdforest forest physics: colliders and ground only")
    for sub in sublayers:
        layer.subLayerPaths.append(f"./{sub}")
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        _place_origin(forest, build, recipe)
        if recipe.physics_scene:
            add_physics_scene(forest)
    return layer


WIND = "wind.usdc"


def _write_wind(recipe: Recipe, staged: Path, extent: np.ndarray) -> None:
    """The wind layer beside the instancer layer, from the trees composed there."""
    from pxr import Usd

    from usdforest.usd.wind import wind_layer

    stage = Usd.Stage.Open(str(staged / "instances.usdc"))
    save_layer(wind_layer(stage, recipe.wind, recipe.seed, extent), staged / WIND)


def interface_layer(
    build: ForestBuild,
    recipe: Recipe,
    sublayers: list[str],
    thumbnail: str | None = None,
    tiles: list | None = None,
    boxes: tuple[np.ndarray, ...] = (),
) -> Sdf.Layer:
    """``forest.usda``: ``/Forest`` (assembly) over the instancer and collision sublayers
    (or the ``tiles``' payloads, see :func:`usdforest.usd.tiles.author_tiles`), with a
    physics scene only when the recipe asks for one; its extentsHint also holds ``boxes``
    (the dead wood's)."""
    layer = new_layer("Forest", comment="usdforest forest")
    for sub in sublayers:
        layer.subLayerPaths.append(sub)
    data = {}
    if thumbnail:
        data["thumbnail"] = Sdf.AssetPath(thumbnail)
    if recipe.crs:  # where the stage's origin is on the map
        data["crs"] = recipe.crs
        data["crsOrigin"] = Gf.Vec2d(*(float(v) for v in _stage_origin(build, recipe)))
    if recipe.wind is not None:  # time codes are the wind's frames; the last is the first
        data["loops"] = True  # so the sensors wrap time
        layer.startTimeCode = 0
        layer.endTimeCode = recipe.wind.frames
        layer.timeCodesPerSecond = recipe.wind.fps
        layer.framesPerSecond = recipe.wind.fps
    if data:
        layer.customLayerData = data
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        forest.assetInfo = {
            "name": build.out.stem,
            "identifier": Sdf.AssetPath(f"./{build.out.name}"),
        }
        _place_origin(forest, build, recipe)
        forest.customData = {
            "usdforest": {
                "seed": recipe.seed,
                "trees": build.n_trees,
                "treesBySpecies": dict(build.trees_by_species),
                "prototypes": len(build.prototypes),
                "regionBounds": Vt.DoubleArray([float(b) for b in recipe.region.bounds]),
                "regionArea": round(float(recipe.region.area), 3),
                "pipeline": "./" + f"{build.assets.name}/pipeline.toml",
            }
        }
        attr(forest, "extentsHint", T.Float3Array, extents(_extents_hint(build, recipe, boxes)))
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


def _extents_hint(
    build: ForestBuild, recipe: Recipe, extra: tuple[np.ndarray, ...] = ()
) -> np.ndarray:
    """``/Forest``'s extentsHint: one box, for the default purpose, holding the ground and
    the trees (``/Forest/Trees`` is a default-purpose prim: its whole extent, proxies
    included, counts there, as ``UsdGeomModelAPI.ComputeExtentsHint`` finds)."""
    boxes = []
    if recipe.ground is not None:
        ground = shifted(recipe.ground["field"], build.anchor)
        x0, y0, x1, y1 = ground.bounds
        boxes.append(np.array([[x0, y0, ground.z.min()], [x1, y1, ground.z.max()]]))
    if build.n_trees:
        boxes.append(build.extent)
    boxes.extend(extra)
    if not boxes:
        return EMPTY_EXTENT
    return np.stack([np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)])


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
    writes a tiled recipe's trees (the same sites) as one instancer layer: the only way a
    tiled recipe's ``[wind]`` is written (the wind layer sways one instancer's trees).
    """
    from usdforest import arguments

    out = Path(arguments.path(out, "out"))
    require_output(out)
    if out.suffix != ".usda":
        raise UsdForestError(f"{out}: the forest's interface layer must end in .usda")
    arguments.seed(recipe.seed, "seed")
    arguments.flag(force, "force")
    arguments.flag(thumbnail, "thumbnail")
    arguments.flag(untiled, "untiled")
    arguments.workers(workers, scheduler, recipe.tiles is not None, untiled)
    if recipe.wind is not None and recipe.tiles is not None and not untiled:
        raise UsdForestError(
            f"{recipe.source}: wind: a tiled forest sways only as one layer; build it with "
            "--untiled (untiled=True in the API), or remove [tiles] or [wind]"
        )
    assets = out.parent / f"{out.stem}_assets"
    with output_lock(out):
        claim_outputs([out], inputs=lambda: recipe_inputs(recipe), folders=[assets], force=force)
        tiled = recipe.tiles is not None
        with dask_client(workers, scheduler) if tiled else nullcontext() as client:
            return _write_forest(
                recipe, out, progress, thumbnail, client, tiled and not untiled, force
            )


def _write_forest(
    recipe: Recipe,
    out: Path,
    progress: Progress | None,
    thumbnail: bool,
    client,
    tiled: bool,
    force: bool,
) -> ForestBuild:
    assets = out.parent / f"{out.stem}_assets"
    tick = progress or (lambda stage, done, total: None)

    # the survey: per square, trees per cell and the stand's sums (nothing of the trees)
    cut = squares(recipe) if tiled else [whole(recipe)]
    surveys = run_tasks(client, survey_task, [(sq,) for sq in cut], recipe, tick, "sampling sites")
    names = recipe.species_names
    by_species = np.sum([s.by_species for s in surveys], axis=0, dtype=np.int64)
    if recipe.wind is not None:  # refused before any tree is grown
        from usdforest.usd.wind import check_samples

        check_samples(int(by_species.sum()), recipe.wind)
    classes = classes_for(recipe, merge_sums(s.sums for s in surveys))
    classes = {n: c for n, c in classes.items() if len(c.sizes)}
    # a species no tree is of still has a prototype (an empty forest has its prototypes), one:
    # an inventory's unplanted species would otherwise grow 64 trees nobody stands on
    planted = dict(zip(names, (int(c) for c in by_species), strict=True))
    counts = {
        n: len(classes[n].sizes) if n in classes else recipe.variants[n] if planted[n] else 1
        for n in names
    }
    prototypes = [(n, v) for n in names for v in range(counts[n])]
    proto_of = {p: i for i, p in enumerate(prototypes)}
    lookup = np.array(
        [[proto_of.get((n, v), -1) for v in range(max([1, *counts.values()]))] for n in names]
    )

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
            stems=recipe.stems,
            target=classes[name].sizes[variant] if name in classes else None,
        )
    tick("growing trees", len(prototypes), len(prototypes))
    ordered = [trees[p] for p in prototypes]
    # only a wind that sways branches needs each limb grouped (see usd.tree)
    w = recipe.wind
    sways = w is not None and w.branch_sway and w.speed > 0
    if sways:  # and its limbs' samples: refused before anything is written
        from usdforest.usd.wind import check_samples

        check_samples(int(by_species.sum()), w, sum(len(t.limbs) for t in ordered))
    proto_extent = np.stack([t.sized_extent for t in ordered])
    grown = proto_extent[:, 1, 2] - proto_extent[:, 0, 2] if recipe.sites is not None else None
    girths = tuple(t.girth for t in ordered)
    stem_lean = np.array([t.lean for t in ordered], dtype=float).reshape(-1, 2)
    plan = Plan(
        classes, lookup, _leans(ordered), first_ids(recipe, surveys), grown, girths, stem_lean
    )

    # per prototype: its height, the girth tape on its stem and the stem's direction
    proto_sizes = ProtoSizes(
        proto_extent[:, 1, 2] - proto_extent[:, 0, 2],
        girths,
        np.array([lean_matrix(*t.lean)[:, 2] for t in ordered]).reshape(-1, 3),
    )
    # the layers are written about an anchor (see ForestBuild); trees.csv keeps the recipe's
    # coordinates
    anchor = anchor_of(recipe)
    ground = shifted(recipe.ground["field"], anchor) if recipe.ground is not None else None
    trees_by_species = {n: int(c) for n, c in zip(names, by_species, strict=True)}

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
            layer = tree_layer(tb, refs, asset_name=stem, identifier=f"./{stem}.usdc", limbs=sways)
            save_layer(layer, staged / "trees" / f"{stem}.usdc")
            tree_assets.append(f"./trees/{stem}.usdc")
        tick("writing trees", len(prototypes), len(prototypes))
        sublayers, tiles, write_csv, hint_boxes = [], None, None, ()
        if tiled:
            kit = TileKit(
                recipe,
                plan,
                tuple(prototypes),
                tuple(Proto(t.bounds, t.colliders) for t in ordered),
                proto_sizes,
                tuple("." + a for a in tree_assets),  # ./trees/x.usdc, seen from tiles/
                anchor,
            )
            written = write_tiles(staged / "tiles", cut, kit, client, tick)
            tiles = [
                (t.name, t.origin, f"./{assets.name}/tiles/{t.name}.usdc", t.extent)
                for t in written
            ]
            boxes = [t.tree_extent + np.array([*t.origin, 0.0]) for t in written if t.trees]
            extent = (
                np.stack([np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)])
                if boxes
                else EMPTY_EXTENT
            )
            build = ForestBuild(
                None,
                tuple(prototypes),
                None,
                trees,
                extent,
                out,
                assets,
                None,
                trees_by_species,
                anchor,
                len(written),
            )
            write_tiles_index(staged / "tiles.csv", written, anchor)
            if has_beneath(recipe):
                # placed among every tree's stem, as untiled: the same layers with or without
                # tiles (the client holds the stand's sites for them)
                placed = place(recipe, whole(recipe), plan)
                stems = (placed.sites.xy, placed.proto_index, placed.sites.scale)
                below = write_beneath(recipe, ordered, stems, staged, tick, trees_by_species, True)
                sublayers += [f"./{assets.name}/{name}" for name in below.layers]
                hint_boxes = below.boxes
        else:
            build, write_csv = _untiled(
                recipe, plan, prototypes, trees, ground, anchor, out, trees_by_species
            )
            tick("writing instances", 0, 1)
            save_layer(
                instancer_layer(
                    build.sites,
                    build.prototypes,
                    build.proto_index,
                    build.ground_z,
                    build.extent,
                    tree_assets,
                    recipe.lod,
                ),
                staged / "instances.usdc",
            )
            sublayers.append(f"./{assets.name}/instances.usdc")
            if recipe.wind is not None:
                tick("writing wind", 0, 1)
                _write_wind(recipe, staged, build.extent)
                sublayers.insert(0, f"./{assets.name}/{WIND}")
                tick("writing wind", 1, 1)
            below = None
            if has_beneath(recipe):
                stems = (build.sites.xy + anchor, build.proto_index, build.sites.scale)
                below = write_beneath(recipe, ordered, stems, staged, tick, trees_by_species, False)
                sublayers += [f"./{assets.name}/{name}" for name in below.layers]
                hint_boxes = below.boxes
            if recipe.colliders != "none":
                caps, cap_names = instance_capsules(
                    [t.colliders for t in ordered],
                    build.proto_index,
                    np.column_stack([build.sites.xy, build.ground_z]),
                    build.sites.yaw,
                    build.sites.scale,
                )
                if below is not None and below.colliders is not None:
                    caps = join_capsules(caps, below.colliders)
                    cap_names = list(caps.names)
                save_layer(collision_layer(caps, cap_names), staged / "colliders.usdc")
                sublayers.append(f"./{assets.name}/colliders.usdc")
            if ground is not None:
                save_layer(
                    ground_layer(ground, recipe.ground["color"], litter(recipe)),
                    staged / "ground.usdc",
                )
                sublayers.append(f"./{assets.name}/ground.usdc")
            bodies = [s.removeprefix(f"./{assets.name}/") for s in sublayers[1:]]
            if bodies:
                save_layer(physics_layer(bodies, build, recipe), staged / "physics.usda")
        # the ground truth is written while the thumbnail renders (numpy lets go of the GIL);
        # leaving the block waits for it, also on an error
        with ThreadPoolExecutor(1) as pool:
            csv = (
                pool.submit(write_csv, staged / "trees.csv", proto_sizes)
                if write_csv is not None
                else None
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
                    hint_boxes,
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
            if csv is not None:
                csv.result()
        publish(tmp, out, tmp / out.name, [(staged, assets)], force=force)
    return build


def _leans(trees: list[TreeBuild]) -> np.ndarray:
    """Per prototype, the direction (degrees from +x) of its one-sided crown (the mean of its
    leaves' xy, measured on the grown tree in leaf: the same in every season); NaN for a
    symmetric one."""
    return np.array(
        [
            np.degrees(exact.arctan2(*t.leaf_centre))
            if t.size is not None and t.size.asymmetry > 0 and t.leaf_centre is not None
            else np.nan
            for t in trees
        ]
    ).reshape(-1)


def _untiled(
    recipe: Recipe,
    plan: Plan,
    prototypes: list[tuple[str, int]],
    trees: dict[tuple[str, int], TreeBuild],
    ground: HeightField | None,
    anchor: np.ndarray,
    out: Path,
    trees_by_species: dict[str, int],
) -> tuple[ForestBuild, Callable[[Path, np.ndarray], None]]:
    """An untiled forest's trees placed in one square, and the writer of its ``trees.csv``."""
    placed = place(recipe, whole(recipe), plan)
    csv_sites = placed.sites
    sites = replace(csv_sites, xy=csv_sites.xy - anchor)
    # each tree stands on the ground mesh (its height on the mesh's triangles, float32 as
    # positions store it)
    ground_z = (
        ground.height(sites.xy[:, 0], sites.xy[:, 1]).astype(np.float32)
        if ground is not None
        else np.zeros(len(sites), dtype=np.float32)
    ) + np.float32(0.0)
    ordered = [trees[p] for p in prototypes]
    # a PointInstancer's extent bounds its prototypes' default, render and proxy purposes:
    # the selected level and, beside a full or medium tree, its proxy
    extent = level_extent(sites, placed.proto_index, ordered, recipe.lod, ground_z)
    build = ForestBuild(
        sites,
        tuple(prototypes),
        placed.proto_index,
        trees,
        extent,
        out,
        out.parent / f"{out.stem}_assets",
        ground_z,
        trees_by_species,
        anchor,
    )

    def write_csv(path: Path, proto_sizes: ProtoSizes) -> None:
        write_trees_csv(path, csv_sites, proto_sizes, placed.proto_index, ground_z, placed.ids)

    return build, write_csv

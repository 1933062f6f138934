"""The layers beneath a forest's crowns, as a build writes them: dead wood, ground
vegetation and the understorey (shrubs and young trees), each placed among the stand's stems
and under the light its crowns let through, written into the build's staging folder with
the templates and tree assets it references.

Each writer takes the recipe, the tree prototypes' builds, the stems (recipe x, y,
prototype index and scale of every tree) and the staging folder, and returns the extentsHint
boxes the forest's interface layer needs (the dead wood's writer its pieces and ids too);
:func:`write_beneath` runs every one the recipe asks for.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from usdforest.cluster import Progress
from usdforest.grow.colliders import Capsules
from usdforest.recipe import Recipe
from usdforest.usd.debris import (
    copy_deadwood_templates,
    deadwood_capsules,
    deadwood_extent,
    deadwood_layer,
    write_deadwood_csv,
)
from usdforest.usd.floor import (
    copy_groundcover_templates,
    groundcover_extent,
    groundcover_layer,
    write_groundcover_csv,
)
from usdforest.usd.instances import anchor_of
from usdforest.usd.layers import save_layer
from usdforest.usd.tree import TreeBuild, build_tree, copy_templates, tree_layer


@dataclass(frozen=True, eq=False)
class Beneath:
    """What :func:`write_beneath` wrote: its layers (file names in the staging folder, in
    sublayer order), the extentsHint boxes they add, and the dead wood's colliders for the
    forest's collision layer (``None`` when they are inside the dead-wood layer or there are
    none)."""

    layers: tuple[str, ...]
    boxes: tuple[np.ndarray, ...]
    colliders: Capsules | None


def has_beneath(recipe: Recipe) -> bool:
    """Whether the recipe asks for any layer beneath the crowns."""
    return any(
        t is not None
        for t in (recipe.deadwood, recipe.groundcover, recipe.shrubs, recipe.regeneration)
    )


def write_beneath(
    recipe: Recipe,
    trees: list[TreeBuild],
    stems: tuple[np.ndarray, np.ndarray, np.ndarray],
    staged: Path,
    tick: Progress,
    by_species: dict[str, int],
    tiled: bool,
) -> Beneath:
    """Every layer the recipe asks for beneath the crowns of ``stems``, written to
    ``staged``: dead wood (its colliders inside its own layer when ``tiled``), ground
    vegetation, shrubs and young trees (``by_species``: the stand's stems per species)."""
    layers, boxes, colliders = [], [], None
    if recipe.deadwood is not None:
        pieces, ids, b = write_dead_wood(recipe, trees, stems, staged, tick, tiled)
        layers.append("deadwood.usdc")
        boxes += b
        if not tiled and recipe.colliders != "none" and len(pieces):
            colliders = deadwood_capsules(pieces, anchor_of(recipe), ids)
    if recipe.groundcover is not None:
        boxes += write_ground_cover(recipe, trees, stems, staged, tick)
        layers.append("groundcover.usdc")
    if recipe.shrubs is not None or recipe.regeneration is not None:
        boxes += write_understorey(recipe, trees, stems, staged, tick, by_species)
        layers.append("understorey.usdc")
    return Beneath(tuple(layers), tuple(boxes), colliders)


def write_dead_wood(
    recipe: Recipe,
    trees: list[TreeBuild],
    stems: tuple[np.ndarray, np.ndarray, np.ndarray],
    staged: Path,
    tick: Progress,
    own_colliders: bool,
):
    """The recipe's dead wood among the ``stems`` (their recipe x, y, prototype index and
    scale), written to ``deadwood.usdc`` and ``deadwood.csv`` in ``staged`` with the
    templates it references; its colliders in the layer itself with ``own_colliders`` (a
    tiled forest), else returned for the forest's collision layer. Returns the pieces, their
    ids and the extentsHint boxes they add."""
    from usdforest.grow.deadwood import place_dead_wood
    from usdforest.usd.debris import piece_shapes

    tick("dead wood", 0, 1)
    xy = stems[0]
    stems_r = _stem_radii(trees, stems)
    shapes = piece_shapes()
    ground = recipe.ground["field"] if recipe.ground is not None else None
    spec, region = recipe.deadwood, recipe.region
    pieces = place_dead_wood(spec, region, recipe.seed, xy, stems_r, shapes, ground)
    anchor = anchor_of(recipe)
    ids = np.arange(len(pieces), dtype=np.int64)
    copy_deadwood_templates(staged / "templates")
    own = own_colliders and recipe.colliders != "none"
    caps = deadwood_capsules(pieces, anchor, ids) if own else None
    save_layer(deadwood_layer(pieces, shapes, anchor, ids, caps), staged / "deadwood.usdc")
    write_deadwood_csv(staged / "deadwood.csv", pieces, ids)
    tick("dead wood", 1, 1)
    boxes = (deadwood_extent(pieces, shapes, anchor),) if len(pieces) else ()
    return pieces, ids, boxes


def litter(recipe: Recipe) -> bool:
    """Whether the forest's ground is leaf litter (``[groundcover] litter``)."""
    return recipe.groundcover is not None and recipe.groundcover.litter


def write_understorey(
    recipe: Recipe,
    trees: list[TreeBuild],
    stems: tuple[np.ndarray, np.ndarray, np.ndarray],
    staged: Path,
    tick: Progress,
    by_species: dict[str, int],
) -> tuple[np.ndarray, ...]:
    """The recipe's shrubs and young trees under the crowns of ``stems``, grown (as tree
    assets in ``trees/``), placed and written to ``understorey.usdc`` and
    ``understorey.csv`` in ``staged``. Returns the extentsHint boxes they add."""
    from usdforest.grow.seasons import seasonal
    from usdforest.grow.species import get_species
    from usdforest.grow.understorey import (
        SHRUB_FORMS,
        Plants,
        place_regeneration,
        place_shrubs,
        regeneration_heights,
    )
    from usdforest.seeds import stream
    from usdforest.usd.undergrowth import (
        Kind,
        understorey_extent,
        understorey_layer,
        write_understorey_csv,
    )

    crowns = _crown_discs(trees, stems)
    clear = (stems[0], _stem_radii(trees, stems))
    jobs: list[tuple[str, str, str, object]] = []  # layer, name, asset stem, build
    if recipe.shrubs is not None:
        for form in SHRUB_FORMS:
            for v in range(recipe.shrubs.variants):
                shrub = seasonal(get_species(form), recipe.season)
                jobs.append(("shrub", form, f"{form}_{v}", (shrub, v, None, None)))
    young = []
    if recipe.regeneration is not None:
        heights = regeneration_heights(recipe.regeneration)
        young = [n for n in recipe.species_names if recipe.species[n].species.allometry]
        for name in young:
            entry = recipe.species[name]
            for c, h in enumerate(heights):
                size = _young_size(entry.species, stream(recipe.seed, name, "young", c), h)
                job = (entry.species, 1000 + c, entry.template_base, size)
                jobs.append(("regeneration", name, f"{name}_young_{c}", job))
    kinds, builds = [], []
    for k, (layer, name, stem, (species, variant, base, size)) in enumerate(jobs):
        tick("growing the understorey", k, len(jobs))
        tb = build_tree(
            species,
            recipe.seed,
            variant,
            template_base=base,
            colliders="none",
            target=size,
            stems=recipe.stems,
        )
        kinds.append(
            Kind(layer, name, stem, float(tb.sized_extent[1, 2]), _footprint(tb), tb.extent)
        )
        builds.append(tb)
        refs = copy_templates(tb, staged / "templates", "../templates/")
        layer_ = tree_layer(tb, refs, asset_name=stem, identifier=f"./{stem}.usdc")
        save_layer(layer_, staged / "trees" / f"{stem}.usdc")
    tick("growing the understorey", len(jobs), len(jobs))
    parts = []
    n_shrubs = sum(1 for k in kinds if k.layer == "shrub")
    if recipe.shrubs is not None:
        shrub = kinds[:n_shrubs]
        reach = np.array(
            [float(np.linalg.norm(b.summer_footprint, axis=1).max()) for b in builds[:n_shrubs]]
        )
        parts.append(
            place_shrubs(
                recipe.shrubs,
                recipe.region,
                recipe.seed,
                crowns,
                clear,
                np.array([k.footprint for k in shrub]),
                reach,
            )
        )
    if recipe.regeneration is not None:
        shares = np.array([by_species.get(n, 0) for n in young], dtype=float)
        p = place_regeneration(
            recipe.regeneration, recipe.region, recipe.seed, crowns, clear, shares
        )
        parts.append(replace(p, proto=(p.proto + n_shrubs).astype(np.int32)))
    plants = Plants.concat(parts)
    ground = recipe.ground["field"] if recipe.ground is not None else None
    z = (
        ground.height(plants.xy[:, 0], plants.xy[:, 1]) - 0.01
        if ground is not None and len(plants)
        else np.full(len(plants), -0.01)
    )
    anchor = anchor_of(recipe)
    ids = np.arange(len(plants), dtype=np.int64)
    save_layer(
        understorey_layer(plants, kinds, z, anchor, ids, recipe.lod),
        staged / "understorey.usdc",
    )
    write_understorey_csv(staged / "understorey.csv", plants, kinds, z, ids)
    return (understorey_extent(plants, kinds, z, anchor),) if len(plants) else ()


def _young_size(species, rng: np.random.Generator, height: float):
    """A young tree of ``height``: at the DBH whose mean height that is (the species' height
    curve's inverse), or under breast height with the inventory's sapling slenderness
    (:func:`usdforest.sites.stand.sapling_dbh`)."""
    from usdforest.grow.allometry import ALLOMETRY
    from usdforest.grow.architecture import BREAST_HEIGHT
    from usdforest.grow.species import tree_size
    from usdforest.sites.stand import sapling_dbh

    h = float(height)
    if h < BREAST_HEIGHT:
        d = float(sapling_dbh(np.array(h))) * 100.0
    else:
        d = float(ALLOMETRY[species.allometry].dbh(np.array(h)))
    return tree_size(species, rng, dbh=d, height=h)


def _stem_radii(trees: list[TreeBuild], stems: tuple[np.ndarray, ...]) -> np.ndarray:
    """Each stem's footprint radius: its DBH (root flare 1.3x) where known, else its trunk
    collider's (``stems``: recipe x, y, prototype index and scale)."""
    xy, proto_index, scale = stems
    radius = np.array(
        [
            0.65 * t.size.dbh
            if t.size is not None
            else (float(t.colliders.radius[0]) if len(t.colliders) else 0.15)
            for t in trees
        ]
    ).reshape(-1)
    return radius[proto_index] * scale if len(xy) else np.zeros(0)


def _crown_discs(
    trees: list[TreeBuild], stems: tuple[np.ndarray, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each stem's crown as a disc for the light on the floor: xy, radius and the leaf area
    index over the disc (see :func:`usdforest.grow.groundcover.floor_light`)."""
    xy, proto_index, scale = stems
    r0, leaf0 = _crowns(trees)
    r = r0[proto_index] * scale if len(xy) else np.zeros(0)
    lai = np.divide(
        leaf0[proto_index] * scale**2 if len(xy) else np.zeros(0),
        np.pi * r**2,
        out=np.zeros(len(r)),
        where=r > 0,
    )
    return xy, r, lai


def _footprint(tree: TreeBuild) -> float:
    """Area (m²) of a grown plant's footprint: the hull of its full level's points on the
    ground, with every leaf it has in summer (a season leaves its place and size as they
    were)."""
    from scipy.spatial import ConvexHull

    fp = tree.summer_footprint
    return float(ConvexHull(fp).volume) if len(fp) >= 3 else 0.0


def _crowns(trees: list[TreeBuild]) -> tuple[np.ndarray, np.ndarray]:
    """Per prototype, the radius of the disc of its crown's footprint area (the hull of its
    points on the ground) and its one-sided leaf area (m²), both in summer: the growing
    season's light places what grows under the crowns, whatever the recipe's season."""
    radius = [np.sqrt(_footprint(t) / np.pi) for t in trees]
    leaf = [t.leaf_area for t in trees]
    return np.array(radius).reshape(-1), np.array(leaf).reshape(-1)


def write_ground_cover(
    recipe: Recipe,
    trees: list[TreeBuild],
    stems: tuple[np.ndarray, np.ndarray, np.ndarray],
    staged: Path,
    tick: Progress,
) -> tuple[np.ndarray, ...]:
    """The recipe's ground vegetation under the crowns of ``stems`` (their recipe x, y,
    prototype index and scale), written to ``groundcover.usdc`` and ``groundcover.csv`` in
    ``staged`` with the templates it references. Returns the extentsHint boxes it adds."""
    from usdforest.grow.groundcover import place_ground_cover
    from usdforest.usd.floor import patch_shapes

    tick("ground vegetation", 0, 1)
    shapes = patch_shapes()
    ground = recipe.ground["field"] if recipe.ground is not None else None
    patches = place_ground_cover(
        recipe.groundcover, recipe.region, recipe.seed, _crown_discs(trees, stems), shapes, ground
    )
    anchor = anchor_of(recipe)
    ids = np.arange(len(patches), dtype=np.int64)
    copy_groundcover_templates(staged / "templates")
    save_layer(groundcover_layer(patches, shapes, anchor, ids), staged / "groundcover.usdc")
    write_groundcover_csv(staged / "groundcover.csv", patches, ids)
    tick("ground vegetation", 1, 1)
    return (groundcover_extent(patches, anchor),) if len(patches) else ()

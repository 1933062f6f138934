"""A forest's trees one square at a time: what a tile task computes alone.

A build cuts the region into squares (its tiles, or one square for an untiled recipe) and
goes over them twice. The **survey** of a square samples its cells (:mod:`usdforest.sites.cells`)
with a ring of cells around them, sizes every tree from its cell's streams and measures how
its neighbours press it (:mod:`usdforest.sites.stand`), and returns only sums: trees per cell
and the stand's fixed-point sums. From all squares' sums the client picks the size classes
(:class:`Plan`), grows one tree per class and variant, and numbers the trees (ids in cell
order, from each cell's count). The **placing** of a square computes the same trees again and
gives its own ones their class, scale, turn, prototype and id. Nothing of one square's trees
ever leaves its task, so the client's memory does not grow with the region, and a tree is the
same whatever the squares are.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.grow import exact
from usdforest.sites.cells import (
    CELL,
    cell_of,
    cells_meeting,
    grid,
    grid_shape,
    sample_cells,
)
from usdforest.sites.sampling import inventory_sites
from usdforest.sites.stand import (
    INVENTORY_SPLIT,
    SizeClasses,
    StandSums,
    crowding,
    pressed,
    size_classes,
    stand_sums,
    tree_sizes,
)
from usdforest.sites.table import Sites


@dataclass(frozen=True)
class Square:
    """Square ``(i, j)`` (east, north) of a grid of side ``size`` from ``corner`` with
    ``shape`` (columns, rows); a tree belongs to the square whose half-open box holds it
    (one on the region's east or north edge to the last one)."""

    i: int
    j: int
    corner: tuple[float, float]
    size: float
    shape: tuple[int, int]

    @property
    def name(self) -> str:
        return f"Tile_{self.i}_{self.j}"

    @property
    def origin(self) -> np.ndarray:
        """The south-west corner (recipe coordinates)."""
        return np.array(self.corner) + np.array([self.i, self.j], dtype=float) * self.size

    @property
    def box(self) -> tuple[float, float, float, float]:
        x, y = (float(v) for v in self.origin)
        return (x, y, x + self.size, y + self.size)

    def owns(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((np.asarray(xy).reshape(-1, 2) - self.corner) / self.size)
        ij = np.clip(ij, 0, np.array(self.shape) - 1)
        return (ij[:, 0] == self.i) & (ij[:, 1] == self.j)


def squares(recipe) -> list[Square]:
    """The recipe's tiles, row by row from the south (untiled: one square over the region)."""
    x0, y0, x1, y1 = recipe.region.bounds
    size = recipe.tiles if recipe.tiles is not None else max(x1 - x0, y1 - y0)
    shape = grid_shape(recipe.region.bounds, size)
    return [Square(i, j, (x0, y0), size, shape) for j in range(shape[1]) for i in range(shape[0])]


def whole(recipe) -> Square:
    """One square over the whole region (an untiled build)."""
    x0, y0, x1, y1 = recipe.region.bounds
    return Square(0, 0, (x0, y0), max(x1 - x0, y1 - y0), (1, 1))


def _block(recipe, square: Square) -> tuple[tuple[int, int, int, int], bool]:
    """The cells a square's own trees come from, and whether it owns its cells' trees
    (``True``: the whole region, or tiles a whole number of cells wide, which then own
    exactly their cells' trees) or those of its box (other sizes: the cells that meet the
    closed box, of which the square keeps the trees in its half-open one)."""
    nx, ny = grid(recipe)
    if square.shape == (1, 1):
        return (0, 0, nx, ny), True
    k = square.size / CELL
    if k == round(k):
        k = round(k)
        i, j = square.i * k, square.j * k
        return (i, j, min(i + k, nx), min(j + k, ny)), True
    return cells_meeting(recipe, square.box), False


def _allometric(recipe) -> set[str]:
    return {n for n in recipe.species_names if recipe.species[n].species.allometry is not None}


@dataclass(frozen=True, eq=False)
class Local:
    """A square's trees and those around it: ``sites`` (drawn marks), ``own`` (the square's),
    ``cell``, ``rank`` (in its cell; an inventory's row), the trees' sizes (NaN for
    non-allometric species), their ``pressure`` and the direction ``away`` from their
    neighbours (NaN: not pressed to one side, or an inventory row that gives its yaw)."""

    sites: Sites
    own: np.ndarray
    cell: np.ndarray
    rank: np.ndarray
    block: tuple[int, int, int, int]
    dbh: np.ndarray
    height: np.ndarray
    crown: np.ndarray
    given_crown: np.ndarray
    pressure: np.ndarray
    away: np.ndarray
    exact: np.ndarray  # rows that give both DBH (> 0) and height: their class fits both


def _given(recipe, key: str) -> np.ndarray:
    return np.array([float(s.get(key, np.nan)) for s in recipe.sites], dtype=float)


def local_sites(recipe, square: Square, replicate: int = 0) -> Local:
    """The trees of ``square`` and of the ring of cells around it (see the module
    docstring); the same for a tree whichever square it is computed in."""
    allometric = _allometric(recipe)
    ring = 1 if allometric else 0  # crowns press within 2 crown radii (< one cell)
    block, by_cell = _block(recipe, square)
    yaw_given = None
    if recipe.sites is not None:
        s = inventory_sites(recipe, replicate)
        cell = cell_of(recipe, s.xy)
        nx, _ = grid(recipe)
        ci, cj = cell % nx, cell // nx
        i0, j0, i1, j1 = block
        near = (ci >= i0 - ring) & (ci < i1 + ring) & (cj >= j0 - ring) & (cj < j1 + ring)
        rows = np.flatnonzero(near)
        sites = Sites(
            s.names, s.xy[rows], s.species[rows], s.variant[rows], s.yaw[rows], s.scale[rows]
        )
        cell, rank = cell[rows], rows.astype(np.int64)
        given = {k: _given(recipe, k)[rows] for k in ("dbh", "height", "crown_radius")}
        yaw_given = np.array(["yaw" in recipe.sites[r] for r in rows], dtype=bool)
    else:
        cs = sample_cells(recipe, replicate, block, ring)
        sites, cell, rank = cs.sites, cs.cell, cs.rank
        given = {k: np.full(len(sites), np.nan) for k in ("dbh", "height", "crown_radius")}
    nx, _ = grid(recipe)
    i0, j0, i1, j1 = block
    in_block = (cell % nx >= i0) & (cell % nx < i1) & (cell // nx >= j0) & (cell // nx < j1)
    own = in_block if by_cell else square.owns(sites.xy) & in_block
    n = len(sites)
    nan = np.full(n, np.nan)
    exact = (given["dbh"] > 0) & np.isfinite(given["height"])
    if not allometric or n == 0:
        return Local(sites, own, cell, rank, block, nan, nan, nan, nan, np.zeros(n), nan, exact)
    dbh, height, crown = tree_sizes(
        {name: recipe.species[name].species for name in sites.names},
        {name: e.stand for name, e in recipe.species.items() if e.stand is not None},
        sites.names,
        sites.species,
        cell,
        given["dbh"],
        given["height"],
        given["crown_radius"],
        recipe.seed,
    )
    if np.nanmax(crown, initial=0.0) >= CELL / 2:
        raise UsdForestError(
            f"a crown radius of {np.nanmax(crown):.0f} m: crowns wider than {CELL / 2:g} m are "
            "not supported"
        )
    pressure, away = pressed(crowding(sites.xy, crown, height))
    if yaw_given is not None:  # a tree whose yaw the inventory gives keeps it
        away = np.where(yaw_given, np.nan, away)
    return Local(
        sites, own, cell, rank, block, dbh, height, crown, given["crown_radius"], pressure, away,
        exact,
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class Survey:
    """What a square's survey returns: its ``cells`` (row-major indices) with the number of
    trees each holds (all of them, when sampled), its own trees per species and its own
    trees' :class:`StandSums`."""

    cells: np.ndarray
    counts: np.ndarray
    by_species: np.ndarray
    sums: StandSums


def survey(recipe, square: Square, replicate: int = 0) -> Survey:
    """A square's :class:`Survey` (a task)."""
    loc = local_sites(recipe, square, replicate)
    nx, _ = grid(recipe)
    i0, j0, i1, j1 = loc.block
    cells = np.array([j * nx + i for j in range(j0, j1) for i in range(i0, i1)], dtype=np.int64)
    counts = np.bincount(
        np.searchsorted(cells, loc.cell[np.isin(loc.cell, cells)]), minlength=len(cells)
    )
    s = loc.sites
    own = loc.own
    sums = stand_sums(
        s.names,
        _allometric(recipe),
        s.species[own],
        loc.dbh[own],
        loc.height[own],
        loc.crown[own],
        loc.given_crown[own],
        loc.pressure[own],
        INVENTORY_SPLIT if recipe.sites is not None else 1,
    )
    by_species = np.bincount(s.species[own], minlength=len(s.names))
    return Survey(cells, counts.astype(np.int64), by_species.astype(np.int64), sums)


@dataclass(frozen=True, eq=False)
class Plan:
    """What every square's placing shares: each allometric species' size ``classes``; the
    prototype of each (species, variant) (``lookup``, -1: none); each prototype's crown
    ``lean`` (degrees, NaN: symmetric); the id of each cell's first tree (``first_id``;
    None for an inventory, whose ids are its rows); for an inventory, each prototype's
    height as grown (``grown``: its top, leaves and shoots included, which in a seedling's
    class stand a third above the stem), by which its rows are scaled to their heights."""

    classes: dict[str, SizeClasses]
    lookup: np.ndarray
    lean: np.ndarray
    first_id: np.ndarray | None
    grown: np.ndarray | None = None
    girths: tuple | None = None  # each prototype's girth tape (usdforest.usd.trunk)
    # each prototype's stem lean and its azimuth (degrees; (0, 0): upright)
    stem_lean: np.ndarray | None = None


def classes_for(recipe, sums: StandSums) -> dict[str, SizeClasses]:
    """The size classes of the recipe's allometric species from the stand's sums."""
    return size_classes(
        {name: recipe.species[name].species for name in recipe.species_names},
        recipe.species_names,
        sums,
        {name: recipe.variants[name] for name in recipe.species_names},
        float(recipe.region.area),
        recipe.seed,
        height_first=recipe.sites is not None,
        split=INVENTORY_SPLIT if recipe.sites is not None else 1,
    )


def first_ids(recipe, surveys: list[Survey]) -> np.ndarray | None:
    """The id of each cell's first tree: trees are numbered in cell order (None for an
    inventory)."""
    if recipe.sites is not None:
        return None
    nx, ny = grid(recipe)
    per_cell = np.zeros(nx * ny, dtype=np.int64)
    for s in surveys:
        per_cell[s.cells] = s.counts
    return np.concatenate([[0], np.cumsum(per_cell)[:-1]]).astype(np.int64)


@dataclass(frozen=True, eq=False)
class Placed:
    """A square's own trees as placed: ``sites`` (recipe coordinates; allometric trees with
    their class as variant and their height over the class's as scale, turned away from
    their neighbours), each tree's prototype and id."""

    sites: Sites
    proto_index: np.ndarray
    ids: np.ndarray


def place(recipe, square: Square, plan: Plan, replicate: int = 0) -> Placed:
    """A square's own trees with their classes, prototypes and ids (a task)."""
    loc = local_sites(recipe, square, replicate)
    own = np.flatnonzero(loc.own)
    s = loc.sites
    sites = Sites(s.names, s.xy[own], s.species[own], s.variant[own], s.yaw[own], s.scale[own])
    variant, scale = sites.variant.copy(), sites.scale.copy()
    for k, name in enumerate(sites.names):
        if name not in plan.classes:
            continue
        at = np.flatnonzero(sites.species == k)
        if len(at):
            classes = plan.classes[name]
            # an inventory's trees as tall as their rows, tops included
            protos = plan.lookup[k, : len(classes.sizes)]
            grown = None if plan.grown is None else plan.grown[protos]
            girths = None if plan.girths is None else tuple(plan.girths[i] for i in protos)
            variant[at], scale[at] = classes.of(
                loc.height[own][at], loc.dbh[own][at], loc.exact[own][at], grown, girths
            )
    proto_index = plan.lookup[sites.species, variant].astype(np.int32)
    away = loc.away[own]
    turn = np.round(away - plan.lean[proto_index], 3) % 360.0
    ok = np.isfinite(away) & np.isfinite(turn)
    yaw = np.where(ok, turn, sites.yaw)
    if plan.stem_lean is not None and recipe.ground is not None:
        yaw = np.where(ok, yaw, downslope_yaw(sites, proto_index, plan.stem_lean, recipe))
    sites = replace(sites, variant=variant, scale=scale, yaw=yaw)
    rank = loc.rank[own]
    ids = rank if plan.first_id is None else plan.first_id[loc.cell[own]] + rank
    return Placed(sites, proto_index, ids.astype(np.int64))


SLOPE_STEP = 1.0  # m: the central differences of the ground's gradient at a tree
SLOPE_SPREAD = 10.0  # degrees of slope over which the lean's spread about down-slope narrows by e


def downslope_yaw(sites: Sites, proto_index: np.ndarray, stem_lean: np.ndarray, recipe):
    """Yaws that turn each leaning stem's lean down the slope it stands on (trunks lean
    down-slope: Lamprecht et al. 2020, Remote Sensing 12: 3744), within a spread that
    narrows as the slope steepens: the tree's own yaw, as an offset of up to 180 degrees
    from down-slope, times ``exp(-slope / SLOPE_SPREAD)`` (a stated choice). Level ground
    and upright stems keep their yaw."""
    ground = recipe.ground["field"]
    x, y = sites.xy[:, 0], sites.xy[:, 1]
    h = SLOPE_STEP
    gx = (ground.height(x + h, y) - ground.height(x - h, y)) / (2 * h)
    gy = (ground.height(x, y + h) - ground.height(x, y - h)) / (2 * h)
    slope = np.degrees(exact.arctan2(np.sqrt(gx * gx + gy * gy), np.ones(len(gx))))
    down = np.degrees(exact.arctan2(-gy, -gx))
    angle, azimuth = stem_lean[proto_index, 0], stem_lean[proto_index, 1]
    offset = ((sites.yaw + 180.0) % 360.0 - 180.0) * exact.exp(-slope / SLOPE_SPREAD)
    turned = np.round(down - azimuth + offset, 3) % 360.0
    return np.where((slope > 0.5) & (angle > 0), turned, sites.yaw)

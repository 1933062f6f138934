"""Stand structure: each tree's DBH and height, and the size classes a forest instances.

Every tree of an allometric species gets its own size: a DBH drawn from the stand's Weibull
distribution (``[species.NAME.stand]``: mean and coefficient of variation) or read from an
inventory (``[[sites]]`` rows or a stem-map CSV with ``dbh`` and ``height``), and a height from
the species' height curve with its residual scatter. The draws come from each 250 m cell's own
stream, so a tree's size never depends on which task sizes it. Trees are grouped into size
classes on a grid of log height (steps of 25 %) and log slenderness (steps of 8 %), merged
two by two (slenderness, then height, in turn) until a species has no more classes than
variants; each class is one tree asset grown to the class's mean size, and each tree
instances its class scaled by its own height over the class's, so its height is exact and
its DBH within half a slenderness step (4 %). Crown base comes from the crown-ratio model
with the basal area of trees larger than the class's mean DBH and the stand's crown
competition factor, so it rises with density. Crowns give way to neighbours: a tree whose
open-grown crown overlaps others' is pressed away from them (:func:`crowding`); its class
grows a one-sided crown (up to 35 % longer branches on one side and shorter on the other, as
one-sided as its trees are pressed on average) and the tree is turned so that the long side
faces away.

An inventory's rows are classed on a grid twice as fine, heights merged before slenderness,
at most 64 classes a species; each row takes the class whose trunk, scaled to the row's
height, measures its DBH best (:meth:`SizeClasses.of`), so every row's sizes are kept
whatever the row count. Seedlings and saplings under breast height have DBH 0 and are grown
with a trunk base of ``height / SAPLING_SLENDERNESS`` (:func:`sapling_dbh`).

What the classes need of the whole stand (per fine class: trees, sums of log height, log
slenderness and pressure; the crown area; basal area by DBH) is kept as
:class:`StandSums` in int64 fixed point, so sums from any number of tiles, added in any
order, are exact and the same. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from usdforest.grow import exact as libm
from usdforest.grow.allometry import ALLOMETRY, weibull_for
from usdforest.grow.architecture import BREAST_HEIGHT, TreeSize, dbh_of_base, scaled_dbh
from usdforest.grow.species import Species, tree_size
from usdforest.seeds import stream

HEIGHT_STEP = math.log(1.25)
SLENDERNESS_STEP = math.log(1.08)
FIXED = 1e9  # fixed point of the stand's sums (1e-9 of a unit; 9e9 units fit in int64)
DBH_BIN = 0.001  # m: the bins of the stand's basal area by DBH
MAX_ASYMMETRY = 0.35
# height over the stem's diameter at the ground of a sapling under breast height: an assumption
# of ours (no per-species equation was at hand), within the 2-4-year Scots pine regeneration
# of Geudens et al. 2004 (Annals of Forest Science 61:653; collar diameters 0.3-2.7 cm)
SAPLING_SLENDERNESS = 50.0
# an inventory's fine grid: steps of 12 % in height and 4 % in slenderness, so that a row
# that shares its class with others is within 2 % of the class's slenderness
INVENTORY_SPLIT = 2
EXACT_DBH = 0.025  # the log-DBH error an inventory row's class may leave (2.5 %)
SUM_COLUMNS = ("trees", "log_height", "log_slenderness", "pressure", "crowns_given", "crown")


@dataclass(frozen=True)
class StandSpec:
    """A species' DBH distribution in a stand (metres): Weibull with this mean and CV, no tree
    thinner than ``dbh_min``."""

    dbh_mean: float
    dbh_cv: float = 0.3
    dbh_min: float = 0.04


def draw_dbh(spec: StandSpec, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` DBHs (m) from the truncated Weibull of ``spec`` (inverse CDF above ``dbh_min``)."""
    k, lam = weibull_for(spec.dbh_mean, spec.dbh_cv)
    f0 = 1.0 - math.exp(-((spec.dbh_min / lam) ** k))
    u = f0 + (1.0 - f0) * rng.uniform(size=n)
    return lam * libm.power(-libm.log1p(-u), 1.0 / k)


def _fixed(x) -> np.ndarray:
    return np.round(np.asarray(x, dtype=float) * FIXED).astype(np.int64)


def tree_sizes(
    species: dict[str, Species],
    stands: dict[str, StandSpec],
    names: tuple[str, ...],
    site_species: np.ndarray,
    cell: np.ndarray,
    given_dbh: np.ndarray,
    given_height: np.ndarray,
    given_crown: np.ndarray,
    seed: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each site's DBH (m), height (m) and open-grown crown radius (m): NaN for trees of
    non-allometric species. Draws come from the stream of the site's ``cell`` (and its
    species), taken in site order; ``given_*`` (NaN where not given) come from an inventory:
    a tree of known height and unknown DBH takes the DBH whose mean height it has."""
    dbh = np.array(given_dbh, dtype=float, copy=True)
    height = np.array(given_height, dtype=float, copy=True)
    crown = np.full(len(site_species), np.nan)
    for k, name in enumerate(names):
        sp = species[name]
        if sp.allometry is None:
            continue
        a = ALLOMETRY[sp.allometry]
        spec = stands.get(name, StandSpec(sp.reference_dbh / 100.0))
        idx = np.flatnonzero(site_species == k)
        drawn = np.empty(len(idx))
        noise = np.empty(len(idx))
        order = np.argsort(cell[idx], kind="stable")  # each cell's trees, in site order
        cells, start = np.unique(cell[idx][order], return_index=True)
        ends = np.append(start[1:], len(idx))[: len(start)]
        for c, a0, a1 in zip(cells, start, ends, strict=True):
            at = order[a0:a1]
            rng = stream(seed, "stand", name, "cell", int(c))
            drawn[at] = draw_dbh(spec, len(at), rng)
            noise[at] = rng.standard_normal(len(at))
        unknown = np.isnan(dbh[idx]) | (dbh[idx] == 0)  # DBH 0: a sapling's
        d = np.where(unknown, drawn, dbh[idx])
        h_curve = a.height(d * 100.0) * libm.exp(a.height_sd * noise)
        d = np.where(unknown & ~np.isnan(height[idx]), a.dbh(height[idx]) / 100, d)
        young = unknown & (height[idx] < BREAST_HEIGHT)
        d = np.where(young, sapling_dbh(np.where(young, height[idx], 1.0)), d)
        dbh[idx] = d
        height[idx] = np.where(np.isnan(height[idx]), h_curve, height[idx])
        own = a.crown_radius(d * 100.0)
        crown[idx] = np.where(np.isnan(given_crown[idx]), own, given_crown[idx])
    return dbh, height, crown


def sapling_dbh(height: np.ndarray) -> np.ndarray:
    """The DBH (m) a tree shorter than breast height is grown with: its trunk template's base
    then measures ``height / SAPLING_SLENDERNESS`` across (the conical template's breast
    height lies above such a tree, so the DBH only sets the base). Its row and ``trees.csv``
    say DBH 0."""
    h = np.asarray(height, dtype=float)
    return dbh_of_base(h / SAPLING_SLENDERNESS, h)


def crowding(xy: np.ndarray, crown: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Per tree, the crowding vector (n, 2), pointing at the neighbours that press it: the
    sum over every neighbour whose open-grown crown (radius ``crown``) overlaps the tree's of
    the unit vector towards it times the overlap's share of the two radii times its height
    over the tree's (at most 2). Trees with NaN ``crown`` neither press nor are pressed. The
    sums are exact (fixed point), so a tree's vector does not depend on the order or company
    its neighbours come in."""
    from scipy.spatial import cKDTree

    out = np.zeros((len(xy), 2), dtype=np.int64)
    ok = np.flatnonzero(np.isfinite(crown))
    if len(ok) < 2:
        return out.astype(float)
    pairs = cKDTree(xy[ok]).query_pairs(2.0 * float(crown[ok].max()), output_type="ndarray")
    i, j = ok[pairs[:, 0]], ok[pairs[:, 1]]
    v = xy[j] - xy[i]
    d = np.hypot(v[:, 0], v[:, 1])
    reach = crown[i] + crown[j]
    near = (d > 1e-9) & (d < reach)
    i, j, v, d, reach = i[near], j[near], v[near], d[near], reach[near]
    overlap = (1.0 - d / reach)[:, None] * v / d[:, None]
    np.add.at(out, i, _fixed(overlap * np.minimum(height[j] / height[i], 2.0)[:, None]))
    np.add.at(out, j, _fixed(-overlap * np.minimum(height[i] / height[j], 2.0)[:, None]))
    return out / FIXED


def pressed(push: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pressure (0-1) of crowding vectors ``push`` and the direction (degrees from +x)
    each crown grows away from its neighbours, NaN where they do not press it to one side."""
    pressure = np.minimum(np.hypot(push[:, 0], push[:, 1]), 1.0)
    away = np.where(
        pressure >= 0.05, np.round(np.degrees(libm.arctan2(-push[:, 1], -push[:, 0])), 3), np.nan
    )
    return pressure, away


def fine_keys(height: np.ndarray, dbh: np.ndarray, split: int = 1) -> np.ndarray:
    """(n, 2) int64: each tree's cell on the grid of log height and log slenderness (its
    steps divided by ``split``: an inventory's finer grid)."""
    lh = libm.log(height)
    ls = libm.log(height / dbh)
    return np.stack(
        [np.floor(lh * split / HEIGHT_STEP), np.floor(ls * split / SLENDERNESS_STEP)], axis=1
    ).astype(np.int64)


@dataclass(frozen=True, eq=False)
class StandSums:
    """What the size classes need of a stand, as exact int64 fixed-point sums: per
    allometric species, its fine classes' ``keys`` (k, 2) and ``sums`` (k, 6) (see
    ``SUM_COLUMNS``: trees, and sums of log height, log slenderness, pressure, given crowns'
    count and radii); all trees' crown area (m²) and basal area (m²) per 1 mm DBH bin."""

    keys: dict[str, np.ndarray]
    sums: dict[str, np.ndarray]
    crown_area: int
    basal: np.ndarray


def stand_sums(
    names: tuple[str, ...],
    allometric: set[str],
    site_species: np.ndarray,
    dbh: np.ndarray,
    height: np.ndarray,
    crown: np.ndarray,
    given_crown: np.ndarray,
    pressure: np.ndarray,
    split: int = 1,
) -> StandSums:
    """The :class:`StandSums` of some trees (a tile's own), on the fine grid divided by
    ``split``."""
    keys, sums = {}, {}
    for k, name in enumerate(names):
        if name not in allometric:
            continue
        idx = np.flatnonzero(site_species == k)
        uniq, inverse = np.unique(
            fine_keys(height[idx], dbh[idx], split), axis=0, return_inverse=True
        )
        inverse = inverse.reshape(-1)
        given = np.isfinite(given_crown[idx])
        cols = [
            np.ones(len(idx), dtype=np.int64),
            _fixed(libm.log(height[idx])),
            _fixed(libm.log(height[idx] / dbh[idx])),
            _fixed(pressure[idx]),
            given.astype(np.int64),
            np.where(given, _fixed(np.where(given, given_crown[idx], 0.0)), 0),
        ]
        acc = np.zeros((len(uniq), len(cols)), dtype=np.int64)
        for c, col in enumerate(cols):
            np.add.at(acc[:, c], inverse, col)
        keys[name], sums[name] = uniq.reshape(-1, 2).astype(np.int64), acc
    known = np.isfinite(dbh)
    bins = np.floor(dbh[known] / DBH_BIN).astype(np.int64)
    basal = np.zeros(int(bins.max()) + 1 if len(bins) else 0, dtype=np.int64)
    np.add.at(basal, bins, _fixed(math.pi / 4.0 * dbh[known] ** 2))
    area = int(_fixed(math.pi * crown[np.isfinite(crown)] ** 2).sum())
    return StandSums(keys, sums, area, basal)


def merge_sums(parts: Iterable[StandSums]) -> StandSums:
    """One :class:`StandSums` of several (exact: the same in any order)."""
    keys: dict[str, list] = {}
    sums: dict[str, list] = {}
    area, basal = 0, np.zeros(0, dtype=np.int64)
    for p in parts:
        for name in p.keys:
            keys.setdefault(name, []).append(p.keys[name])
            sums.setdefault(name, []).append(p.sums[name])
        area += p.crown_area
        if len(p.basal) > len(basal):
            basal = np.concatenate([basal, np.zeros(len(p.basal) - len(basal), np.int64)])
        basal[: len(p.basal)] += p.basal
    out_keys, out_sums = {}, {}
    for name in keys:
        k = np.concatenate(keys[name]).reshape(-1, 2)
        s = np.concatenate(sums[name]).reshape(-1, len(SUM_COLUMNS))
        uniq, inverse = np.unique(k, axis=0, return_inverse=True)
        acc = np.zeros((len(uniq), s.shape[1]), dtype=np.int64)
        np.add.at(acc, inverse.reshape(-1), s)
        out_keys[name], out_sums[name] = uniq.reshape(-1, 2), acc
    return StandSums(out_keys, out_sums, area, basal)


@dataclass(frozen=True, eq=False)
class SizeClasses:
    """A species' size classes: fine keys (height, slenderness) divided by ``2**shift`` give
    the class ``keys`` (sorted); ``sizes`` the size each class's tree asset grows to."""

    shift: tuple[int, int]
    keys: np.ndarray
    sizes: tuple[TreeSize, ...]
    split: int = 1  # the fine grid's steps divided by this (an inventory's: INVENTORY_SPLIT)

    def of(
        self,
        height: np.ndarray,
        dbh: np.ndarray,
        exact: np.ndarray | None = None,
        grown: np.ndarray | None = None,
        girths: tuple | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each tree's class and its scale: its height over its class's (over the class's
        tree as ``grown``, when given per class). A tree marked ``exact`` (an inventory row
        that gives both sizes) takes instead the class whose scaled trunk measures its DBH
        best (within ``EXACT_DBH`` if any does, the nearest in height among those), so its
        DBH does not depend on where the class grid fell: by each class's own girth tape
        where ``girths`` gives them (:class:`usdforest.usd.trunk.StemGirth`), else by the
        conical trunk's (:func:`scaled_dbh`)."""
        coarse = np.floor_divide(fine_keys(height, dbh, self.split), np.left_shift(1, self.shift))
        variant = np.full(len(height), -1, dtype=np.int32)
        for c, key in enumerate(self.keys):
            variant[np.all(coarse == key, axis=1)] = c
        if np.any(variant < 0):
            raise ValueError("a tree outside every size class (sizes differ from the survey)")
        h_class = np.array([s.height for s in self.sizes])
        tall = h_class if grown is None else np.asarray(grown, dtype=float)
        rows = np.flatnonzero(exact) if exact is not None else np.zeros(0, dtype=np.int64)
        if len(rows):
            d_class = np.array([s.dbh for s in self.sizes])
            ratio = height[rows, None] / tall[None, :]
            if girths is None:
                measured = scaled_dbh(d_class, h_class, ratio)
            else:
                measured = np.stack([g.dbh(ratio[:, c]) for c, g in enumerate(girths)], axis=1)
            with np.errstate(divide="ignore"):  # a class that would leave it no DBH: inf
                err = np.abs(libm.log(measured / dbh[rows, None]))
            far = np.abs(libm.log(ratio))
            close = err <= EXACT_DBH
            score = np.where(close, far, 1e3 + err)  # any close class before every other
            variant[rows] = np.argmin(score, axis=1)
        return variant, height / tall[variant]


def size_classes(
    species: dict[str, Species],
    names: tuple[str, ...],
    sums: StandSums,
    max_classes: dict[str, int],
    area_m2: float,
    seed: int,
    height_first: bool = False,
    split: int = 1,
) -> dict[str, SizeClasses]:
    """Each allometric species' size classes from its stand's sums (see the module
    docstring): at most ``max_classes`` per species, grown at the stand's crown competition
    factor and each class's basal area of larger trees. ``height_first`` (an inventory)
    merges heights before any slenderness: a tree's height is exact whatever its class, its
    DBH only as near as its class's slenderness. ``split``: the sums' fine grid's."""
    area_m2 = max(area_m2, 1e-9)
    ccf = 100.0 * sums.crown_area / FIXED / area_m2 if sums.keys else 100.0
    larger = np.concatenate([np.cumsum(sums.basal[::-1])[::-1], [0]]) / FIXED  # m², bin and up
    out = {}
    for name in names:
        if species[name].allometry is None:
            continue
        fine = sums.keys.get(name, np.zeros((0, 2), dtype=np.int64))
        if len(fine) == 0:
            out[name] = SizeClasses((0, 0), np.zeros((0, 2), dtype=np.int64), (), split)
            continue
        # heights merged until one class spans them all (an inventory's), then slenderness
        span = int(fine[:, 0].max() - fine[:, 0].min()).bit_length() + 1 if height_first else 0
        step = 0
        while True:  # merge slenderness classes two by two, then height, and so on
            if step < span:
                shift = (step, 0)
            else:
                shift = (span + (step - span) // 2, (step - span + 1) // 2)
            coarse, inverse = np.unique(
                np.floor_divide(fine, np.left_shift(1, shift)), axis=0, return_inverse=True
            )
            if len(coarse) <= max_classes[name]:
                break
            step += 1
        inverse = inverse.reshape(-1)
        acc = np.zeros((len(coarse), len(SUM_COLUMNS)), dtype=np.int64)
        np.add.at(acc, inverse, sums.sums[name])
        count = acc[:, 0].astype(float)
        rng = stream(seed, "classes", name)
        sizes = []
        for c in range(len(coarse)):
            # rounded so that the class's grammar (and its bytes) do not depend on the last
            # bits of a log-mean
            hc = round(math.exp(acc[c, 1] / FIXED / count[c]), 3)
            dc = round(hc / math.exp(acc[c, 2] / FIXED / count[c]) * 100.0, 2)
            b = min(math.floor(dc / 100.0 / DBH_BIN) + 1, len(larger) - 1)
            bal = float(larger[b]) / (area_m2 / 1e4)
            size = tree_size(species[name], rng, dbh=dc, height=hc, bal=bal, ccf=ccf)
            pressure = float(acc[c, 3] / FIXED / count[c])
            size = replace(size, asymmetry=round(MAX_ASYMMETRY * pressure, 3))
            n_given = int(acc[c, 4])
            if n_given:  # the inventory's radii, the allometry's for the rest
                total = acc[c, 5] / FIXED + (count[c] - n_given) * size.crown_radius
                size = replace(size, crown_radius=round(float(total / count[c]), 4))
            sizes.append(size)
        out[name] = SizeClasses(shift, coarse.reshape(-1, 2), tuple(sizes), split)
    return out

"""Stand structure: each tree's DBH and height, and the size classes a forest instances.

Every tree of an allometric species gets its own size: a DBH drawn from the stand's Weibull
distribution (``[species.NAME.stand]``: mean and coefficient of variation) or read from an
inventory (``[[sites]]`` rows or a stem-map CSV with ``dbh`` and ``height``), and a height from
the species' height curve with its residual scatter. Trees are grouped into size classes on a
grid of log height (steps of 25 %) and log slenderness (steps of 8 %); each class is one tree
asset grown to the class's mean size, and each tree instances its class scaled by its own
height over the class's, so its height is exact and its DBH within half a slenderness step
(4 %). Crown base comes from the crown-ratio model with each class's basal area of larger
trees and the stand's crown competition factor, so it rises with density. Crowns give way to
neighbours: a tree whose open-grown crown overlaps others' is pressed away from them
(:func:`crowding`); its class grows a one-sided crown (up to 35 % longer branches on one side
and shorter on the other, as one-sided as its trees are pressed on average) and the tree is
turned so that the long side faces away. Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from usdforest.grow.allometry import ALLOMETRY, basal_area_larger, weibull_for
from usdforest.grow.architecture import TreeSize
from usdforest.grow.species import Species, tree_size
from usdforest.seeds import stream

HEIGHT_STEP = math.log(1.25)
SLENDERNESS_STEP = math.log(1.08)


@dataclass(frozen=True)
class StandSpec:
    """A species' DBH distribution in a stand (metres): Weibull with this mean and CV, no tree
    thinner than ``dbh_min``."""

    dbh_mean: float
    dbh_cv: float = 0.3
    dbh_min: float = 0.04


@dataclass(frozen=True, eq=False)
class StandSizes:
    """Per site: ``dbh`` (m) and ``height`` (m), NaN for trees of non-allometric species;
    per species: the class targets (one tree asset each); ``variant`` and ``scale`` are the
    sites' new marks; ``away`` the direction (degrees from +x) a tree's crown grows away
    from its neighbours, NaN where they do not press it to one side."""

    dbh: np.ndarray
    height: np.ndarray
    variant: np.ndarray
    scale: np.ndarray
    classes: dict[str, tuple[TreeSize, ...]]
    away: np.ndarray


def draw_dbh(spec: StandSpec, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` DBHs (m) from the truncated Weibull of ``spec`` (inverse CDF above ``dbh_min``)."""
    k, lam = weibull_for(spec.dbh_mean, spec.dbh_cv)
    f0 = 1.0 - math.exp(-((spec.dbh_min / lam) ** k))
    u = f0 + (1.0 - f0) * rng.uniform(size=n)
    return lam * (-np.log1p(-u)) ** (1.0 / k)


def crowding(xy: np.ndarray, crown: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Per tree, the crowding vector (n, 2), pointing at the neighbours that press it: the
    sum over every neighbour whose open-grown crown (radius ``crown``) overlaps the tree's of
    the unit vector towards it times the overlap's share of the two radii times its height
    over the tree's (at most 2). Trees with NaN ``crown`` neither press nor are pressed."""
    from scipy.spatial import cKDTree

    out = np.zeros((len(xy), 2))
    ok = np.flatnonzero(np.isfinite(crown))
    if len(ok) < 2:
        return out
    pairs = cKDTree(xy[ok]).query_pairs(2.0 * float(crown[ok].max()), output_type="ndarray")
    i, j = ok[pairs[:, 0]], ok[pairs[:, 1]]
    v = xy[j] - xy[i]
    d = np.hypot(v[:, 0], v[:, 1])
    reach = crown[i] + crown[j]
    near = (d > 1e-9) & (d < reach)
    i, j, v, d, reach = i[near], j[near], v[near], d[near], reach[near]
    overlap = (1.0 - d / reach)[:, None] * v / d[:, None]
    np.add.at(out, i, overlap * np.minimum(height[j] / height[i], 2.0)[:, None])
    np.add.at(out, j, -overlap * np.minimum(height[i] / height[j], 2.0)[:, None])
    return out


MAX_ASYMMETRY = 0.35


def stand_sizes(
    species: dict[str, Species],
    stands: dict[str, StandSpec],
    names: tuple[str, ...],
    site_species: np.ndarray,
    xy: np.ndarray,
    given_dbh: np.ndarray,
    given_height: np.ndarray,
    given_crown: np.ndarray,
    area_m2: float,
    max_classes: dict[str, int],
    seed: int,
) -> StandSizes:
    """Sizes and size classes for every site (see the module docstring).

    ``given_dbh`` / ``given_height`` / ``given_crown`` (crown radius; m, NaN where not
    given) come from an inventory; a class whose trees give crown radii grows to their mean.
    """
    n = len(site_species)
    dbh = np.array(given_dbh, dtype=float, copy=True)
    height = np.array(given_height, dtype=float, copy=True)
    variant = np.zeros(n, dtype=np.int32)
    scale = np.ones(n)
    classes: dict[str, tuple[TreeSize, ...]] = {}
    allometric = [s for s in names if species[s].allometry is not None]
    for k, name in enumerate(names):
        if name not in allometric:
            continue
        sp = species[name]
        a = ALLOMETRY[sp.allometry or ""]
        idx = np.flatnonzero(site_species == k)
        rng = stream(seed, "stand", name)
        spec = stands.get(name, StandSpec(sp.reference_dbh / 100.0))
        drawn = draw_dbh(spec, len(idx), rng)
        noise = rng.standard_normal(len(idx))
        d = np.where(np.isnan(dbh[idx]), drawn, dbh[idx])
        h_curve = a.height(d * 100.0) * np.exp(a.height_sd * noise)
        # a tree of known height and unknown DBH takes the DBH whose mean height it has
        d = np.where(np.isnan(dbh[idx]) & ~np.isnan(height[idx]), a.dbh(height[idx]) / 100, d)
        dbh[idx] = d
        height[idx] = np.where(np.isnan(height[idx]), h_curve, height[idx])
    # competition: basal area of larger trees (all species) and the crown competition factor
    known = ~np.isnan(dbh)
    bal = np.zeros(n)
    area_ha = area_m2 / 1e4
    bal[known] = basal_area_larger(dbh[known] * 100.0, area_ha)
    crown = np.full(n, np.nan)
    for k, name in enumerate(names):
        if name in allometric:
            sel = site_species == k
            own = ALLOMETRY[species[name].allometry or ""].crown_radius(dbh[sel] * 100.0)
            crown[sel] = np.where(np.isnan(given_crown[sel]), own, given_crown[sel])
    ccf = 100.0 * float(np.nansum(math.pi * crown**2)) / max(area_m2, 1e-9) if n else 100.0
    # crowns grow away from their neighbours: each class's crowns are as one-sided as its
    # trees' mean pressure, and each tree turns its long side away from it
    push = crowding(np.asarray(xy, dtype=float), crown, height)
    pressure = np.minimum(np.hypot(push[:, 0], push[:, 1]), 1.0)
    away = np.where(
        pressure >= 0.05, np.round(np.degrees(np.arctan2(-push[:, 1], -push[:, 0])), 3), np.nan
    )
    for k, name in enumerate(names):
        if name not in allometric:
            continue
        idx = np.flatnonzero(site_species == k)
        if len(idx) == 0:
            classes[name] = ()
            continue
        lh = np.log(height[idx])
        ls = np.log(height[idx] / dbh[idx])
        hs, ss = HEIGHT_STEP, SLENDERNESS_STEP
        while True:
            key = np.stack([np.floor(lh / hs), np.floor(ls / ss)], axis=1).astype(np.int64)
            uniq, inverse = np.unique(key, axis=0, return_inverse=True)
            if len(uniq) <= max_classes[name]:
                break
            hs, ss = hs * 1.3, ss * 1.3
        inverse = inverse.reshape(-1)
        count = np.bincount(inverse)
        mh = np.exp(np.bincount(inverse, lh) / count)
        ms = np.exp(np.bincount(inverse, ls) / count)
        mbal = np.bincount(inverse, bal[idx]) / count
        mpress = np.bincount(inverse, pressure[idx]) / count
        rng = stream(seed, "classes", name)
        sizes = []
        for c in range(len(uniq)):
            # rounded so that the class's grammar (and its bytes) do not depend on the last
            # bits of a log-mean
            hc = round(float(mh[c]), 3)
            dc = round(hc / float(ms[c]) * 100.0, 2)
            size = tree_size(species[name], rng, dbh=dc, height=hc, bal=float(mbal[c]), ccf=ccf)
            size = replace(size, asymmetry=round(MAX_ASYMMETRY * float(mpress[c]), 3))
            gc = given_crown[idx][inverse == c]
            if np.isfinite(gc).any():  # the inventory's radii, the allometry's for the rest
                mean = float(np.mean(np.where(np.isnan(gc), size.crown_radius, gc)))
                size = replace(size, crown_radius=round(mean, 4))
            sizes.append(size)
        classes[name] = tuple(sizes)
        variant[idx] = inverse.astype(np.int32)
        scale[idx] = height[idx] / np.array([s.height for s in sizes])[inverse]
    return StandSizes(dbh, height, variant, scale, classes, away)


def with_sizes(sites, sizes: StandSizes, names_allometric: set[str]):
    """``sites`` with the variant and scale of allometric species' trees replaced."""
    is_allo = np.isin(sites.species, [sites.names.index(n) for n in names_allometric])
    return replace(
        sites,
        variant=np.where(is_allo, sizes.variant, sites.variant).astype(np.int32),
        scale=np.where(is_allo, sizes.scale, sites.scale),
    )

"""Seasons: what a recipe's ``season`` does to its species (the leaves they carry and their
colour).

In ``summer`` (the default) nothing changes. In ``autumn`` and ``winter`` each species keeps
the fraction of its leaves its geometry's ``autumn_leaf_on`` and ``winter_leaf_on`` say (a
broadleaf by default all of them in autumn and none in winter; the conifer presets all of them
in both) and wears its ``autumn_color`` on those it keeps (an evergreen's is its summer
colour). The wood, twigs included, is the same in every season, so a leaf-off tree is its
summer tree without leaves. The leaves kept are drawn from the tree's own seed, the same
leaves whatever else the recipe holds.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from usdforest.grow.placement import Placement
from usdforest.grow.species import Species

SEASONS = ("summer", "autumn", "winter")


def seasonal(species: Species, season: str) -> Species:
    """``species`` as it is in ``season``: its geometry's ``leaf_on`` and leaf colour."""
    if season == "summer":
        return species
    g = species.geometry
    on = g.autumn_leaf_on if season == "autumn" else g.winter_leaf_on
    return replace(species, geometry=replace(g, leaf_on=on, leaf_color=g.autumn_color))


def keep_leaves(placement: Placement, fraction: float, rng: np.random.Generator) -> Placement:
    """``placement`` with ``round(fraction n)`` of its ``n`` leaves, drawn from ``rng`` (in
    their order; all of them when ``fraction`` is 1)."""
    n = len(placement.leaf_proto)
    if fraction >= 1.0:
        return placement
    keep = np.sort(rng.permutation(n)[: round(fraction * n)])
    return replace(
        placement,
        leaf_position=placement.leaf_position[keep],
        leaf_orient=placement.leaf_orient[keep],
        leaf_scale=placement.leaf_scale[keep],
        leaf_segment=placement.leaf_segment[keep],
        leaf_proto=placement.leaf_proto[keep],
    )

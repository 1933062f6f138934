"""Small stands of allometric trees that several tests build: a recipe from its sites, and
a forest built from a recipe's text."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

# the four allometric presets, each under a short name the sites use
SPECIES = """
[species.pine]
preset = "scots-pine"
[species.beech]
preset = "european-beech"
[species.birch]
preset = "silver-birch"
[species.spruce]
preset = "norway-spruce"
"""

# a beech and a pine 8 m apart on a 20 m square (the seasons' and the flutter's stand)
BEECH_AND_PINE = """
[[sites]]
x = 6.0
y = 10.0
species = "beech"
dbh = 0.25
height = 18.0
[[sites]]
x = 14.0
y = 10.0
species = "pine"
dbh = 0.25
height = 18.0
"""


def beech_and_pine(seed: int) -> str:
    """The recipe of :data:`BEECH_AND_PINE` on its 20 m square, with the two presets."""
    return (
        f"seed = {seed}\n[region]\nbounds = [0.0, 0.0, 20.0, 20.0]\n{BEECH_AND_PINE}\n"
        '[species.beech]\npreset = "european-beech"\n[species.pine]\npreset = "scots-pine"\n'
    )


def allometric_stand(seed: int, size: float, sites: list[str], extra: str = "") -> str:
    """A recipe of ``sites`` (TOML inline tables) on a ``size`` m square, the four species
    and ``extra`` (more tables)."""
    rows = ",\n".join(f"  {{ {s} }}" for s in sites)
    return (
        f"seed = {seed}\nsites = [\n{rows},\n]\n[region]\nbounds = [0, 0, {size:g}, {size:g}]\n"
        + SPECIES
        + extra
    )


def build_text(root: Path, name: str, text: str, **overrides) -> Path:
    """``root/name.usda``, the forest of the recipe ``text`` (``overrides``: ``seed``,
    ``hard_core`` or ``season`` over it), built without a thumbnail."""
    from usdforest.recipe import parse_recipe
    from usdforest.usd.forest import write_forest

    out = root / f"{name}.usda"
    recipe = parse_recipe(tomllib.loads(text), root, f"{name}.toml", **overrides)
    write_forest(recipe, out, thumbnail=False)
    return out


def slice_middles(t: np.ndarray, rate: float, fps: float, start: float, end: float) -> np.ndarray:
    """The time a rolling lidar sweep casts each pulse fired at ``t`` (s; sweeps of ``rate``
    Hz from ``start``, the flight ending at ``end``): the middle of the part of its sweep
    between the two time codes (``fps`` a second, from 0) on either side of it."""
    t = np.asarray(t, dtype=float)
    sweep = np.floor((t - start) * rate + 1e-9)
    t0 = start + sweep / rate
    t1 = np.minimum(t0 + 1 / rate, end)
    code = np.floor(t * fps + 1e-9)
    return (np.maximum(t0, code / fps) + np.minimum(t1, (code + 1) / fps)) / 2

"""Small stands of allometric trees that several tests build: a recipe from its sites."""

from __future__ import annotations

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


def allometric_stand(seed: int, size: float, sites: list[str], extra: str = "") -> str:
    """A recipe of ``sites`` (TOML inline tables) on a ``size`` m square, the four species
    and ``extra`` (more tables)."""
    rows = ",\n".join(f"  {{ {s} }}" for s in sites)
    return (
        f"seed = {seed}\nsites = [\n{rows},\n]\n[region]\nbounds = [0, 0, {size:g}, {size:g}]\n"
        + SPECIES
        + extra
    )

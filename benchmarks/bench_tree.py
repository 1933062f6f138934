"""Build one tree asset (grow, place templates, write .usdc) with about 1k, 10k, 100k leaves."""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

from usdforest.grow.species import get_species
from usdforest.usd.tree import build_tree, write_tree

BROADLEAF = get_species("broadleaf")
OUT = Path(tempfile.mkdtemp(prefix="usdforest-bench-"))


def _tree(leaves_per_site: float) -> tuple[int, str]:
    sp = replace(BROADLEAF, geometry=replace(BROADLEAF.geometry, leaves_per_site=leaves_per_site))
    b = write_tree(sp, OUT / "tree.usdc", seed=1, force=True)
    return b.placement.n_leaves, "leaves"


def _preset(name: str) -> tuple[int, str, str]:
    """A preset grown, placed and bounded with its levels of detail (no file written)."""
    b = build_tree(get_species(name), seed=1)
    return b.placement.n_leaves, "leaves", "built in memory"


def _written(name: str) -> tuple[int, str, str]:
    """An allometric preset's reference tree (its allometry at its reference DBH), written."""
    b = write_tree(get_species(name), OUT / f"{name}.usdc", seed=1, force=True)
    return b.placement.n_leaves, "leaves", f"{b.placement.n_wood:,} wood prims, written"


BENCHMARKS = {
    "tree: broadleaf, ~1k leaves, written": lambda: _tree(3.0),
    "tree: broadleaf, ~10k leaves, written": lambda: _tree(28.0),
    "tree: broadleaf, ~100k leaves, written": lambda: _tree(285.0),
    "tree: broadleaf, ~1M leaves, written": lambda: _tree(2850.0),
    "tree: paper-rule-1 preset, built": lambda: _preset("paper-rule-1"),
    "tree: paper-rule-3 preset, built": lambda: _preset("paper-rule-3"),
    "tree: pine preset, built": lambda: _preset("pine"),
    "tree: scots-pine (20 cm, 21 m), written": lambda: _written("scots-pine"),
    "tree: norway-spruce (20 cm, 19 m), written": lambda: _written("norway-spruce"),
    "tree: european-beech (20 cm, 13 m), written": lambda: _written("european-beech"),
}

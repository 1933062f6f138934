"""Build one tree asset (grow, place templates, write .usdc) with about 1k, 10k, 100k leaves."""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

from usdforest.species import get_species
from usdforest.usd.tree import write_tree

BROADLEAF = get_species("broadleaf")
OUT = Path(tempfile.mkdtemp(prefix="usdforest-bench-"))


def _tree(leaves_per_site: float) -> tuple[int, str]:
    sp = replace(BROADLEAF, geometry=replace(BROADLEAF.geometry, leaves_per_site=leaves_per_site))
    b = write_tree(sp, OUT / "tree.usdc", seed=1, force=True)
    return b.placement.n_leaves, "leaves"


BENCHMARKS = {
    "tree: broadleaf, ~1k leaves, written": lambda: _tree(3.0),
    "tree: broadleaf, ~10k leaves, written": lambda: _tree(28.0),
    "tree: broadleaf, ~100k leaves, written": lambda: _tree(285.0),
}

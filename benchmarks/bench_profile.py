"""Whole-tree CAD models: extraction, and growing a tree from the extracted profile.

Uses the shared CC0 samples (``../shared/cad-samples``); without them these benchmarks are
not registered.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import tomli_w

from usdforest.cad.extract import extract_tree
from usdforest.cad.parts import read_cad
from usdforest.recipe import read_species
from usdforest.usd.template import write_template
from usdforest.usd.tree import write_tree

SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "cad-samples"
OUT = Path(tempfile.mkdtemp(prefix="usdforest-bench-profile-"))
SOURCE_TRIANGLES = (
    {n: read_cad(SAMPLES / f"{n}.obj").n_triangles for n in ("Tree_2", "Pine_1")}
    if (SAMPLES / "Tree_2.obj").is_file()
    else {}
)


def _extract(name: str) -> tuple[int, str, str]:
    ex = extract_tree(SAMPLES / f"{name}.obj")
    folder = OUT / name
    folder.mkdir(exist_ok=True)
    for t in ex.templates:
        write_template(t, folder / f"{t.name}.usdc")
    (folder / "profile.toml").write_text(tomli_w.dumps(ex.profile()))
    return (
        SOURCE_TRIANGLES[name],
        "source triangles",
        f"{len(ex.branches)} branches, {len(ex.clumps)} clumps; templates and profile written",
    )


def _grow(name: str) -> tuple[int, str, str]:
    folder = OUT / name
    if not (folder / "profile.toml").is_file():
        _extract(name)
    recipe = OUT / f"{name}.toml"
    recipe.write_text(f'[species.m]\nprofile = "{name}/profile.toml"\n')
    entry = read_species(recipe)["m"]
    b = write_tree(
        entry.species, OUT / f"{name}.usdc", template_base=entry.template_base, force=True
    )
    return (
        b.placement.n_wood + b.placement.n_leaves,
        "prims+instances",
        f"{b.placement.n_wood} wood prims, {b.placement.n_leaves} clumps, written",
    )


BENCHMARKS = (
    {
        "extract: Tree_2.obj": lambda: _extract("Tree_2"),
        "extract: Pine_1.obj": lambda: _extract("Pine_1"),
        "profile tree: Tree_2, grown and written": lambda: _grow("Tree_2"),
        "profile tree: Pine_1, grown and written": lambda: _grow("Pine_1"),
    }
    if (SAMPLES / "Tree_2.obj").is_file()
    else {}
)

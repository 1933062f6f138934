"""Forest sites: sample the recipe's point process and marks (pure numpy, no USD)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from usdforest.atomic import atomic_path
from usdforest.recipe import Recipe
from usdforest.seeds import stream
from usdforest.sites.cells import grid, sample_cells
from usdforest.sites.pointprocess import draw_marks
from usdforest.sites.table import Sites


def sample_sites(recipe: Recipe, replicate: int = 0) -> Sites:
    """Sites of one replicate: the recipe's explicit sites, or its point process sampled cell
    by cell (:mod:`usdforest.sites.cells`: thinning, hard core, marks), in cell order.

    Replicate 0 is what ``usdforest build`` places. Each replicate draws from its own
    streams, seeded by (seed, replicate and the cell; explicit sites: seed, "marks",
    replicate). These are the sites' drawn marks: a build sizes allometric species' trees
    on top (:mod:`usdforest.sites.stand`).
    """
    if recipe.sites is not None:
        return inventory_sites(recipe, replicate)
    nx, ny = grid(recipe)
    return sample_cells(recipe, replicate, (0, 0, nx, ny)).sites


def inventory_sites(recipe: Recipe, replicate: int = 0) -> Sites:
    """The recipe's explicit sites (``[[sites]]`` or a stem map), in their order, with the
    marks they do not give drawn from (seed, "marks", replicate)."""
    names = recipe.species_names
    xy = np.array([[s["x"], s["y"]] for s in recipe.sites], dtype=float).reshape(-1, 2)
    marks = draw_marks(
        xy,
        [w for _, w in recipe.mix],
        [recipe.variants[n] for n in names],
        recipe.scale.as_tuple(),
        stream(recipe.seed, "marks", replicate),
        recipe.ground["field"].height if recipe.ground is not None else None,
        names,
        recipe.region.bounds,
    )
    species, yaw, scale = marks.species.copy(), marks.yaw.copy(), marks.scale.copy()
    for i, s in enumerate(recipe.sites):
        if "species" in s:
            species[i] = names.index(s["species"])
        if "yaw" in s:
            yaw[i] = s["yaw"]
        if "scale" in s:
            scale[i] = s["scale"]
    variant = np.minimum(marks.variant, np.array([recipe.variants[n] for n in names])[species] - 1)
    return Sites(names, xy, species, variant.astype(np.int32), yaw, scale)


def write_sites_csv(path: str | Path, replicates: list[Sites]) -> None:
    """``replicate,x,y,species,variant,yaw,scale`` rows, written atomically."""
    from usdforest import csvtext

    with atomic_path(path) as tmp, tmp.open("wb") as f:
        f.write(b"replicate,x,y,species,variant,yaw,scale\n")
        for r, s in enumerate(replicates):
            csvtext.write_rows(
                f,
                len(s),
                lambda i, r=r, s=s: [
                    csvtext.integers(np.full(len(s.xy[i]), r)),
                    csvtext.fixed(s.xy[i, 0], 4),
                    csvtext.fixed(s.xy[i, 1], 4),
                    csvtext.labels(s.species[i], s.names),
                    csvtext.integers(s.variant[i]),
                    csvtext.fixed(s.yaw[i], 3),
                    csvtext.fixed(s.scale[i], 4),
                ],
            )


def read_sites_csv(path: str | Path, names: tuple[str, ...], replicate: int = 0) -> Sites:
    """One replicate of a sites CSV written by :func:`write_sites_csv`, read as stem maps
    are (:mod:`usdforest.sites.stemmap`: each column once, finite numbers, positions within
    1e8 m, the file and line named in one line); ``scale`` above 0, ``variant`` a whole
    number 0 or more."""
    from usdforest.errors import UsdForestError
    from usdforest.paths import shown
    from usdforest.sites.stemmap import number, position, read_table

    path = Path(path)
    name = shown(path)
    _, table = read_table(
        path,
        ("replicate", "x", "y"),
        known=("replicate", "x", "y", "species", "variant", "yaw", "scale"),
    )
    rows = []
    last = -1  # the highest replicate the file has
    for row in table:
        k = _whole(row, "replicate", name)
        last = max(last, k)
        if k != replicate:
            continue
        x, y = position(row, name)
        scale = number(row, "scale", name)
        if scale is not None and scale <= 0:
            raise UsdForestError(f"{name} line {row['line']}: scale = {scale:g} must be above 0")
        yaw = number(row, "yaw", name)
        variant = _whole(row, "variant", name) if row.get("variant") else 0
        rows.append((x, y, row.get("species") or names[0], variant, yaw or 0.0, scale or 1.0))
    if replicate > last:
        has = "no sites" if last < 0 else f"replicates 0 to {last}"
        raise UsdForestError(f"{name}: no replicate {replicate} (the file has {has})")
    all_names = tuple(dict.fromkeys([*names, *(r[2] for r in rows)]))
    xy = np.array([[r[0], r[1]] for r in rows], dtype=float).reshape(-1, 2)
    return Sites(
        all_names,
        xy,
        np.array([all_names.index(r[2]) for r in rows], dtype=np.int32),
        np.array([r[3] for r in rows], dtype=np.int32),
        np.array([r[4] for r in rows], dtype=float),
        np.array([r[5] for r in rows], dtype=float),
    )


def _whole(row: dict[str, str], key: str, name: str) -> int:
    """``row[key]`` as a whole number 0 or more, or a one-line error naming the line."""
    from usdforest.errors import UsdForestError

    text = row.get(key, "")
    if not text.isdigit() or int(text) > 2**31 - 1:
        raise UsdForestError(
            f"{name} line {row['line']}: {key} = {text!r} is not a whole number 0 or more"
        )
    return int(text)

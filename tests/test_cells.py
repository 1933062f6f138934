"""Cell-by-cell sampling of tiled recipes: sites that do not depend on how the work is cut."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import usdforest.sites.cells as cells
import usdforest.sites.local as local
from usdforest.recipe import parse_recipe
from usdforest.sites.sampling import sample_sites
from usdforest.sites.table import Sites


def _recipe(tmp_path, tiles=500.0, hard_core=0.0, side=1100.0, **extra):
    data = {
        "seed": 11,
        "region": {"bounds": [0.0, 0.0, side, 0.8 * side]},
        "intensity": {"kind": "expression", "expr": "0.002 + 0.004 * (x / 1100) ** 2"},
        "species": {"pine": {}, "broadleaf": {}},
        "forest": {"variants": 2, "hard_core": hard_core},
        **({"tiles": {"size": tiles}} if tiles else {}),
        **extra,
    }
    return parse_recipe(data, tmp_path, str(tmp_path / "r.toml"))


def _same(a, b) -> None:
    for f in ("xy", "species", "variant", "yaw", "scale"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


def _joined(parts):
    """Sites from several squares or blocks in one table, ordered by cell and rank."""
    cell = np.concatenate([p[1] for p in parts])
    rank = np.concatenate([p[2] for p in parts])
    order = np.lexsort((rank, cell))
    cols = {
        f: np.concatenate([getattr(p[0], f) for p in parts])[order]
        for f in ("xy", "species", "variant", "yaw", "scale")
    }
    return type("S", (), cols)


def _thomas(scale):  # clusters wide enough to cross the 250 m cells' edges (Thomas: 4 scale)
    return {"clusters": {"kind": "thomas", "scale": scale, "offspring": 12}}


@pytest.mark.parametrize(
    ("hard_core", "extra"),
    [
        (0.0, {}),
        (6.0, {}),
        (260.0, {}),
        (0.0, _thomas(30.0)),
        (2.0, {"clusters": {"kind": "matern", "scale": 80.0, "offspring": 12}}),
        (0.0, {"inhibition": {"kind": "strauss", "radius": 20.0, "gamma": 0.2}}),
    ],
    ids=[
        "poisson",
        "hard-core-6m",
        "hard-core-260m",
        "thomas-30m",
        "matern-80m-hard-core",
        "strauss-20m",
    ],
)
def test_sites_do_not_depend_on_tiles_or_blocks(tmp_path, hard_core, extra):
    """Every recipe is sampled cell by cell: without tiles, with tiles of 37 or 500 m (each
    square's own sites computed alone), and in blocks of one cell (a hard core wider than a
    cell reaches two rings of cells), the same sites in the same order."""
    untiled = _recipe(tmp_path, tiles=None, hard_core=hard_core, **extra)
    base = sample_sites(untiled)
    assert len(base) > (3 if hard_core > 100 else 100)
    for size in (37.0, 500.0):
        r = _recipe(tmp_path, tiles=size, hard_core=hard_core, **extra)
        _same(base, sample_sites(r))
        parts = []
        for sq in local.squares(r):
            loc = local.local_sites(r, sq)
            o = loc.own
            s = loc.sites
            own = Sites(s.names, s.xy[o], s.species[o], s.variant[o], s.yaw[o], s.scale[o])
            parts.append((own, loc.cell[o], loc.rank[o]))
        assert sum(len(p[0]) for p in parts) == len(base)
        _same(base, _joined(parts))
    nx, ny = cells.grid(untiled)
    one = [
        cells.sample_cells(untiled, 0, (i, j, i + 1, j + 1)) for j in range(ny) for i in range(nx)
    ]
    _same(base, _joined([(c.sites, c.cell, c.rank) for c in one]))
    if hard_core:  # and no two sites closer than the hard core, across every cell edge
        pairs = cKDTree(base.xy).query_pairs(hard_core * (1 - 1e-12))
        assert not pairs


def test_cell_sampling_is_the_process_it_says(tmp_path):
    """Counts over replicates against the integral of lambda (mean and variance of a Poisson
    count), and the density rising with x as lambda does."""
    r = _recipe(tmp_path, side=600.0)
    counts, xs = [], []
    for k in range(60):
        s = sample_sites(r, k)
        counts.append(len(s))
        xs.append(s.xy[:, 0])
    expected = r.expected_trees()
    counts = np.array(counts)
    assert abs(counts.mean() - expected) < 4 * np.sqrt(expected / len(counts))
    assert 0.6 < counts.var(ddof=1) / expected < 1.5
    x = np.concatenate(xs)
    # lambda = 0.002 + 0.004 (x / 1100)^2: the share of sites east of x = 300 on [0, 600]
    east = (0.002 * 300 + 0.004 * (600**3 - 300**3) / 3 / 1100**2) / (
        0.002 * 600 + 0.004 * 600**3 / 3 / 1100**2
    )
    assert abs(np.mean(x > 300) - east) < 0.02

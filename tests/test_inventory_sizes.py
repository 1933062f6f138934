"""Inventories of any size (issue 38, item 4): 2,000 rows with seedlings and saplings, every
row's height and DBH reproduced on the composed stage, at a cost set by the size classes
(not the row count)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from usdforest.errors import RecipeError
from usdforest.recipe import read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.inventory import stand_figures
from usdforest.usd.validate import validate

ROWS = 2000
SIDE = 100.0
SAPLINGS = 0.12  # share of rows under breast height: DBH 0


def naslund(d_cm: np.ndarray, a: float, b: float) -> np.ndarray:
    """Näslund's height curve (p = 2), as Luke's metsi ships it: pine a 0.894, b 0.185;
    birch and other broadleaves a 1.026, b 0.234 (the test's own copy)."""
    return 1.3 + d_cm**2 / (a + b * d_cm) ** 2


def stem_map(path: Path) -> dict[str, np.ndarray]:
    """A young mixed plot of 2,000 stems/ha: DBH Weibull, heights on the species' curve with a
    12 % lognormal scatter (slenderness kept in 25-240), 12 % saplings 0.15-1.25 m tall."""
    rng = np.random.default_rng(7)
    g = math.ceil(math.sqrt(ROWS))
    ij = np.array([(i, j) for i in range(g) for j in range(g)])[:ROWS]
    xy = (ij + 0.2 + 0.6 * rng.uniform(size=(ROWS, 2))) * (SIDE / g)  # 30 cm apart at least
    pine = rng.uniform(size=ROWS) < 0.6
    sapling = rng.uniform(size=ROWS) < SAPLINGS
    d_cm = np.clip(rng.weibull(1.6, ROWS) * 12 + 1, 1, 60)
    h = np.where(pine, naslund(d_cm, 0.894, 0.185), naslund(d_cm, 1.026, 0.234))
    h = np.maximum(h * np.exp(rng.normal(0, 0.12, ROWS)), 1.35)
    d = h / np.clip(h / (d_cm / 100), 25, 240)
    h = np.where(sapling, rng.uniform(0.15, 1.25, ROWS), h)
    d = np.where(sapling, 0.0, d)
    lines = ["x,y,species,dbh,height"]
    for k in range(ROWS):
        name = "pine" if pine[k] else "beech"
        lines.append(f"{xy[k, 0]:.3f},{xy[k, 1]:.3f},{name},{d[k]:.4f},{h[k]:.3f}")
    path.write_text("\n".join(lines) + "\n")
    rows = np.array([line.split(",") for line in lines[1:]])
    return {"xy": rows[:, :2].astype(float), "dbh": rows[:, 3].astype(float),
            "height": rows[:, 4].astype(float)}  # fmt: skip


RECIPE = """seed = 3
sites = "stems.csv"
[region]
bounds = [0, 0, 100, 100]
[species.pine]
preset = "scots-pine"
[species.beech]
preset = "european-beech"
"""


@pytest.fixture(scope="module")
def plot(tmp_path_factory):
    d = tmp_path_factory.mktemp("inventory2k")
    rows = stem_map(d / "stems.csv")
    (d / "r.toml").write_text(RECIPE)
    out = d / "f.usda"
    write_forest(read_recipe(d / "r.toml"), out, thumbnail=False)
    return rows, out


def test_every_row_is_reproduced_on_the_composed_stage(plot):
    rows, out = plot
    assert validate(out) == []
    t = stand_figures(out)["per_tree"]
    dist, j = cKDTree(t["xy"]).query(rows["xy"])
    assert dist.max() < 1e-3 and len(set(j)) == ROWS  # one composed tree per row
    height, dbh = t["height"][j], t["dbh"][j]
    assert np.all(np.abs(height / rows["height"] - 1) < 0.01)  # to its leaves' top
    stem = rows["dbh"] > 0
    err = np.abs(dbh[stem] / rows["dbh"][stem] - 1)  # girth tape on the composed trunk
    assert np.all(err < 0.05), f"{np.sum(err >= 0.05)} rows off by 5 % or more"
    assert np.median(err) < 0.02
    # seedlings and saplings: as tall as their rows, no stem at breast height
    assert (~stem).sum() > 0.08 * ROWS
    assert np.all(np.isnan(dbh[~stem]))
    assert rows["height"][~stem].min() < 0.3


def test_the_cost_is_the_size_classes_not_the_rows(plot):
    _, out = plot
    assets = list((out.parent / "f_assets" / "trees").glob("*.usdc"))
    # at most 64 classes a species (the inventory's default): 2,000 rows, far fewer assets
    assert 2 <= len(assets) <= 128
    trees = np.genfromtxt(out.parent / "f_assets" / "trees.csv", delimiter=",", names=True,
                          dtype=None, encoding="utf-8")  # fmt: skip
    assert len(trees) == ROWS
    young = trees["height"] < 1.3
    assert np.all(trees["dbh"][young] == 0)  # trees.csv says DBH 0 for a sapling


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ('{ x = 1, y = 1, species = "pine", dbh = 0.01, height = 1.0 }', "no stem at breast"),
        ('{ x = 1, y = 1, species = "pine", dbh = 0, height = 4.0 }', "0 is a sapling's"),
        ('{ x = 1, y = 1, species = "pine", dbh = 0 }', "give its height"),
        ('{ x = 1, y = 1, species = "pine", height = 0.05 }', "not a tree height"),
        ('{ x = 1, y = 1, species = "pine", dbh = -0.1, height = 3.0 }', "must be >= 0"),
    ],
)
def test_sapling_rows_that_contradict_themselves_are_named(tmp_path, row, message):
    r = tmp_path / "r.toml"
    r.write_text(
        f"seed = 1\nsites = [\n  {row},\n]\n[region]\nbounds = [0, 0, 10, 10]\n"
        '[species.pine]\npreset = "scots-pine"\n'
    )
    with pytest.raises(RecipeError, match=message) as e:
        read_recipe(r)
    assert "sites[0]" in str(e.value)

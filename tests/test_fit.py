"""Recipes fitted to stem maps: the fit recovers the parameters of simulated stands (an
inhomogeneous Poisson, a Thomas, a Strauss and a hard-core pattern), and the fitted recipe's
own simulations put the data's L(r) inside their envelope (Baddeley et al. 2015, ch. 9, 12
and 13)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from usdforest.cli import app
from usdforest.recipe import read_recipe
from usdforest.seeds import stream
from usdforest.sites import inhibition
from usdforest.sites.clusters import Clusters, simulate
from usdforest.sites.fit import fit_stand
from usdforest.sites.pattern import l_function
from usdforest.sites.pointprocess import Constant, Rectangle, matern_ii
from usdforest.sites.sampling import sample_sites

BOX = (0.0, 0.0, 300.0, 300.0)


def test_a_log_linear_intensity_is_recovered_within_its_standard_errors():
    rng = np.random.default_rng(2)
    beta = (math.log(0.02), 0.6, -0.3)
    top = 0.02 * math.exp(0.9)
    c = rng.uniform(0, 300, (rng.poisson(top * 9e4), 2))
    u, v = 2 * c[:, 0] / 300 - 1, 2 * c[:, 1] / 300 - 1
    xy = c[rng.uniform(size=len(c)) * top < np.exp(beta[0] + beta[1] * u + beta[2] * v)]
    f = fit_stand(xy, BOX)
    assert f.trend and f.interaction == "poisson" and f.clusters is None
    assert np.all(np.abs(np.subtract(f.beta, beta)) < 3 * np.asarray(f.beta_se))
    # a constant intensity is found constant
    flat = rng.uniform(0, 300, (rng.poisson(0.02 * 9e4), 2))
    g = fit_stand(flat, BOX)
    assert not g.trend and math.exp(g.beta[0]) == pytest.approx(len(flat) / 9e4)


@pytest.mark.parametrize("seed", [10, 11, 12])
def test_a_thomas_stand_is_found_clustered_and_its_clusters_measured(seed):
    """kappa 0.003 parents/m², clusters of sd 3 m and 10 trees: minimum contrast on K gets
    the scale within 20 % and kappa within 25 % (measured: 2.58-2.88 m, 0.0030-0.0034)."""
    xy = simulate(Clusters("thomas", 3.0, 10.0), 0.003, BOX, np.random.default_rng(seed))
    f = fit_stand(xy, BOX)
    assert f.interaction == "thomas" and f.clark_evans < 0.8
    assert f.clusters.scale == pytest.approx(3.0, rel=0.2)
    assert f.kappa == pytest.approx(0.003, rel=0.25)


@pytest.mark.parametrize(("gamma", "key"), [(0.2, 2), (0.5, 5)])
def test_a_strauss_stand_is_found_softly_inhibited_and_its_interaction_measured(gamma, key):
    """beta 0.1, radius 2 m on 150 m x 150 m (1,200-1,500 trees): the logistic composite
    likelihood with the radius profiled finds the radius within 0.1 m, gamma within 0.1 and
    beta within 10 % (measured: 1.99-2.00 m, gamma 0.18 and 0.49, beta 0.096 and 0.109)."""
    box = (0.0, 0.0, 150.0, 150.0)
    s = inhibition.Inhibition("strauss", 2.0, gamma)
    xy = inhibition.simulate(s, Rectangle(*box), Constant(0.1), stream(1, "f", key))
    f = fit_stand(xy, box)
    assert f.interaction == "strauss" and f.hard_core == 0 and f.clusters is None
    assert f.inhibition.radius == pytest.approx(2.0, abs=0.1)
    assert f.inhibition.gamma == pytest.approx(gamma, abs=0.1)
    assert math.exp(f.first_order[0]) == pytest.approx(0.1, rel=0.1)


def test_a_hard_core_stand_is_found_regular():
    rng = np.random.default_rng(3)
    c = rng.uniform(0, 300, (rng.poisson(0.05 * 9e4), 2))
    xy = c[matern_ii(c, 2.0, rng)]
    f = fit_stand(xy, BOX)
    # Matérn II is no Gibbs process: the model chosen carries its 2 m hard core (the
    # Strauss process with a hard core fits its pairs just beyond it, rarer than Poisson's)
    assert f.interaction in ("hard core", "strauss-hard-core")
    hard = f.hard_core if f.interaction == "hard core" else f.inhibition.hard_core
    assert hard == pytest.approx(2.0, abs=0.01)
    assert f.clark_evans > 1.1


def _write_map(path, xy, rng):
    species = rng.choice(["scots-pine", "european-beech"], len(xy), p=[0.7, 0.3])
    dbh = np.where(species == "scots-pine", rng.normal(0.25, 0.06, len(xy)), 0.3).clip(0.05)
    path.write_text(
        "x,y,species,dbh\n"
        + "".join(f"{x:.3f},{y:.3f},{s},{d:.3f}\n" for (x, y), s, d in zip(xy, species, dbh,
                                                                              strict=True))
    )  # fmt: skip
    return species


@pytest.mark.parametrize("kind", ["clustered", "inhibited", "soft"])
def test_the_fitted_recipe_makes_stands_like_the_map(tmp_path, runner, kind):
    """usdforest fit writes a recipe that build and sample take; 19 of its simulations put
    the map's L(r) inside their envelope at 90 % of the distances up to 25 m, and its
    species shares and DBH are the map's."""
    import json

    rng = np.random.default_rng(4)
    if kind == "clustered":
        xy = simulate(Clusters("thomas", 3.0, 10.0), 0.003, BOX, rng)
    elif kind == "soft":
        s = inhibition.Inhibition("strauss", 2.5, 0.3)
        xy = inhibition.simulate(s, Rectangle(*BOX), Constant(0.04), stream(4, "map"))
    else:
        c = rng.uniform(0, 300, (rng.poisson(0.05 * 9e4), 2))
        xy = c[matern_ii(c, 2.0, rng)]
    species = _write_map(tmp_path / "map.csv", xy, rng)
    out = tmp_path / "fitted.toml"
    r = runner.invoke(app, ["fit", str(tmp_path / "map.csv"), "--region", "0,0,300,300",
                            "-o", str(out), "--json"])  # fmt: skip
    assert r.exit_code == 0, r.output
    fit = json.loads(r.stdout)
    # (a Matérn II map is no Gibbs process: any model with a hard core or a soft one that
    # makes stands like it will do; its L below)
    inhibited = ("hard core", "strauss-hard-core", "diggle-gratton", "soft-core")
    want = {"clustered": ("thomas",), "inhibited": inhibited, "soft": ("strauss",)}[kind]
    assert fit["interaction"] in want
    assert fit["species"]["scots-pine"] == pytest.approx(np.mean(species == "scots-pine"))
    recipe = read_recipe(out)
    radii = np.linspace(0.5, 25, 50)
    sims = np.array([l_function(sample_sites(recipe, k).xy, BOX, radii) for k in range(19)])
    data = l_function(xy, BOX, radii)
    inside = (data >= sims.min(axis=0)) & (data <= sims.max(axis=0))
    assert inside.mean() >= 0.9, radii[~inside]
    pines = np.loadtxt(tmp_path / "map.csv", delimiter=",", skiprows=1, usecols=3)[
        species == "scots-pine"
    ]
    dbh = recipe.data["species"]["scots-pine"]["stand"]
    assert dbh["dbh_mean"] == pytest.approx(pines.mean(), abs=1e-4)
    assert dbh["dbh_cv"] == pytest.approx(pines.std(ddof=1) / pines.mean(), abs=1e-4)


@pytest.mark.parametrize(
    ("rows", "args", "message"),
    [
        ("x,y,species\n1,1,larch\n", [], "species 'larch' not among the presets"),
        ("x,y\n" + "".join(f"{k},{k}\n" for k in range(5)), [], "at least 20 trees"),
        ("a,b\n1,2\n", [], "needs the columns x, y"),
        ("x,y\n1,1\n2,2\n", ["-o", "f.usda"], "written as .toml"),
    ],
)
def test_fit_refuses_bad_maps_in_one_line(tmp_path, runner, rows, args, message):
    (tmp_path / "m.csv").write_text(rows)
    out = ["-o", str(tmp_path / "f.toml")] if not args else [args[0], str(tmp_path / args[1])]
    r = runner.invoke(app, ["fit", str(tmp_path / "m.csv"), *out])
    assert r.exit_code == 2 and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]


def _map(rows: list[str], header: str = "x,y,dbh") -> str:
    return header + "\n" + "".join(r + "\n" for r in rows)


GRID = [f"{1 + 2 * (k % 5)},{1 + 2 * (k // 5)},0.2" for k in range(25)]


@pytest.mark.parametrize(
    ("text", "args", "message"),
    [
        # the reader the recipe's stem maps go through: DBH in metres, 0 or more, finite
        (_map([*GRID[:24], "3,3,25"]), [], "line 26: dbh = 25 looks like centimetres"),
        (_map([*GRID[:24], "3,3,-0.2"]), [], "line 26: dbh = -0.2 is below 0"),
        (_map([*GRID[:24], "3,3,nan"]), [], "line 26: dbh = nan is not a finite number"),
        (_map([*GRID[:24], "1e300,3,0.2"]), [], "line 26: x = 1e+300 is beyond 1e+08 m"),
        (_map(GRID, "x,y,x"), [], "the header names x more than once"),
        (_map(GRID), ["--region", "0,0,1e12,1e12"], "reaches beyond 1e+08 m"),
        # maps too small or degenerate to fit, named with the file and why
        (_map([]), [], "0 tree(s) at 0 distinct position(s); a fit needs at least 20 trees"),
        (_map(["3,3,0.2"] * 25), [], "25 tree(s) at 1 distinct position(s)"),
        (_map([f"{k},5,0.2" for k in range(25)]), [], "the trees lie on one line (y = 5 for"),
    ],
)
def test_fit_reads_maps_as_the_stem_map_reader_does(tmp_path, runner, text, args, message):
    """What a recipe's stem map refuses, fit refuses: one line naming the file (and the line
    or the reason), nothing written (before: a recipe of dbh_mean 64.2 that build then
    refused, bad rows dropped, exit 3 on overflow, "window: bounds [5.0, 5.0, 5.0, 5.0] are
    empty")."""
    (tmp_path / "m.csv").write_text(text)
    r = runner.invoke(app, ["fit", str(tmp_path / "m.csv"), "-o", str(tmp_path / "f.toml"),
                            *args])  # fmt: skip
    lines = r.stderr.strip().splitlines()
    assert r.exit_code == 2 and len(lines) == 1 and message in lines[0], r.output
    assert "m.csv" in lines[0] or "--region" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]
    if "--region" not in args and "one line" in message:  # the plot's window fits it
        r = runner.invoke(app, ["fit", str(tmp_path / "m.csv"), "-o", str(tmp_path / "f.toml"),
                                "--region", "-1,0,25,10"])  # fmt: skip
        assert r.exit_code == 0, r.output


def test_a_large_maps_pairs_stay_within_the_budget():
    """K and g hold the pairs within rmax: a quarter of the window's side, or less where a
    map is dense (100,000 trees on 1 km² held 1e9 pairs within 250 m: 24 GB, and the fit
    never ended); counted here on a random map against the budget."""
    from scipy.spatial import cKDTree

    from usdforest.sites.pattern import PAIR_BUDGET, pair_rmax

    assert pair_rmax(500, 100.0, 100.0, 25.0) == 25.0  # a plot's map: as before
    r = pair_rmax(100_000, 1000.0, 1000.0, 250.0)
    assert 20.0 < r < 30.0
    n, side, budget = 20_000, 200.0, 200_000
    pts = np.random.default_rng(3).uniform(0, side, (n, 2))
    r = pair_rmax(n, side, side, side / 4, budget)
    pairs = (cKDTree(pts).count_neighbors(cKDTree(pts), r) - n) / 2
    assert 0.8 * budget < pairs < 1.05 * budget  # the edge loses a few
    assert PAIR_BUDGET == 10_000_000


def test_a_recipes_stem_map_refuses_a_column_named_twice(tmp_path):
    """The recipe's stem maps go through the same reader: a second ``x`` column was read in
    place of the first, without a word."""
    from usdforest.errors import RecipeError
    from usdforest.recipe import read_recipe

    (tmp_path / "s.csv").write_text("x,y,species,dbh,height,x\n3,4,pine,0.2,18,30\n")
    (tmp_path / "r.toml").write_text(
        'seed = 1\nsites = "s.csv"\n[region]\nbounds = [0, 0, 40, 40]\n'
        '[species.pine]\npreset = "scots-pine"\n'
    )
    with pytest.raises(RecipeError, match=r"r\.toml: sites: s\.csv: the header names x more"):
        read_recipe(tmp_path / "r.toml")

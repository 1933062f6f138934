"""Pattern statistics and clustered stands against their theory: K, L, g and Clark-Evans of
Poisson, Thomas and Matérn cluster patterns (Illian et al. 2008; Baddeley et al. 2015), and
recipes with [clusters] that place the trees the process says."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from usdforest.errors import RecipeError, UsdForestError
from usdforest.recipe import parse_recipe
from usdforest.sites.clusters import Clusters, simulate
from usdforest.sites.pattern import (
    clark_evans,
    csr_envelope,
    k_function,
    l_function,
    pair_correlation,
)
from usdforest.sites.sampling import sample_sites

BOX = (0.0, 0.0, 200.0, 200.0)
R = np.array([2.0, 5.0, 10.0, 20.0])
REPS = 40


def _poisson(rng, lam: float = 0.05) -> np.ndarray:
    return rng.uniform(0, 200, size=(rng.poisson(lam * 200 * 200), 2))


def _mean_within(values: np.ndarray, theory: np.ndarray, sds: float = 4.0) -> None:
    """The mean of ``REPS`` estimates is within ``sds`` standard errors of the theory."""
    ratio = np.asarray(values) / theory
    err = ratio.std(axis=0, ddof=1) / math.sqrt(len(ratio))
    assert np.all(np.abs(ratio.mean(axis=0) - 1) < sds * err + 1e-3), (ratio.mean(axis=0), err)


def test_poisson_patterns_have_k_pi_r_squared_g_one_and_r_one():
    rng = np.random.default_rng(3)
    pats = [_poisson(rng) for _ in range(REPS)]
    _mean_within([k_function(p, BOX, R) for p in pats], math.pi * R**2)
    _mean_within([pair_correlation(p, BOX, R) for p in pats], np.ones_like(R))
    _mean_within([[clark_evans(p, BOX)] for p in pats], np.ones(1))
    np.testing.assert_allclose(
        l_function(pats[0], BOX, R), np.sqrt(k_function(pats[0], BOX, R) / math.pi)
    )


@pytest.mark.parametrize(("kind", "scale"), [("thomas", 3.0), ("matern", 6.0)])
def test_cluster_patterns_have_their_closed_form_k(kind, scale):
    """Thomas: K = pi r² + (1 - exp(-r²/4σ²))/κ; Matérn cluster: pi r² + h(r/2R)/κ; both far
    above Poisson's at small r, and Clark-Evans R well below 1."""
    c, kappa = Clusters(kind, scale, 10.0), 0.004
    rng = np.random.default_rng(5)
    pats = [simulate(c, kappa, BOX, rng) for _ in range(REPS)]
    assert abs(np.mean([len(p) for p in pats]) - kappa * 10 * 200 * 200) < 0.05 * 1600
    _mean_within([k_function(p, BOX, R) for p in pats], c.k_function(R, kappa))
    assert np.all(c.k_function(R[:2], kappa) > 1.2 * math.pi * R[:2] ** 2)  # 2 and 5 m
    assert np.mean([clark_evans(p, BOX) for p in pats]) < 0.75


def test_the_matern_cluster_k_has_its_limits():
    """h(0) = 0 and h(z >= 1) = 1: no extra pairs at r = 0, all of a cluster's beyond 2R."""
    c, kappa = Clusters("matern", 5.0, 4.0), 0.01
    np.testing.assert_allclose(c.k_function(np.array([0.0]), kappa), [0.0], atol=1e-12)
    far = np.array([10.0, 30.0])
    np.testing.assert_allclose(c.k_function(far, kappa), math.pi * far**2 + 1 / kappa)


def test_a_clustered_pattern_leaves_the_csr_envelope_and_a_poisson_one_does_not():
    rng = np.random.default_rng(7)
    r = np.array([1.0, 2.0, 4.0, 8.0])
    clustered = simulate(Clusters("thomas", 2.0, 8.0), 0.003, BOX, rng)
    env = csr_envelope(clustered, BOX, r, nsim=39, seed=1)
    assert env.outside.all() and np.all(env.observed > env.hi)
    np.testing.assert_allclose(env.theory, r)
    poisson = csr_envelope(_poisson(rng, 0.02), BOX, r, nsim=39, seed=1)
    assert poisson.outside.sum() <= 1


def test_pattern_statistics_refuse_what_they_cannot_measure():
    with pytest.raises(UsdForestError, match="at least 2 points"):
        k_function(np.zeros((1, 2)), BOX, R)
    with pytest.raises(UsdForestError, match="outside the window"):
        k_function(np.array([[1.0, 1.0], [300.0, 5.0]]), BOX, R)
    with pytest.raises(UsdForestError, match="half the window's shorter side"):
        k_function(np.array([[1.0, 1.0], [3.0, 5.0]]), BOX, np.array([150.0]))


def _recipe(tmp_path, clusters, **extra):
    data = {
        "seed": 2,
        "region": {"bounds": [0.0, 0.0, 300.0, 300.0]},
        "intensity": {"kind": "expression", "expr": "0.01 + 0.03 * x / 300"},
        "species": {"scots-pine": {}},
        **({"clusters": clusters} if clusters else {}),
        **extra,
    }
    return parse_recipe(data, tmp_path, str(tmp_path / "r.toml"))


def test_a_clustered_recipe_keeps_its_intensity_and_clusters_its_trees(tmp_path):
    """[clusters] over an inhomogeneous intensity: the same trees per strip as the intensity
    says (mean of 30 replicates within 4 standard errors), clustered (Clark-Evans R about
    0.6 where the Poisson recipe gives 1)."""
    clustered = _recipe(tmp_path, {"kind": "thomas", "scale": 2.5, "offspring": 10})
    poisson = _recipe(tmp_path, None)
    strips = np.linspace(0, 300, 4)
    lam = [(0.01 * 100 + 0.03 * (b**2 - a**2) / 600) * 300 for a, b in itertools.pairwise(strips)]
    counts, ce = [], []
    for rep in range(30):
        xy = sample_sites(clustered, rep).xy
        counts.append(np.histogram(xy[:, 0], strips)[0])
        ce.append(clark_evans(xy, (0, 0, 300, 300)))
    _mean_within(counts, np.array(lam))
    assert np.mean(ce) < 0.75
    assert abs(clark_evans(sample_sites(poisson).xy, (0, 0, 300, 300)) - 1) < 0.05


@pytest.mark.parametrize(
    ("clusters", "message"),
    [
        ({"kind": "neyman", "scale": 2, "offspring": 3}, "clusters.kind: 'neyman' is not one of"),
        ({"kind": "thomas", "scale": 0, "offspring": 3}, "clusters.scale: must be > 0"),
        ({"kind": "thomas", "scale": 500, "offspring": 3}, r"clusters.scale: expected metres in"),
        ({"kind": "thomas", "scale": 2}, "clusters.offspring: missing"),
        ({"kind": "thomas", "scale": 2, "offspring": 3, "size": 1}, "clusters: unknown key"),
        ("thomas", "clusters: expected a table"),
    ],
)
def test_bad_clusters_are_refused_by_key(tmp_path, clusters, message):
    with pytest.raises(RecipeError, match=message):
        _recipe(tmp_path, clusters)


def test_usdforest_pattern_on_a_forest_and_on_a_csv(tmp_path, runner):
    """The command reads a built forest (its trees.csv and region) or any CSV of x,y, prints
    the figures and the envelope test, writes the plot, and refuses bad input in one line."""
    import json

    from usdforest.cli import app
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.usd.forest import write_forest

    recipe = read_recipe(default_recipe_path().parent / "paper-ipp-dense.toml")
    write_forest(recipe, tmp_path / "f.usda", thumbnail=False)
    r = runner.invoke(app, ["pattern", str(tmp_path / "f.usda"), "--json", "--nsim", "9", "-q"])
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    xy = sample_sites(recipe).xy
    assert data["trees"] == len(xy) and data["window"] == list(recipe.region.bounds)
    # trees.csv holds positions to the millimetre
    assert data["clark_evans"] == pytest.approx(clark_evans(xy, recipe.region.bounds), rel=1e-4)
    assert len(data["r"]) == len(data["g"]) == len(data["l_minus_r_hi"]) == 50
    (tmp_path / "stems.csv").write_text(
        "x,y,dbh\n" + "".join(f"{x:.3f},{y:.3f},0.2\n" for x, y in xy)
    )
    png = tmp_path / "p.png"
    r = runner.invoke(app, ["pattern", str(tmp_path / "stems.csv"), "--region",
                            ",".join(map(str, recipe.region.bounds)), "--nsim", "9", "-o",
                            str(png)])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "clark_evans" in r.stdout and png.stat().st_size > 10_000
    for args, message in (
        ([str(tmp_path / "f_assets" / "pipeline.toml")], "needs the columns x, y"),
        ([str(tmp_path / "stems.csv"), "--region", "0,0,5"], "--region: expected x0,y0,x1,y1"),
        ([str(tmp_path / "stems.csv"), "-o", str(png)], "exists; pass --force"),
    ):
        r = runner.invoke(app, ["pattern", *args])
        assert r.exit_code == 2 and message in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1

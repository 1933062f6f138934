"""Soft inhibition: the Strauss process against its theory. In a window where every pair
interacts the count has a closed-form law; gamma = 1 is the Poisson process; otherwise the
intensity is near the Poisson-saddlepoint approximation (Baddeley and Nair 2012) and g(r)
stays below 1 inside the radius, rising to 1 beyond it. Recipes with [inhibition] keep their
trend and are checked by key."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import lambertw

from usdforest.errors import RecipeError
from usdforest.recipe import parse_recipe
from usdforest.seeds import stream
from usdforest.sites.inhibition import Inhibition, simulate
from usdforest.sites.pattern import k_function, pair_correlation
from usdforest.sites.pointprocess import Constant, Rectangle
from usdforest.sites.sampling import sample_sites

BOX = (0.0, 0.0, 120.0, 120.0)


def test_where_every_pair_interacts_the_count_has_the_strauss_law():
    """In a 1 m square with radius 2 m every pair interacts, so the density of n trees is
    beta^n / n! x gamma^(n (n - 1) / 2) (times the window's area^n): 1,000 chains' final
    counts against those probabilities, each within 4 standard errors."""
    beta, gamma = 3.0, 0.4
    s = Inhibition("strauss", 2.0, gamma)
    counts = np.array(
        [len(simulate(s, Rectangle(0, 0, 1, 1), Constant(beta), stream(7, "law", k)))
         for k in range(1000)]
    )  # fmt: skip
    n = np.arange(12)
    w = beta**n / np.array([math.factorial(k) for k in n]) * gamma ** (n * (n - 1) / 2)
    p = w / w.sum()
    seen = np.bincount(counts, minlength=12)[:12] / len(counts)
    se = np.sqrt(p * (1 - p) / len(counts))
    assert np.all(np.abs(seen - p) <= 4 * se + 1e-3), (seen, p)


def test_gamma_one_is_the_poisson_process():
    """No interaction: the count of beta x area on average and K(r) = pi r² (means of 10
    patterns within 4 standard errors)."""
    s, r = Inhibition("strauss", 3.0, 1.0), np.array([2.0, 4.0, 8.0])
    pats = [simulate(s, Rectangle(*BOX), Constant(0.04), stream(3, "p", k)) for k in range(10)]
    counts = np.array([len(p) for p in pats])
    mean = 0.04 * 120 * 120
    assert abs(counts.mean() - mean) < 4 * math.sqrt(mean / len(counts))
    ratio = np.array([k_function(p, BOX, r) for p in pats]) / (math.pi * r**2)
    err = ratio.std(axis=0, ddof=1) / math.sqrt(len(ratio))
    assert np.all(np.abs(ratio.mean(axis=0) - 1) < 4 * err + 1e-3)


@pytest.mark.parametrize("gamma", [0.1, 0.5])
def test_strauss_patterns_are_thinner_than_beta_and_repel_inside_the_radius(gamma):
    """Radius 2 m, beta 0.12: the intensity at most 9 % below W(beta G) / G and never above it
    by more than 2 % (G = (1 - gamma) pi r²; the saddlepoint approximation overestimates a
    strongly inhibited process's intensity, by 7 % here at gamma 0.1 with chains of 50 or
    200 steps a tree alike), written here with scipy's Lambert W; g(r) well below 1 inside
    the radius (near gamma at 1 m) and within 15 % of 1 from 3 to 8 m."""
    radius, beta = 2.0, 0.12
    s = Inhibition("strauss", radius, gamma)
    pats = [simulate(s, Rectangle(*BOX), Constant(beta), stream(5, "s", k)) for k in range(6)]
    lam = np.mean([len(p) for p in pats]) / (120 * 120)
    g_ = (1 - gamma) * math.pi * radius**2
    ps = float(lambertw(beta * g_).real) / g_
    assert -0.09 < lam / ps - 1 < 0.02, (lam, ps)
    assert s.intensity(beta) == pytest.approx(ps)
    g = np.mean([pair_correlation(p, BOX, np.array([1.0, 1.5, 3.0, 5.0, 8.0])) for p in pats], 0)
    assert g[0] < gamma + 0.15 and g[1] < 0.5 * (1 + gamma)
    assert np.all(np.abs(g[2:] - 1) < 0.15), g


def test_a_hard_core_strauss_keeps_every_pair_apart():
    """gamma = 0: no two trees within the radius, at the Poisson start's density or not."""
    from scipy.spatial import cKDTree

    s = Inhibition("strauss", 2.5, 0.0)
    p = simulate(s, Rectangle(*BOX), Constant(0.2), stream(9, "h"))
    assert len(p) > 600 and not cKDTree(p).query_pairs(2.5)


def _recipe(tmp_path, inhibition, **extra):
    data = {
        "seed": 4,
        "region": {"bounds": [0.0, 0.0, 240.0, 120.0]},
        "intensity": {"kind": "expression", "expr": "0.02 + 0.1 * x / 240"},
        "species": {"scots-pine": {}, "silver-birch": {}},
        **({"inhibition": inhibition} if inhibition else {}),
        **extra,
    }
    return parse_recipe(data, tmp_path, str(tmp_path / "r.toml"))


def test_an_inhibited_recipe_keeps_its_trend_and_repels_its_trees(tmp_path):
    """[inhibition] over an intensity rising eastwards: more trees in the east strip than the
    west, each strip's count near the local saddlepoint approximation W(beta(x) G) / G
    integrated over it (within 8 %), and far fewer pairs within the radius than the Poisson
    recipe gives at the same count."""
    from scipy.spatial import cKDTree

    s = Inhibition("strauss", 2.0, 0.2)
    rec = _recipe(tmp_path, s.describe())
    xs = np.linspace(0, 240, 2401)
    x_mid = 0.5 * (xs[1:] + xs[:-1])
    local = np.array([s.intensity(0.02 + 0.1 * x / 240) for x in x_mid]) * 0.1 * 120
    want = [local[x_mid < 120].sum(), local[x_mid >= 120].sum()]
    sites = [sample_sites(rec, k) for k in range(3)]
    west = np.mean([np.sum(t.xy[:, 0] < 120) for t in sites])
    east = np.mean([np.sum(t.xy[:, 0] >= 120) for t in sites])
    assert abs(west / want[0] - 1) < 0.08 and abs(east / want[1] - 1) < 0.08, (west, east, want)
    close = len(cKDTree(sites[0].xy).query_pairs(2.0))
    n = len(sites[0])
    # Poisson with the same count and trend: pairs within r are about n² pi r² E[lambda]/ |W|
    lam = 0.02 + 0.1 * sites[0].xy[:, 0] / 240
    poisson_pairs = 0.5 * n * np.mean(lam / lam.mean()) * n / (240 * 120) * math.pi * 4
    assert close < 0.35 * poisson_pairs
    assert set(np.unique(sites[0].species)) == {0, 1}


@pytest.mark.parametrize(
    ("inhibition", "extra", "message"),
    [
        ({"kind": "strauss", "radius": 2, "gamma": 1.5}, {}, r"inhibition.gamma: expected"),
        ({"kind": "strauss", "radius": 0, "gamma": 0.5}, {}, "inhibition.radius: must be > 0"),
        ({"kind": "strauss", "radius": 80, "gamma": 0.5}, {}, "inhibition.radius: expected"),
        ({"kind": "geyer", "radius": 2, "gamma": 0.5}, {}, "inhibition.kind: 'geyer' is not"),
        ({"kind": "strauss", "radius": 2}, {}, "inhibition.gamma: missing"),
        ({"radius": 2, "gamma": 0.5, "r": 1}, {}, "inhibition: unknown key"),
        ("strauss", {}, "inhibition: expected a table"),
        (
            {"radius": 2, "gamma": 0.5},
            {"clusters": {"kind": "thomas", "scale": 2, "offspring": 3}},
            "inhibition: a stand is clustered or inhibited",
        ),
        ({"radius": 2, "gamma": 0.5}, {"forest": {"hard_core": 1.5}}, "not with forest.hard_core"),
    ],
)
def test_bad_inhibition_is_refused_by_key(tmp_path, inhibition, extra, message):
    with pytest.raises(RecipeError, match=message):
        _recipe(tmp_path, inhibition, **extra)

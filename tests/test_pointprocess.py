"""The inhomogeneous Poisson process: counts against the integral, quadrat tests, regions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from usdforest.errors import RecipeError, UsdForestError
from usdforest.expr import compile_expression
from usdforest.sites.pointprocess import (
    Bump,
    Constant,
    ExpressionIntensity,
    GaussianMixture,
    Polygon,
    Raster,
    Rectangle,
    draw_marks,
    matern_ii,
    thin,
)

SQUARE = Rectangle(0, 0, 100, 100)
MIXTURE = GaussianMixture(0.002, (Bump(30, 70, 12, 0.03), Bump(70, 30, 20, 0.015)))
# a concave L-shaped polygon
ELL = Polygon(((0, 0), (60, 0), (60, 25), (25, 25), (25, 60), (0, 60)))


def counts(region, intensity, reps, seed=0):
    rng = np.random.default_rng(seed)
    return np.array([len(thin(region, intensity, rng)) for _ in range(reps)])


@pytest.mark.parametrize(
    ("region", "intensity"),
    [
        (Rectangle(0, 0, 20, 20), Constant(0.05)),
        (SQUARE, MIXTURE),
        (ELL, ExpressionIntensity("0.02 * (1 + sin(x / 10)) * exp(-y / 80)")),
    ],
    ids=["constant", "gaussian-mixture", "expression-on-polygon"],
)
def test_count_mean_and_variance_match_the_integral(region, intensity):
    mu = intensity.integral(region)
    reps = 1500
    n = counts(region, intensity, reps)
    se = math.sqrt(mu / reps)
    assert abs(n.mean() - mu) < 4 * se, (n.mean(), mu)
    # Poisson: variance equals the mean (sd of the sample variance ~ mu * sqrt(2 / reps))
    assert abs(n.var(ddof=1) / mu - 1) < 4 * math.sqrt(2 / reps) + 2 / mu


def test_gaussian_mixture_integral_is_analytic_and_agrees_with_quadrature():
    from usdforest.sites.pointprocess import _grid_integral

    assert MIXTURE.integral(SQUARE) == pytest.approx(_grid_integral(MIXTURE, SQUARE), rel=1e-4)
    # a bump well inside the square: base * area + 2 pi sigma^2 peak
    inside = GaussianMixture(0.002, (Bump(50, 50, 8, 0.03),))
    assert inside.integral(SQUARE) == pytest.approx(20 + 2 * math.pi * 64 * 0.03, rel=1e-9)


def quadrat_chi2(sites: np.ndarray, expected_density, reps: int, k: int = 8) -> float:
    """p-value of a chi-square test of quadrat counts against the expected intensity."""
    edges = np.linspace(0, 100, k + 1)
    obs, _, _ = np.histogram2d(sites[:, 0], sites[:, 1], bins=[edges, edges])
    exp = np.zeros((k, k))
    for i in range(k):
        for j in range(k):
            cell = Rectangle(edges[i], edges[j], edges[i + 1], edges[j + 1])
            exp[i, j] = expected_density.integral(cell) * reps
    chi2 = float(((obs - exp) ** 2 / exp).sum())
    return float(stats.chi2.sf(chi2, k * k - 1))


def test_quadrat_chi_square_against_lambda_and_a_negative_control():
    rng = np.random.default_rng(7)
    reps = 60
    sites = np.concatenate([thin(SQUARE, MIXTURE, rng) for _ in range(reps)])
    assert quadrat_chi2(sites, MIXTURE, reps) > 0.001
    # negative control: the same sites tested against a uniform intensity with the same total
    wrong = Constant(MIXTURE.integral(SQUARE) / SQUARE.area)
    assert quadrat_chi2(sites, wrong, reps) < 1e-9


def test_sites_lie_inside_the_region_polygons_included():
    rng = np.random.default_rng(1)
    s = thin(ELL, Constant(0.3), rng)
    assert len(s) > 500
    assert np.all(ELL.contains(s[:, 0], s[:, 1]))
    assert not np.any((s[:, 0] > 25) & (s[:, 1] > 25))  # the notch of the L stays empty
    r = Rectangle(-5, 10, 5, 12)
    s = thin(r, Constant(2.0), rng)
    assert np.all((s[:, 0] >= -5) & (s[:, 0] <= 5) & (s[:, 1] >= 10) & (s[:, 1] <= 12))


@pytest.mark.parametrize("bound", [0.01, 1e-9])
def test_bound_too_low_is_an_error_not_a_bias(bound):
    """Refused up front, also when the bound is so low that no candidate would ever be drawn
    to be checked against it (0 sites where 25 are expected, before)."""
    low = ExpressionIntensity("0.05 * x / 100", declared_bound=bound)
    with pytest.raises(UsdForestError, match=r"intensity.bound: .* is below the intensity's max"):
        thin(SQUARE, low, np.random.default_rng(0))


def test_expression_bound_is_computed_from_the_region():
    e = ExpressionIntensity("0.01 + 0.04 * exp(-((x-50)^2+(y-50)^2)/50)")
    assert 0.05 <= e.bound(SQUARE) <= 0.06


def test_candidate_limit_is_refused_before_drawing():
    with pytest.raises(UsdForestError, match="candidates"):
        thin(Rectangle(0, 0, 1e4, 1e4), Constant(10.0), np.random.default_rng(0))


def test_raster_intensity():
    grid = np.array([[0.0, 0.1], [0.02, 0.0]])  # row 0 = north
    r = Raster(grid, (0, 0, 100, 100))
    assert r.integral(SQUARE) == pytest.approx(0.12 / 4 * 1e4)
    assert r.evaluate(np.array([75.0, 25.0]), np.array([75.0, 25.0])).tolist() == [0.1, 0.02]
    s = thin(SQUARE, r, np.random.default_rng(0))
    ne = np.mean((s[:, 0] > 50) & (s[:, 1] > 50))
    assert ne == pytest.approx(0.1 / 0.12, abs=0.03)
    assert not np.any((s[:, 0] < 50) & (s[:, 1] > 50))


def test_matern_ii_keeps_a_minimum_spacing():
    rng = np.random.default_rng(3)
    s = thin(SQUARE, Constant(0.1), rng)
    keep = matern_ii(s, 2.5, rng)
    from scipy.spatial import cKDTree

    kept = s[keep]
    d, _ = cKDTree(kept).query(kept, k=2)
    assert d[:, 1].min() >= 2.5
    # retention (1 - exp(-lambda pi r^2)) / (lambda pi r^2) for Matern II
    a = 0.1 * math.pi * 2.5**2
    assert keep.mean() == pytest.approx((1 - math.exp(-a)) / a, abs=0.05)


def test_marks_follow_a_spatially_varying_mix():
    rng = np.random.default_rng(5)
    sites = rng.uniform(0, 100, (20000, 2))
    w_pine = compile_expression("y / 100", ("x", "y"))
    m = draw_marks(sites, [w_pine, 0.5], [3, 2], ("uniform", 0.8, 1.2), rng)
    north = sites[:, 1] > 80
    south = sites[:, 1] < 20
    assert (m.species[north] == 0).mean() == pytest.approx(0.9 / 1.4, abs=0.03)
    assert (m.species[south] == 0).mean() == pytest.approx(0.1 / 0.6, abs=0.03)
    assert m.variant[m.species == 1].max() == 1 and m.variant[m.species == 0].max() == 2
    assert 0 <= m.yaw.min() and m.yaw.max() < 360
    assert 0.8 <= m.scale.min() and m.scale.max() <= 1.2


@pytest.mark.parametrize(
    ("make", "fragment"),
    [
        (lambda: Rectangle(0, 0, 0, 10), "are empty"),
        (lambda: Rectangle(0, 0, math.inf, 10), "must be finite"),
        (lambda: Polygon(((0, 0), (1, 1))), "at least 3"),
        (lambda: Polygon(((0, 0), (1, 1), (2, 2))), "zero area"),
        (lambda: Polygon(((0, 0), (10, 10), (10, 0), (0, 10))), "intersects itself"),
        (lambda: Constant(-0.1), "must be a finite number >= 0"),
        (lambda: Constant(math.nan), "must be a finite number >= 0"),
        (lambda: GaussianMixture(0.01, (Bump(0, 0, 0, 1),)), "sigma: must be > 0"),
        (lambda: ExpressionIntensity("0.01 - x / 1000").bound(SQUARE), "is negative somewhere"),
        (lambda: ExpressionIntensity("log(x - 50)").integral(SQUARE), "not finite"),
        (lambda: ExpressionIntensity("x + z"), "unknown name 'z'"),
        (lambda: Raster(np.array([[1.0, -1.0]]), (0, 0, 1, 1)), "is negative"),
    ],
)
def test_bad_regions_and_intensities(make, fragment):
    with pytest.raises(RecipeError, match=None) as exc:
        make()
    assert fragment in str(exc.value)

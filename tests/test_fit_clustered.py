"""The trend of a clustered stand (issue 38): Poisson's likelihood-ratio test finds trends a
Thomas process does not have; the Waagepetersen (2007) sandwich variance that ``fit`` uses once
it has found the clusters is the spread of the fitted coefficients over simulations, and its
Wald test keeps the false trends near 5 %."""

from __future__ import annotations

import math

import numpy as np

from usdforest.sites.clusters import Clusters, simulate
from usdforest.sites.fit import CHI2_2DF_95, FittedStand, _wald, fit_intensity, thomas_covariance

BOX = (0.0, 0.0, 300.0, 300.0)
KAPPA, SIGMA, MU = 0.002, 4.0, 12.0  # parents/m², m, trees a parent


def fitted(xy: np.ndarray, trend: bool) -> FittedStand:
    beta, se, _ = fit_intensity(xy, BOX, trend=trend)
    return FittedStand(BOX, len(xy), beta, se, trend, None, None, 0.0, 0.0, "poisson")


def test_the_sandwich_is_the_coefficients_spread_and_keeps_false_trends_rare():
    rng = np.random.default_rng(11)
    naive = adjusted = 0
    slopes, predicted = [], []
    runs = 40
    for _ in range(runs):
        xy = simulate(Clusters("thomas", SIGMA, MU), KAPPA, BOX, rng)
        _, _, l1 = fit_intensity(xy, BOX, trend=True)
        _, _, l0 = fit_intensity(xy, BOX, trend=False)
        naive += 2 * (l1 - l0) > CHI2_2DF_95
        f = fitted(xy, True)
        cov = thomas_covariance(f, KAPPA, SIGMA)
        adjusted += _wald(f, cov) > CHI2_2DF_95
        slopes.append(f.beta[1])
        predicted.append(math.sqrt(cov[1, 1]))
    # the spread of b1 over the simulations against the sandwich's (and Poisson's, far less)
    spread = float(np.std(slopes))
    assert 0.75 < spread / float(np.mean(predicted)) < 1.33
    assert naive / runs > 0.3  # Poisson's test: a trend in a third or more of trendless stands
    assert adjusted / runs <= 0.15


def test_a_real_trend_survives_the_clustered_test():
    rng = np.random.default_rng(12)
    kept = 0
    for _ in range(10):
        xy = simulate(Clusters("thomas", SIGMA, MU), KAPPA, BOX, rng)
        # thinned by exp(1.5 (u - 1)): three quarters of the trees on the east half
        u = 2 * xy[:, 0] / 300 - 1
        xy = xy[rng.uniform(size=len(xy)) < np.exp(1.5 * (u - 1))]
        f = fitted(xy, True)
        kept += _wald(f, thomas_covariance(f, KAPPA, SIGMA)) > CHI2_2DF_95
    assert kept >= 9

"""Pairwise-interaction processes fitted to a stem map by logistic composite likelihood, and
the choice among them.

Every model's conditional intensity is ``lambda(u) = exp(theta z(u) + c s(u))`` where it is
not forbidden (a hard core), with ``z`` the first-order terms (1, the scaled coordinates,
covariates) and ``s(u)`` the model's interaction statistic of the data points near ``u`` (a
data point's own pair aside) for a given value of its irregular parameters:

=====================  ===========================================  ==========  ==============
model                  s(u)                                         c           profiled over
=====================  ===========================================  ==========  ==============
hard core              (none; forbidden within h)                   -           h = n/(n+1) x
                                                                                the shortest
                                                                                pair
Strauss                trees within r                               log gamma   r
Strauss, hard core     trees within [h, r); forbidden within h      log gamma   r (h as above)
Diggle-Gratton         sum log((d - delta) / (rho - delta)) within  kappa >= 0  rho, delta
                       rho; forbidden within delta
soft core              -sum (d / d0)**(-2 / kappa)                  (sigma /    kappa
                                                                    d0)**(2 /
                                                                    kappa)
=====================  ===========================================  ==========  ==============

(``d0`` the mean nearest-neighbour distance, which keeps the soft core's statistic of a
reasonable size.) The estimator is Baddeley, Coeurjolly, Rubak and Waagepetersen's (2014,
Biometrika 101:377; spatstat's ``ppm(..., method = "logi")``): dummy points of intensity
``rho`` (``DUMMIES_PER_TREE`` a tree, one uniform point in each cell of a grid), maximising
``sum_data log(lambda / (lambda + rho)) + sum_dummies log(rho / (lambda + rho))``; a dummy
point where the model forbids a tree adds 0. Only points ``border`` or more inside the window
count, the same for every model, so their likelihoods compare.

Diggle-Gratton's ``delta`` is profiled over 0, 1/4, 1/2, 3/4 and 1 of ``h``. Every model
is fitted with the data's hard core ``h`` (see :data:`MATERIAL`) and written with it where it
is material (the Strauss process then as the Strauss process with a hard core).

**The choice** (:func:`choose`): the smallest composite-likelihood AIC, ``2 (-log CL) + 2 k``
with ``k`` the regular and irregular parameters (Baddeley, Rubak and Turner 2015, *Spatial
Point Patterns*, section 13.5.9: AIC on the composite likelihood as spatstat computes it for
``ppm``), a stated criterion: it prefers the model whose interaction shape the data carry
(a Diggle-Gratton pair correlation rising from 0 over a Strauss step) and penalises the
extra parameters of a hard core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.sites.covariates import Covariate
from usdforest.sites.inhibition import MAX_RADIUS, Inhibition

DUMMIES_PER_TREE = 4
SOFT_KAPPAS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
MODELS = ("hard core", "strauss", "strauss-hard-core", "diggle-gratton", "soft-core")


def _scaled(window, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The coordinates scaled to [-1, 1] over the window (the log-linear terms' u, v)."""
    x0, y0, x1, y1 = window
    return (2 * (np.asarray(x) - x0) / (x1 - x0) - 1, 2 * (np.asarray(y) - y0) / (y1 - y0) - 1)


@dataclass(frozen=True)
class Fitted:
    """One model fitted: its ``kind`` (:data:`MODELS`), the interaction (``None`` for the
    hard core, which is ``hard_core`` alone), the log-beta coefficients ``theta`` (b0, b1,
    b2, then one a covariate), minus its log composite likelihood and its AIC."""

    kind: str
    inhibition: Inhibition | None
    hard_core: float
    theta: tuple[float, ...]
    neg_log_cl: float
    aic: float


@dataclass(frozen=True, eq=False)
class _Quadrature:
    xy: np.ndarray  # data first, then dummies, those within the border kept
    data: np.ndarray  # bool
    z: np.ndarray  # first-order design
    log_rho: float
    pairs: tuple[np.ndarray, np.ndarray, np.ndarray]  # quadrature row, data column, distance


def _quadrature(pts, window, trend, covariates, border, reach) -> _Quadrature:
    from scipy.spatial import cKDTree

    x0, y0, x1, y1 = window
    n = len(pts)
    area = (x1 - x0) * (y1 - y0)
    side = math.sqrt(area / max(DUMMIES_PER_TREE * n, 1))
    gx = np.arange(x0, x1, side)
    gy = np.arange(y0, y1, side)
    corner = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
    rng = np.random.default_rng(0)  # fixed: the same fit for the same map
    dummy = corner + rng.uniform(0, side, corner.shape)
    dummy = dummy[(dummy[:, 0] < x1) & (dummy[:, 1] < y1)]
    rho = len(dummy) / area
    quad = np.concatenate([pts, dummy])
    data = np.arange(len(quad)) < n
    rb = float(border)
    keep = (quad[:, 0] - x0 >= rb) & (x1 - quad[:, 0] >= rb)
    keep &= (quad[:, 1] - y0 >= rb) & (y1 - quad[:, 1] >= rb)
    own = np.flatnonzero(keep)  # each kept row's index in quad (a data point's own column)
    quad, data = quad[keep], data[keep]
    u, v = _scaled(window, quad[:, 0], quad[:, 1])
    z = np.column_stack(
        [*([np.ones(len(quad)), u, v] if trend else [np.ones(len(quad))]),
         *(c(quad[:, 0], quad[:, 1]) for c in covariates)]
    )  # fmt: skip
    m = cKDTree(quad).sparse_distance_matrix(cKDTree(pts), reach, output_type="coo_matrix")
    row, col, d = m.row.astype(np.int64), m.col.astype(np.int64), m.data
    mine = ~(data[row] & (own[row] == col))  # a data point's pair with itself aside
    # (a pair at distance 0 is dropped by scipy's sparse matrix; only self-pairs are)
    return _Quadrature(quad, data, z, math.log(rho), (row[mine], col[mine], d[mine]))


def _logistic(q: _Quadrature, s: np.ndarray | None, allowed: np.ndarray, bound):
    """Minus the log composite likelihood at its minimum and the coefficients (theta, then
    c when ``s`` is given, within ``bound``) over the quadrature points ``allowed``."""
    from scipy.optimize import minimize

    zz = q.z[allowed] if s is None else np.column_stack([q.z, s])[allowed]
    data = q.data[allowed]
    log_rho = q.log_rho

    def neg(p):
        eta = zz @ p
        both = np.logaddexp(eta, log_rho)  # log(lambda + rho), without overflow
        share = np.exp(eta - both)
        value = both.sum() - eta[data].sum() - log_rho * (len(eta) - data.sum())
        return float(value), zz.T @ share - zz[data].sum(axis=0)

    start = np.zeros(zz.shape[1])
    start[0] = math.log(max(data.sum(), 1) / max(len(zz) - data.sum(), 1)) + log_rho
    bounds = [(None, None)] * q.z.shape[1] + ([bound] if s is not None else [])
    m = minimize(neg, start, jac=True, method="L-BFGS-B", bounds=bounds)
    return float(m.fun), m.x


def _theta(p: np.ndarray, trend: bool, k: int) -> tuple[float, ...]:
    head = [float(p[0]), float(p[1]), float(p[2])] if trend else [float(p[0]), 0.0, 0.0]
    return (*head, *(float(c) for c in p[(3 if trend else 1) : (3 if trend else 1) + k]))


def _sum_rows(q: _Quadrature, values: np.ndarray, sel: np.ndarray) -> np.ndarray:
    out = np.zeros(len(q.xy))
    np.add.at(out, q.pairs[0][sel], values)
    return out


def fit_strauss(
    pts: np.ndarray,
    window,
    trend: bool,
    radii: np.ndarray,
    border: float,
    covariates: tuple[Covariate, ...] = (),
) -> tuple[float, float, tuple[float, ...]]:
    """``(radius, gamma, log-beta coefficients)`` of the Strauss process that best fits
    ``pts`` over ``radii`` (see the module docstring); gamma in [exp(-30), 1]."""
    q = _quadrature(pts, window, trend, covariates, border, float(np.max(radii)))
    best = _best_strauss(q, np.asarray(radii, float), 0.0)
    _, r, p = best
    return r, math.exp(float(p[-1])), _theta(p, trend, len(covariates))


def _best_strauss(q: _Quadrature, radii: np.ndarray, hard: float):
    _, _, d = q.pairs
    allowed = np.ones(len(q.xy), bool)
    if hard > 0:
        allowed = _sum_rows(q, np.ones(int(np.sum(d < hard))), d < hard) == 0
    best = None
    for r in radii:
        if r <= hard:
            continue
        sel = (d <= r) & (d >= hard)
        t = _sum_rows(q, np.ones(int(sel.sum())), sel)
        value, p = _logistic(q, t, allowed, (-30.0, 0.0))
        if best is None or value < best[0]:
            best = (value, float(r), p)
    return best


def _refined(q: _Quadrature, lo: float, top: float, hard: float):
    """The Strauss fit over 24 radii from ``lo`` to ``top``, then a tenth of a step about
    the best (spatstat's ``profilepl``)."""
    coarse = np.linspace(lo, top, 24)
    _, r, _ = _best_strauss(q, coarse, hard)
    step = coarse[1] - coarse[0]
    return _best_strauss(q, np.linspace(max(r - step, lo), min(r + step, top), 21), hard)


def fit_models(
    pts: np.ndarray,
    window,
    trend: bool,
    covariates: tuple[Covariate, ...],
    top: float,
) -> list[Fitted]:
    """Every model of :data:`MODELS` fitted to ``pts`` (radii up to ``top``, which is also
    the border), in that order."""
    from scipy.spatial import cKDTree

    n = len(pts)
    nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
    hard = float(nn.min()) * n / (n + 1)
    reach = max(top, float(nn.mean()) * SOFT_REACH_FACTOR)
    q = _quadrature(pts, window, trend, covariates, top, min(reach, MAX_RADIUS))
    k_cov = len(covariates)
    _, _, d = q.pairs
    near = d < hard
    free = _sum_rows(q, np.ones(int(near.sum())), near) == 0
    out: list[Fitted] = []

    def add(kind, inhibition, value, p, irregular, hc=0.0):
        k = len(p) + irregular
        out.append(Fitted(kind, inhibition, hc, _theta(p, trend, k_cov), value, 2 * value + 2 * k))

    # every model carries the data's hard core h (the dummies within h of a data point
    # dropped): its likelihood gain is the shortest pair's, the same for all, so the AIC
    # compares the interactions beyond it
    value, p = _logistic(q, None, free, None)
    add("hard core", None, value, p, 1, hard)
    # the hard core each model is written with: the data's, where it is material
    kept = hard if hard >= MATERIAL * float(nn.mean()) else 0.0
    value, r, p = _refined(q, hard * 1.05, top, hard)
    gamma = math.exp(float(p[-1]))
    if kept:
        add("strauss-hard-core", Inhibition("strauss-hard-core", r, gamma, kept), value, p, 2)
    else:
        add("strauss", Inhibition("strauss", r, gamma), value, p, 2)
    best = None
    for delta in (hard * f for f in (0.0, 0.25, 0.5, 0.75, 1.0)):
        for rho in np.linspace(max(hard * 1.2, float(nn.mean()) * 0.5), top, 24):
            sel = (d < rho) & (d > delta)
            s = _sum_rows(q, np.log((d[sel] - delta) / (rho - delta)), sel)
            value, p = _logistic(q, s, free, (0.0, 50.0))
            if best is None or value < best[0]:
                best = (value, float(rho), float(delta), p)
    value, rho, delta, p = best
    dg = Inhibition("diggle-gratton", rho, hard_core=kept, kappa=float(p[-1]), delta=delta)
    add("diggle-gratton", dg, value, p, 3)
    d0 = float(nn.mean())
    best = None
    for kappa in SOFT_KAPPAS:
        s = -_sum_rows(q, (d / d0) ** (-2.0 / kappa), np.ones(len(d), bool))
        value, p = _logistic(q, s, free, (0.0, None))
        if best is None or value < best[0]:
            best = (value, kappa, p)
    value, kappa, p = best
    sigma = d0 * max(float(p[-1]), 1e-12) ** (kappa / 2)
    sigma = min(max(sigma, 1e-3), MAX_RADIUS / 10)
    soft = Inhibition("soft-core", kappa=kappa, sigma=sigma, hard_core=kept)
    add("soft-core", soft, value, p, 2)
    return out


SOFT_REACH_FACTOR = 3.0  # the soft core's pairs counted to this many mean nearest neighbours
# Every model is fitted with the data's hard core h (the dummies within h of a data point
# dropped: a hard core at the shortest pair gains the likelihood of the dummies inside it, a
# gain the AIC's penalty does not price, so all share it), and written with it where it is
# at least this share of the mean nearest-neighbour distance (below, it changes little)
MATERIAL = 0.25


def choose(fits: list[Fitted]) -> Fitted:
    """The fit of the smallest AIC (the first of equals)."""
    return min(fits, key=lambda f: f.aic)

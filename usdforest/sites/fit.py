"""A recipe fitted to a stem map: more stands like the one that was mapped.

Three steps, each a published method (Baddeley, Rubak and Turner 2015, chapters 9 and 12):

1. **Intensity**, log-linear in the coordinates, ``lambda(x, y) = exp(b0 + b1 u + b2 v)``
   with ``u, v`` the coordinates scaled to [-1, 1] over the window, by maximum Poisson
   likelihood (the integral over the rectangle is exact). The trend is kept only when the
   likelihood-ratio test against a constant intensity rejects it at 5 % (chi-squared, 2
   degrees of freedom). With raster covariates (:mod:`usdforest.sites.covariates`), the
   log-intensity is linear in them too (``+ sum c_j z_j(x, y)``, each standardised over
   the window), the likelihood's integral a midpoint rule at half the finest covariate cell
   (spatstat's ``ppm(X ~ x + y + Z)`` on a quadrature); covariates are dropped one at a time
   while the likelihood-ratio test (1 degree of freedom) keeps none of them at 5 % (backward
   elimination), and the trend is tested as before given those kept.
2. **Interaction.** The pattern is compared with 39 patterns of the fitted Poisson process
   (its L(r) - r, with the inhomogeneous K when the intensity has a trend). Above the
   envelope at short range: a Thomas cluster process fitted by minimum contrast on K
   (Diggle 1983; ``sum (K^q - K_theory^q)^2`` with q = 1/4 over ``r`` up to a quarter of the
   shorter side); the trend is then tested again with the variance the clusters give the
   coefficients (:func:`thomas_covariance`) and dropped where it fails. Below it: the
   inhibition models foresters' statisticians use - a hard core, Strauss, Strauss with a
   hard core, Diggle-Gratton and the soft core - each fitted by logistic composite
   likelihood (Baddeley et al. 2014, the border correction), its irregular parameters
   profiled over a grid (spatstat's ``profilepl``), and the one of the smallest
   composite-likelihood AIC chosen (:mod:`usdforest.sites.gibbsfit`); its first-order term
   is log-linear like the intensity. A chosen hard core, or a Strauss gamma below
   ``HARD_GAMMA``, is written as a Matérn II hard core at the shortest nearest-neighbour
   distance. Inside: Poisson.
3. **Marks**: species shares from a ``species`` column, and per species the mean and
   coefficient of variation of ``dbh`` (metres) when the map has them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.sites.clusters import MAX_SCALE, Clusters
from usdforest.sites.covariates import Covariate, quadrature
from usdforest.sites.gibbsfit import _scaled, choose, fit_models, fit_strauss  # noqa: F401
from usdforest.sites.inhibition import MAX_RADIUS, Inhibition
from usdforest.sites.pattern import Bounds, _checked, clark_evans, inhomogeneous_k, pair_rmax

CHI2_2DF_95 = 5.991  # the 95 % quantile of chi-squared with 2 degrees of freedom
CHI2_1DF_95 = 3.841  # and with 1
NSIM = 39
HARD_GAMMA = 0.05  # a fitted Strauss gamma below this is written as a hard core


@dataclass(frozen=True)
class FittedStand:
    """What :func:`fit_stand` found, with the method of each part."""

    window: Bounds
    trees: int
    beta: tuple[float, float, float]  # b0, b1, b2 (b1 = b2 = 0: constant intensity)
    beta_se: tuple[float, float, float]
    trend: bool
    clusters: Clusters | None
    kappa: float | None
    hard_core: float
    clark_evans: float
    interaction: str  # "poisson", "thomas", "hard core" or an Inhibition kind
    species: dict[str, float] = field(default_factory=dict)
    dbh: dict[str, tuple[float, float]] = field(default_factory=dict)  # mean, cv
    inhibition: Inhibition | None = None
    # a Strauss process's log beta: b0, b1, b2 and one coefficient a covariate
    first_order: tuple[float, ...] | None = None
    covariates: tuple[Covariate, ...] = ()
    slopes: tuple[float, ...] = ()  # the intensity's coefficient of each covariate
    slopes_se: tuple[float, ...] = ()
    # each inhibition model's composite-likelihood AIC, where one was chosen among them
    models: dict[str, float] = field(default_factory=dict)

    def intensity(
        self, x: np.ndarray, y: np.ndarray, coefficients: tuple[float, ...] | None = None
    ) -> np.ndarray:
        """The intensity at ``x, y``, or the log-linear ``coefficients`` (b0, b1, b2, then one
        a covariate) there."""
        b = (*self.beta, *self.slopes) if coefficients is None else coefficients
        u, v = _scaled(self.window, x, y)
        eta = b[0] + b[1] * u + b[2] * v
        for c, z in zip(b[3:], self.covariates, strict=True):
            eta = eta + c * z(x, y)
        return np.exp(eta)

    def bound(self, coefficients: tuple[float, ...] | None = None) -> float:
        """The intensity's maximum over the window (or that of the log-linear
        ``coefficients``): at a corner, or with covariates its greatest on the quadrature
        (which meets every covariate cell) times what the trend adds within half a cell."""
        b = (*self.beta, *self.slopes) if coefficients is None else coefficients
        if not self.covariates:
            return math.exp(b[0] + abs(b[1]) + abs(b[2]))
        quad, _ = quadrature(self.window, self.covariates)
        x0, y0, x1, y1 = self.window
        cell = min(c.cell for c in self.covariates)
        margin = abs(b[1]) * cell / (x1 - x0) + abs(b[2]) * cell / (y1 - y0)
        return float(self.intensity(quad[:, 0], quad[:, 1], b).max()) * math.exp(margin)

    def expression(self, coefficients: tuple[float, float, float] | None = None) -> str:
        """The intensity (or log-linear ``coefficients`` in the same scaled coordinates) as
        a recipe expression in x and y."""
        x0, y0, x1, y1 = self.window
        cx, cy, hx, hy = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
        b0, b1, b2 = self.beta if coefficients is None else coefficients
        u = f"(x - {cx:.10g}) / {hx:.10g}"
        v = f"(y - {cy:.10g}) / {hy:.10g}"
        return f"exp({b0:.10g} + {b1:.10g} * {u} + {b2:.10g} * {v})"


def _log_integral(b: float) -> tuple[float, float, float]:
    """log of the integral of exp(b u) over u in [-1, 1], and its first two derivatives."""
    if abs(b) < 1e-6:
        return math.log(2.0), b / 3, 1 / 3
    s = math.sinh(b) / b
    coth = math.cosh(b) / math.sinh(b)
    d1 = coth - 1 / b
    return math.log(2 * s), d1, 1 / b**2 - 1 / math.sinh(b) ** 2


def fit_loglinear(
    xy: np.ndarray,
    window: Bounds,
    trend: bool,
    covariates: tuple[Covariate, ...],
    quad: tuple[np.ndarray, float],
) -> tuple:
    """``(coefficients, se, loglik)`` of the Poisson intensity log-linear in the scaled
    coordinates (with ``trend``) and the standardised ``covariates``, by Newton's method on
    the likelihood with its integral the midpoint rule ``quad`` (points and weight,
    :func:`covariates.quadrature`; one for every model compared): coefficients b0, b1, b2
    (0 without trend), then one a covariate."""
    quad, weight = quad

    def design(p: np.ndarray) -> np.ndarray:
        u, v = _scaled(window, p[:, 0], p[:, 1])
        cols = [np.ones(len(p)), u, v] if trend else [np.ones(len(p))]
        return np.column_stack([*cols, *(z(p[:, 0], p[:, 1]) for z in covariates)])

    zd, zq = design(xy), design(quad)
    n, k = len(xy), zd.shape[1]
    total = zd.sum(axis=0)
    area = weight * len(quad)
    b = np.zeros(k)
    b[0] = math.log(n / area)

    def loglik(b: np.ndarray) -> float:
        return float(total @ b - weight * np.exp(zq @ b).sum())

    ll = loglik(b)
    for _ in range(100):
        e = weight * np.exp(zq @ b)
        grad = total - zq.T @ e
        hess = (zq * e[:, None]).T @ zq
        step = np.linalg.solve(hess, grad)
        t = 1.0
        while loglik(b + t * step) < ll - 1e-12 and t > 1e-6:  # the likelihood is concave
            t /= 2
        b = b + t * step
        new = loglik(b)
        done = abs(new - ll) < 1e-12 * max(abs(ll), 1.0) or np.abs(t * step).max() < 1e-10
        ll = new
        if done:
            break
    e = weight * np.exp(zq @ b)
    se = np.sqrt(np.diag(np.linalg.inv((zq * e[:, None]).T @ zq)))
    full = np.zeros(3 + len(covariates))
    full_se = np.zeros(3 + len(covariates))
    at = [0, 1, 2] if trend else [0]
    at += list(range(3, 3 + len(covariates)))
    full[at], full_se[at] = b, se
    return tuple(float(v) for v in full), tuple(float(v) for v in full_se), ll


def fit_intensity(xy: np.ndarray, window: Bounds, trend: bool = True) -> tuple:
    """``(beta, se, loglik)`` of the log-linear Poisson intensity (constant without
    ``trend``) by Newton's method on the exact likelihood."""
    x0, y0, x1, y1 = window
    area = (x1 - x0) * (y1 - y0)
    n = len(xy)
    u, v = _scaled(window, xy[:, 0], xy[:, 1])
    su, sv = float(u.sum()), float(v.sum())
    b = np.array([math.log(n / area), 0.0, 0.0])
    k = 3 if trend else 1
    for _ in range(100):
        iu, iv = _log_integral(b[1]), _log_integral(b[2])
        big = math.exp(b[0] + iu[0] + iv[0]) * area / 4  # the integral of lambda
        grad = np.array([n - big, su - big * iu[1], sv - big * iv[1]])[:k]
        hess = (
            -big
            * np.array(
                [
                    [1, iu[1], iv[1]],
                    [iu[1], iu[1] ** 2 + iu[2], iu[1] * iv[1]],
                    [iv[1], iu[1] * iv[1], iv[1] ** 2 + iv[2]],
                ]
            )[:k, :k]
        )
        step = np.linalg.solve(hess, grad)
        b[:k] -= step
        if np.abs(step).max() < 1e-10:
            break
    iu, iv = _log_integral(b[1]), _log_integral(b[2])
    big = math.exp(b[0] + iu[0] + iv[0]) * area / 4
    loglik = float(n * b[0] + b[1] * su + b[2] * sv - big)
    se = np.zeros(3)
    se[:k] = np.sqrt(np.diag(np.linalg.inv(-hess)))
    return tuple(float(v) for v in b), tuple(float(v) for v in se), loglik


def _thomas_contrast(k_hat: np.ndarray, r: np.ndarray) -> tuple[float, float]:
    """``(kappa, sigma)`` of the Thomas K closest to ``k_hat`` in ``sum (K^q - K_T^q)^2``,
    q = 1/4, searched on log scales from a grid of starts."""
    from scipy.optimize import minimize

    q = 0.25
    target = np.maximum(k_hat, 0) ** q

    def cost(p: np.ndarray) -> float:
        kappa, sigma = math.exp(p[0]), math.exp(p[1])
        model = math.pi * r**2 + (1 - np.exp(-(r**2) / (4 * sigma**2))) / kappa
        return float(((target - model**q) ** 2).sum())

    starts = [(math.log(k), math.log(s)) for k in (1e-4, 1e-3, 1e-2, 1e-1) for s in (0.5, 2, 8)]
    best = min((minimize(cost, s, method="Nelder-Mead", options={"xatol": 1e-6,
               "fatol": 1e-12, "maxiter": 4000}) for s in starts), key=lambda m: m.fun)  # fmt: skip
    return math.exp(best.x[0]), math.exp(best.x[1])


MIN_TREES = 20  # a fit of fewer is refused (also by `usdforest fit`, naming the map)


def fit_stand(
    xy: np.ndarray,
    window: Bounds,
    species: list[str] | None = None,
    dbh: np.ndarray | None = None,
    seed: int = 0,
    covariates: tuple[Covariate, ...] = (),
) -> FittedStand:
    """Fit intensity, interaction and marks to the stem map ``xy`` in ``window``, the
    intensity log-linear in the coordinates and in ``covariates`` where the data say so."""
    pts, w, h, area = _checked(xy, window)
    n = len(pts)
    if n < MIN_TREES:
        raise UsdForestError(f"a fit needs at least {MIN_TREES} trees, got {n}")
    beta, se, trend, covariates, slopes, slopes_se = _first_order(pts, window, covariates)
    fitted = FittedStand(
        window, n, beta, se, trend, None, None, 0.0, 0.0, "poisson",
        covariates=covariates, slopes=slopes, slopes_se=slopes_se,
    )  # fmt: skip
    lam = fitted.intensity(pts[:, 0], pts[:, 1])
    rmax = pair_rmax(n, w, h, min(w, h) / 4)  # (a large map's pairs held in bounded memory)
    r = np.linspace(rmax / 40, rmax, 40)
    short = r <= rmax / 2
    k_hat = inhomogeneous_k(pts, window, r, lam)
    # the envelope of the fitted Poisson process, from its own thinned simulations
    rng = np.random.default_rng(seed)
    sims = []
    bound = fitted.bound()
    x0, y0, x1, y1 = window
    for _ in range(NSIM):
        m = rng.poisson(bound * area)
        c = np.column_stack([rng.uniform(x0, x1, m), rng.uniform(y0, y1, m)])
        c = c[rng.uniform(size=m) * bound < fitted.intensity(c[:, 0], c[:, 1])]
        if len(c) >= 2:
            sims.append(inhomogeneous_k(c, window, r, fitted.intensity(c[:, 0], c[:, 1])))
    lo, hi = np.min(sims, axis=0), np.max(sims, axis=0)
    ce = clark_evans(pts, window)
    clusters, kappa, hard_core, kind = None, None, 0.0, "poisson"
    if np.any(k_hat[short] > hi[short]):
        kappa, sigma = _thomas_contrast(k_hat, r)
        # the likelihood-ratio tests and standard errors assumed Poisson; under the fitted
        # Thomas process the coefficients vary more (Waagepetersen 2007): the trend is
        # tested again with that variance, and dropped (K refitted) where it fails
        cov = thomas_covariance(fitted, kappa, sigma)
        if trend and _wald(fitted, cov) <= CHI2_2DF_95:
            beta, se, trend, covariates, slopes, slopes_se = _first_order(
                pts, window, covariates, allow_trend=False
            )
            fitted = replace(fitted, beta=beta, trend=trend, covariates=covariates, slopes=slopes)
            lam = fitted.intensity(pts[:, 0], pts[:, 1])
            k_hat = inhomogeneous_k(pts, window, r, lam)
            kappa, sigma = _thomas_contrast(k_hat, r)
            bound = fitted.bound()
            cov = thomas_covariance(fitted, kappa, sigma)
        sd = np.sqrt(np.diag(cov))
        se, slopes_se = _spread(sd, fitted)
        # within what a recipe takes: a scale of at most MAX_SCALE m, at most 10,000 trees a
        # cluster (a minimum contrast that runs off to either is a pattern barely clustered)
        clusters = Clusters("thomas", min(sigma, MAX_SCALE), min(max(bound / kappa, 1e-3), 1e4))
        kind = "thomas"
    inhibition, first_order = None, None
    models: dict[str, float] = {}
    if kind == "poisson" and np.any(k_hat[short] < lo[short]):
        from scipy.spatial import cKDTree

        nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
        top = max(min(3 * nn.mean(), rmax / 2, MAX_RADIUS), nn.min())
        fits = fit_models(pts, window, trend, covariates, top)
        models = {f.kind: f.aic for f in fits}
        chosen = choose(fits)
        if chosen.kind == "hard core" or (
            chosen.kind == "strauss" and chosen.inhibition.gamma < HARD_GAMMA
        ):
            hard_core, kind = float(nn.min()), "hard core"
        else:
            inhibition, first_order, kind = chosen.inhibition, chosen.theta, chosen.kind
    shares: dict[str, float] = {}
    sizes: dict[str, tuple[float, float]] = {}
    if species is not None:
        names, counts = np.unique(np.asarray(species), return_counts=True)
        shares = {str(k): float(c) / n for k, c in zip(names, counts, strict=True)}
        if dbh is not None:
            d = np.asarray(dbh, dtype=float)
            for name in shares:
                sel = d[(np.asarray(species) == name) & np.isfinite(d) & (d > 0)]
                if len(sel) >= 2:
                    sizes[name] = (float(sel.mean()), float(sel.std(ddof=1) / sel.mean()))
    return FittedStand(
        window, n, beta, se, trend, clusters, kappa, hard_core, ce, kind, shares, sizes,
        inhibition, first_order, covariates, slopes, slopes_se, models,
    )  # fmt: skip


def _spread(values: np.ndarray, f: FittedStand) -> tuple[tuple, tuple]:
    """Per-coefficient ``values`` of :func:`thomas_covariance`'s order as ``(b0, b1, b2)``
    (0 for a trend not fitted) and one a covariate."""
    head = [float(values[0]), 0.0, 0.0]
    if f.trend:
        head[1:] = [float(values[1]), float(values[2])]
    return tuple(head), tuple(float(v) for v in values[(3 if f.trend else 1) :])


def _wald(f: FittedStand, cov: np.ndarray) -> float:
    """The Wald statistic of the trend (b1, b2) under the covariance ``cov``."""
    b = np.array(f.beta[1:3])
    return float(b @ np.linalg.solve(cov[1:3, 1:3], b))


def thomas_covariance(f: FittedStand, kappa: float, sigma: float) -> np.ndarray:
    """The covariance of the first-order coefficients (b0, b1 and b2 with a trend, then one a
    covariate) when the pattern is a Thomas process of ``kappa`` parents/m² and scale
    ``sigma`` m, by Waagepetersen's (2007, Biometrics 63:252) sandwich ``I^-1 (I + J) I^-1``:
    ``I = int z z' lambda``, the Poisson information, and ``J = int int z(u) z(v)' lambda(u)
    lambda(v) (g(u - v) - 1)``, with the Thomas ``g - 1 = exp(-r^2 / (4 sigma^2)) / (4 pi
    kappa sigma^2)``; both on a grid over the window at a quarter of sigma (at most 512 a
    side), the double integral a convolution (FFT)."""
    from scipy.signal import fftconvolve

    x0, y0, x1, y1 = f.window
    step = max(sigma / 4, (x1 - x0) / 512, (y1 - y0) / 512)
    nx, ny = max(math.ceil((x1 - x0) / step), 8), max(math.ceil((y1 - y0) / step), 8)
    dx, dy = (x1 - x0) / nx, (y1 - y0) / ny
    gx = x0 + (np.arange(nx) + 0.5) * dx
    gy = y0 + (np.arange(ny) + 0.5) * dy
    xx, yy = np.meshgrid(gx, gy)
    lam = f.intensity(xx, yy)
    u, v = _scaled(f.window, xx, yy)
    cols = [np.ones_like(xx), u, v] if f.trend else [np.ones_like(xx)]
    cols += [c(xx, yy) for c in f.covariates]
    w = dx * dy
    fields = [c * lam for c in cols]
    info = np.array([[w * float((a * b / lam).sum()) for b in fields] for a in fields])
    # the kernel to where it falls below exp(-16), or across the window (no pair is further
    # apart: a minimum contrast that ran off to a huge sigma made a grid of 77 GiB)
    kx = np.arange(-min(int(8 * sigma / dx), nx), min(int(8 * sigma / dx), nx) + 1) * dx
    ky = np.arange(-min(int(8 * sigma / dy), ny), min(int(8 * sigma / dy), ny) + 1) * dy
    kxx, kyy = np.meshgrid(kx, ky)
    kernel = np.exp(-(kxx**2 + kyy**2) / (4 * sigma**2)) / (4 * math.pi * kappa * sigma**2)
    spread = [fftconvolve(fld, kernel, mode="same") for fld in fields]
    extra = np.array([[w * w * float((a * s).sum()) for s in spread] for a in fields])
    inv = np.linalg.inv(info)
    return inv @ (info + extra) @ inv


def _first_order(
    pts: np.ndarray,
    window: Bounds,
    covariates: tuple[Covariate, ...],
    allow_trend: bool = True,
) -> tuple:
    """``(beta, se, trend, covariates kept, their slopes, their se)``: the covariates by
    backward elimination (each dropped in turn while the likelihood-ratio test of the model
    without it does not reject that at 5 %, chi-squared 1 degree of freedom), then the trend
    by its own test given them (no trend without ``allow_trend``); without covariates, the
    exact likelihood."""
    if not covariates:
        b1, se1, ll1 = fit_intensity(pts, window, trend=True)
        b0, se0, ll0 = fit_intensity(pts, window, trend=False)
        trend = allow_trend and 2 * (ll1 - ll0) > CHI2_2DF_95
        beta, se = (b1, se1) if trend else (b0, se0)
        return beta, se, trend, (), (), ()
    quad = quadrature(window, covariates)
    kept = tuple(covariates)
    full = fit_loglinear(pts, window, allow_trend, kept, quad)
    while kept:  # backward elimination: drop the covariate the data need least, if any
        drops = [
            fit_loglinear(pts, window, allow_trend, kept[:j] + kept[j + 1 :], quad)
            for j in range(len(kept))
        ]
        j = int(np.argmax([d[2] for d in drops]))
        if 2 * (full[2] - drops[j][2]) > CHI2_1DF_95:
            break
        kept, full = kept[:j] + kept[j + 1 :], drops[j]
    flat = fit_loglinear(pts, window, False, kept, quad)
    trend = allow_trend and 2 * (full[2] - flat[2]) > CHI2_2DF_95
    b, se, _ = full if trend else flat
    return b[:3], se[:3], trend, kept, b[3 : 3 + len(kept)], se[3 : 3 + len(kept)]


def intensity_grid(f: FittedStand) -> np.ndarray:
    """The fitted intensity (a Strauss process's beta) over the window as a raster recipe
    reads it: one value a cell at the covariates' finest cell (at most 2,000 a side), row 0
    north, each the intensity at the cell's centre."""
    x0, y0, x1, y1 = f.window
    cell = min(c.cell for c in f.covariates)
    nx = int(min(max(math.ceil((x1 - x0) / cell), 1), 2000))
    ny = int(min(max(math.ceil((y1 - y0) / cell), 1), 2000))
    gx = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    gy = y1 - (np.arange(ny) + 0.5) * (y1 - y0) / ny
    xx, yy = np.meshgrid(gx, gy)
    coefficients = f.first_order or (*f.beta, *f.slopes)
    return f.intensity(xx, yy, coefficients)


def recipe_toml(f: FittedStand, raster: str | None = None) -> dict:
    """The fitted stand as recipe data (what ``tomli_w`` writes and ``usdforest build``
    reads): region, intensity, clusters or hard core, the species mix and sizes. An
    intensity with covariates is the raster file ``raster`` (:func:`intensity_grid`, saved
    beside the recipe)."""
    data: dict = {"seed": 1, "region": {"kind": "rectangle", "bounds": list(f.window)}}
    coefficients = f.first_order or f.beta  # a Strauss process's intensity is its beta
    if f.covariates:
        if raster is None:
            raise UsdForestError("an intensity fitted with covariates is written as a raster")
        data["intensity"] = {"kind": "raster", "file": raster}
    elif f.trend:
        data["intensity"] = {
            "kind": "expression",
            "expr": f.expression(coefficients[:3]),
            "bound": f.bound(coefficients[:3]) * (1 + 1e-6),
        }
    else:
        data["intensity"] = {"kind": "constant", "value": math.exp(coefficients[0])}
    if f.inhibition is not None:
        data["inhibition"] = f.inhibition.describe()
    if f.clusters is not None:
        data["clusters"] = f.clusters.describe()
    if f.hard_core > 0:
        data["forest"] = {"hard_core": round(f.hard_core, 3)}
    if f.species:
        from usdforest.grow.species import get_species

        data["mix"] = dict(f.species)
        data["species"] = {}
        for name in f.species:
            table: dict = {}
            if name in f.dbh and get_species(name).allometry is not None:
                mean, cv = f.dbh[name]
                # the recipe's ranges: a CV of 0.02-1.5, the smallest tree below the mean
                table["stand"] = {
                    "dbh_mean": round(mean, 4),
                    "dbh_cv": round(min(max(cv, 0.02), 1.5), 4),
                    "dbh_min": round(min(0.04, mean / 2), 4),
                }
            data["species"][name] = table
    return data

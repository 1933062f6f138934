"""Soft inhibition: pairwise-interaction Gibbs processes, the Strauss process (Strauss 1975;
Kelly and Ripley 1976) first, in which trees closer than ``radius`` repel each other without
forbidding each other, and the Strauss process with a hard core, Diggle and Gratton's and the
soft core (:class:`Inhibition`), whose pair correlations rise from 0 as real stands' do.

A pattern ``x`` in the window ``W`` has density (with respect to the unit-rate Poisson
process) ``f(x) ∝ prod_i beta(x_i) * gamma^s(x)``, where ``s(x)`` counts the pairs closer than
``radius``: ``gamma = 1`` is the Poisson process of intensity ``beta``, ``gamma = 0`` a hard
core, and between them nearby trees are allowed but rarer, so the pair-correlation function
rises gradually towards 1 inside ``radius`` instead of jumping there (Illian et al. 2008,
*Statistical Analysis and Modelling of Spatial Point Patterns*, section 3.6; spatstat's
``rStrauss`` and ``ppm(..., Strauss(r))``). The recipe's ``[intensity]`` is ``beta(x, y)``,
the process's first-order term: the stand is sparser than ``beta``, by about
``lambda = W(beta G) / G`` with ``G = (1 - gamma) pi radius^2`` (the integral of ``1 - phi``
for the other interactions) and ``W`` Lambert's function
(the Poisson-saddlepoint approximation of Baddeley and Nair 2012, Statistics and Computing
22:1247; exact for ``gamma = 1``).

Simulated by the birth-death Metropolis-Hastings algorithm of Geyer and Møller (1994,
Scandinavian Journal of Statistics 21:359; Møller and Waagepetersen 2004, algorithm 7.1;
spatstat's ``rmh``): starting from the Poisson process of intensity ``beta``, each step
proposes with probability 1/2 a birth at a uniform point ``u`` of the window's bounding box
``B``, accepted with probability ``min(1, beta(u) |B| gamma^t(u) / (n + 1))``, and otherwise
the death of a uniformly chosen tree ``x_i``, accepted with probability ``min(1, n / (beta(x_i)
|B| gamma^t(x_i)))``, where ``t`` counts the trees within ``radius`` of the point (for the
other interactions ``gamma^t`` is the product of ``phi`` over the trees near it). The chain
runs ``STEPS_PER_TREE`` steps per tree of the starting pattern (and at least ``MIN_STEPS``),
in numba, with the trees in a grid of cells at least ``radius`` wide so that each step looks
at the 3 x 3 cells around its point.

The simulation covers the whole region at once (a Gibbs process has no cell-by-cell
construction), from its own random stream, so the forest is the same whatever its tiles,
blocks or workers: every task of a build takes its cells' trees from the same pattern, which a
process computes once.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import RecipeError
from usdforest.grow import exact

KINDS = ("strauss", "strauss-hard-core", "diggle-gratton", "soft-core")
CODES = {k: i for i, k in enumerate(KINDS)}  # the kernel's interaction codes
MAX_RADIUS = 50.0  # metres
STEPS_PER_TREE = 50
MIN_STEPS = 20_000
CHUNK = 1_000_000  # steps whose random numbers are drawn at once
MAX_GRID = 4_000_000  # cells of the neighbour grid
SOFT_REACH = 1e-4  # a soft core's pairs farther apart than where -log phi falls below this
# are left out


@dataclass(frozen=True)
class Inhibition:
    """A pairwise interaction ``phi(d)`` of trees ``d`` apart (the chain's conditional
    intensity is ``beta(u)`` times the product of ``phi`` over the trees near ``u``):

    * ``strauss``: ``gamma`` within ``radius`` (Strauss 1975), ``gamma`` in [0, 1] (0: a
      hard core at the radius, 1: none);
    * ``strauss-hard-core``: 0 within ``hard_core``, ``gamma`` from there to ``radius``
      (spatstat's ``StraussHard``);
    * ``diggle-gratton``: 0 within ``delta``, ``((d - delta) / (radius - delta))**kappa``
      from there to ``radius`` (rho), 1 beyond (Diggle and Gratton 1984, JRSS B 46:193;
      spatstat's ``DiggleGratton``): a pair correlation rising smoothly from 0 to 1,
      ``kappa`` >= 0 its steepness;
    * ``soft-core``: ``exp(-(sigma / d)**(2 / kappa))``, ``sigma`` > 0 metres, ``kappa`` in
      (0, 1) (Ogata and Tanemura 1984; spatstat's ``Softcore``): no range of its own, cut
      where ``-log phi`` falls below :data:`SOFT_REACH` (:attr:`reach`).

    Diggle-Gratton and the soft core may carry a ``hard_core`` too (0 within it: what a fit
    to a map with a hard core writes). Distances in metres; each parameter only where the
    kind has it."""

    kind: str
    radius: float = 0.0
    gamma: float = 1.0
    hard_core: float = 0.0
    kappa: float = 0.0
    sigma: float = 0.0
    delta: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise RecipeError(f"inhibition.kind: {self.kind!r} is not one of {', '.join(KINDS)}")
        if self.kind == "soft-core":
            if not (math.isfinite(self.sigma) and 0 < self.sigma <= MAX_RADIUS / 10):
                raise RecipeError(
                    f"inhibition.sigma: expected metres in (0, {MAX_RADIUS / 10:g}], "
                    f"got {self.sigma:g}"
                )
            if not (math.isfinite(self.kappa) and 0 < self.kappa < 1):
                raise RecipeError(
                    f"inhibition.kappa: expected a number in (0, 1), got {self.kappa:g}"
                )
            self._check_hard_core(self.reach)
            return
        if not (math.isfinite(self.radius) and 0 < self.radius <= MAX_RADIUS):
            raise RecipeError(
                f"inhibition.radius: expected metres in (0, {MAX_RADIUS:g}], got {self.radius:g}"
            )
        if not (math.isfinite(self.gamma) and 0 <= self.gamma <= 1):
            raise RecipeError(f"inhibition.gamma: expected a number in [0, 1], got {self.gamma:g}")
        if self.kind != "strauss":
            self._check_hard_core(self.radius)
        if self.kind == "diggle-gratton":
            if not (math.isfinite(self.delta) and 0 <= self.delta < self.radius):
                raise RecipeError(
                    f"inhibition.delta: expected metres in [0, radius = {self.radius:g}), "
                    f"got {self.delta:g}"
                )
            if not (math.isfinite(self.kappa) and 0 <= self.kappa <= 50):
                raise RecipeError(
                    f"inhibition.kappa: expected a number in [0, 50], got {self.kappa:g}"
                )

    def _check_hard_core(self, reach: float) -> None:
        if not (math.isfinite(self.hard_core) and 0 <= self.hard_core < reach):
            raise RecipeError(
                f"inhibition.hard_core: expected metres in [0, {reach:g}) (the interaction's "
                f"range), got {self.hard_core:g}"
            )

    @property
    def reach(self) -> float:
        """The farthest two trees interact (m)."""
        if self.kind == "soft-core":
            return min(self.sigma * SOFT_REACH ** (-self.kappa / 2), MAX_RADIUS)
        return self.radius

    def phi(self, d: np.ndarray) -> np.ndarray:
        """The interaction of trees ``d`` apart (1: none, 0: forbidden)."""
        d = np.asarray(d, dtype=float)
        if self.kind == "strauss":
            return np.where(d < self.radius, self.gamma, 1.0)
        if self.kind == "strauss-hard-core":
            f = np.where(d < self.radius, self.gamma, 1.0)
        elif self.kind == "diggle-gratton":
            t = np.clip((d - self.delta) / (self.radius - self.delta), 0.0, 1.0)
            f = np.where(d <= self.delta, 0.0, exact.power(t, self.kappa))
        else:
            with np.errstate(divide="ignore"):
                r = exact.power(self.sigma / np.maximum(d, 1e-300), 2 / self.kappa)
                f = np.where(d < self.reach, exact.exp(-np.minimum(r, 745.0)), 1.0)
        return np.where(d < self.hard_core, 0.0, f)

    def params(self) -> np.ndarray:
        """The kernel's parameters: squared reach, gamma, hard core, radius, kappa, sigma,
        delta."""
        return np.array(
            [self.reach**2, self.gamma, self.hard_core, self.radius, self.kappa, self.sigma,
             self.delta]
        )  # fmt: skip

    def excluded_area(self) -> float:
        """``G``, the integral of ``1 - phi`` over the plane (m²): the area a tree takes from
        its neighbours' chances."""
        if self.kind == "strauss":
            return (1 - self.gamma) * math.pi * self.radius**2
        d = np.linspace(0.0, self.reach, 4001)
        f = (1.0 - self.phi(d)) * 2 * math.pi * d
        return float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(d)))

    def intensity(self, beta):
        """The Poisson-saddlepoint approximation of the stand's intensity where the
        first-order term is ``beta`` (a number or an array; Baddeley and Nair 2012):
        ``W(beta G) / G``, ``G`` :meth:`excluded_area`."""
        from scipy.special import lambertw

        g = self.excluded_area()
        if g == 0:
            return beta
        lam = lambertw(np.asarray(beta, dtype=float) * g).real / g
        return float(lam) if np.ndim(lam) == 0 else lam

    def expected(self, region, intensity) -> float:
        """About how many trees a recipe's stand has: :meth:`intensity` of the recipe's
        ``beta(x, y)`` summed over a grid of the region (a local saddlepoint approximation)."""
        from usdforest.sites.pointprocess import region_grid

        gx, gy, inside, cell = region_grid(region)
        beta = np.zeros(gx.shape)
        beta[inside] = intensity.evaluate(gx[inside], gy[inside])
        return float(np.sum(self.intensity(beta)) * cell)

    def describe(self) -> dict:
        keys = {
            "strauss": ("radius", "gamma"),
            "strauss-hard-core": ("radius", "gamma", "hard_core"),
            "diggle-gratton": ("radius", "delta", "kappa", "hard_core"),
            "soft-core": ("sigma", "kappa", "hard_core"),
        }[self.kind]
        out = {"kind": self.kind, **{k: getattr(self, k) for k in keys}}
        if self.kind in ("diggle-gratton", "soft-core") and not self.hard_core:
            out.pop("hard_core")
        return out


def simulate(inhibition: Inhibition, region, intensity, rng: np.random.Generator) -> np.ndarray:
    """A Strauss pattern in ``region`` with first-order term ``intensity`` (its
    ``evaluate(x, y)``; see the module): ``float64[n, 2]`` sites."""
    from usdforest.sites import inhibition_kernels as kern
    from usdforest.sites.pointprocess import thin

    start = thin(region, intensity, rng)
    x0, y0, x1, y1 = region.bounds
    box = (x1 - x0) * (y1 - y0)
    side = max(inhibition.reach, math.sqrt(box / MAX_GRID))
    nx, ny = max(1, math.ceil((x1 - x0) / side)), max(1, math.ceil((y1 - y0) / side))
    cap = 3 * len(start) + 1000  # above any count the chain reaches from a Poisson start
    state = kern.State.empty(cap, nx * ny)
    beta0 = np.asarray(intensity.evaluate(start[:, 0], start[:, 1]), float) * box
    kern.insert_all(state.arrays(), start[:, 0], start[:, 1], beta0, x0, y0, side, nx, ny)
    steps = max(STEPS_PER_TREE * len(start), MIN_STEPS)
    r2 = inhibition.radius**2
    code, params = CODES[inhibition.kind], inhibition.params()
    for done in range(0, steps, CHUNK):
        m = min(CHUNK, steps - done)
        birth = rng.uniform(size=m) < 0.5
        nb = int(birth.sum())
        cx = np.zeros(m)
        cy = np.zeros(m)
        cb = np.zeros(m)
        cx[birth] = rng.uniform(x0, x1, nb)
        cy[birth] = rng.uniform(y0, y1, nb)
        inside = region.contains(cx[birth], cy[birth])
        b = np.zeros(nb)
        if inside.any():
            b[inside] = intensity.evaluate(cx[birth][inside], cy[birth][inside])
        cb[birth] = b * box
        accept = rng.uniform(size=m)
        pick = rng.uniform(size=m)
        if code == 0:  # Strauss: gamma to the number of neighbours
            full = kern.run(
                state.arrays(), birth, cx, cy, cb, accept, pick,
                x0, y0, side, nx, ny, r2, inhibition.gamma,
            )  # fmt: skip
        else:
            full = kern.run_pairwise(
                state.arrays(), birth, cx, cy, cb, accept, pick,
                x0, y0, side, nx, ny, code, params,
            )  # fmt: skip
        if full:
            raise RecipeError(
                f"inhibition: the chain grew past {cap:,} trees; the [intensity] and "
                "[inhibition] do not describe a stand that settles"
            )
    return state.sites()


_SIMULATED: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}  # the last few


def recipe_sites(recipe, replicate: int, cell_of) -> tuple[np.ndarray, np.ndarray]:
    """The Strauss pattern of a recipe's replicate, simulated once per process and recipe
    content (the tile tasks of one build share it): sites ordered by their sampling cell
    (``cell_of(recipe, xy)``, :func:`usdforest.sites.cells.cell_of`, passed in so that the
    modules do not import each other; stably: within a cell in the chain's order), and those
    cells."""
    from usdforest.seeds import stream

    key = (json.dumps([recipe.data, str(recipe.base), recipe.seed], sort_keys=True, default=str),
           replicate)  # fmt: skip
    if key not in _SIMULATED:
        rng = stream(recipe.seed, "inhibition", replicate)
        pts = simulate(recipe.inhibition, recipe.region, recipe.intensity, rng)
        cell = cell_of(recipe, pts)
        order = np.argsort(cell, kind="stable")
        pts, cell = pts[order], cell[order]
        pts.setflags(write=False)
        cell.setflags(write=False)
        while len(_SIMULATED) >= 4:
            _SIMULATED.pop(next(iter(_SIMULATED)))
        _SIMULATED[key] = (pts, cell)
    return _SIMULATED[key]

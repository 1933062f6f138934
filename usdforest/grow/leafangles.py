"""Leaf inclination distributions: the density of the angle between a leaf's normal and the
vertical (0: a flat leaf, 90°: an upright one), as canopy radiative transfer writes them.

A distribution is named by a short tuple, as a recipe's ``[species.NAME.geometry]`` gives it:

* de Wit's (1965) archetypes, no parameter: ``("planophile",)`` (mostly flat leaves, mean
  26.8°), ``("erectophile",)`` (63.2°), ``("plagiophile",)`` (45°), ``("extremophile",)``
  (45°, flat and upright), ``("spherical",)`` (57.3°: leaf normals spread evenly over the
  hemisphere) and ``("uniform",)`` (45°);
* ``("ellipsoidal", x)``: Campbell's (1986) ellipsoidal distribution, leaf normals spread as
  the normals of a spheroid's surface whose horizontal semi-axis is ``x`` times its vertical
  one (1: spherical; larger: flatter leaves);
* ``("beta", mu, nu)``: the two-parameter beta distribution of ``t = 2 theta / pi`` (Goel &
  Strebel 1984), ``f(t) = t^(nu-1) (1-t)^(mu-1) / B(mu, nu)``, mean ``90 nu / (mu + nu)``
  degrees, the form leveled-photography datasets publish (Chianucci et al. 2018).

Draws use the inverse of the cumulative distribution tabulated every 0.01° (plain numpy
arithmetic, so the same seed gives the same leaves on every platform).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import RecipeError
from usdforest.grow import exact

ARCHETYPES = ("planophile", "erectophile", "plagiophile", "extremophile", "spherical", "uniform")
PARAMETERS = {**{k: 0 for k in ARCHETYPES}, "ellipsoidal": 1, "beta": 2}
GRID = 9001  # tabulated angles, 0-90 degrees every 0.01


def density(spec: tuple, theta: np.ndarray) -> np.ndarray:
    """The (unnormalised) density of leaf inclination ``theta`` (radians) for ``spec``."""
    kind, args = spec[0], [float(a) for a in spec[1:]]
    t = np.asarray(theta, dtype=np.float64)
    if kind == "planophile":
        return 1.0 + np.cos(2.0 * t)
    if kind == "erectophile":
        return 1.0 - np.cos(2.0 * t)
    if kind == "plagiophile":
        return 1.0 - np.cos(4.0 * t)
    if kind == "extremophile":
        return 1.0 + np.cos(4.0 * t)
    if kind == "spherical":
        return np.sin(t)
    if kind == "uniform":
        return np.ones_like(t)
    if kind == "ellipsoidal":
        x = args[0]
        return np.sin(t) / (np.cos(t) ** 2 + x * x * np.sin(t) ** 2) ** 2
    mu, nu = args
    s = np.clip(2.0 * t / math.pi, 1e-12, 1.0 - 1e-12)
    return exact.power(s, nu - 1.0) * exact.power(1.0 - s, mu - 1.0)


def check(spec: tuple, where: str) -> tuple:
    """``spec`` as a tuple ``(kind, *numbers)``, or a one-line error naming ``where``."""
    spec = tuple(spec)
    if not spec or not isinstance(spec[0], str) or spec[0] not in PARAMETERS:
        raise RecipeError(
            f"{where}: expected [kind, parameters...] with kind one of "
            f"{', '.join(PARAMETERS)}, got {list(spec)!r}"
        )
    kind, args = spec[0], spec[1:]
    if len(args) != PARAMETERS[kind]:
        raise RecipeError(f"{where}: {kind!r} takes {PARAMETERS[kind]} number(s), got {len(args)}")
    for a in args:
        if isinstance(a, bool) or not isinstance(a, int | float) or not (0 < a < 1e3):
            raise RecipeError(f"{where}: {kind!r} parameters must be numbers in (0, 1000)")
    return (kind, *(float(a) for a in args))


@dataclass(frozen=True, eq=False)
class LeafAngles:
    """A tabulated leaf inclination distribution (see the module's docstring)."""

    spec: tuple
    theta: np.ndarray  # radians, 0..pi/2
    cdf: np.ndarray

    @classmethod
    def of(cls, spec: tuple, where: str = "leaf inclination") -> LeafAngles:
        spec = check(spec, where)
        theta = np.linspace(0.0, math.pi / 2, GRID)
        f = np.maximum(density(spec, theta), 0.0)
        cdf = np.concatenate([[0.0], np.cumsum((f[1:] + f[:-1]) * 0.5 * np.diff(theta))])
        cdf /= cdf[-1]
        theta.setflags(write=False)
        cdf.setflags(write=False)
        return cls(spec, theta, cdf)

    def sample(self, u: np.ndarray) -> np.ndarray:
        """Inclinations (radians) at cumulative probabilities ``u`` in [0, 1]."""
        return np.interp(u, self.cdf, self.theta)

    def mean_deg(self) -> float:
        """The mean inclination in degrees."""
        mid = 0.5 * (self.theta[1:] + self.theta[:-1])
        return float(np.degrees(np.sum(mid * np.diff(self.cdf))))

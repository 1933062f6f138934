"""Published allometry of five temperate European trees: height, crown and foliage from DBH.

Units: DBH ``d`` in cm, heights in m, basal area of larger trees ``bal`` in m²/ha, crown
competition factor ``ccf`` in %. Every equation names its source; where the project had to
choose a number itself, the docstring says so.

* **Height - DBH**: Näslund's curve ``h = 1.3 + d**p / (a + b d)**p``. Pine, spruce and birch
  take the parameters of Luke's stand simulator (``lukefi/metsi``, ``naslund.py``, attributed
  there to Siipilehto): pine p=2, a=0.894, b=0.185; spruce p=3, a=1.811, b=0.308; birch p=2,
  a=0.898, b=0.242. Beech and oak take Näslund curves (p=2) fitted here, over DBH 5-70 cm, to
  Söderberg's individual-tree height functions for southern Sweden (Söderberg 1992, *Functions
  for forest management: height, form height and bark thickness of individual trees*, SLU
  Dept. of Forest Survey Report 52; fitted on 220 beech and 292 oak trees of the Swedish NFI),
  evaluated at latitude 56°, 100 m altitude, no spruce, in the counties where Swedish beech
  and oak grow (Skåne, Halland, Blekinge: the functions' "region 5"), the stand conditions
  being the project's choice: beech in a stand 100 years old (a=1.3505, b=0.2067); oak on a
  site of pine site index H100 26 m whose largest tree is 70 cm (a=1.444, b=0.1922). The fits
  are within 6-7 % of the functions over 5-70 cm. At 8 m they give slendernesses of 106-108
  (beech yield table, Wiedemann 1931: 102-144). Residual scatter: lognormal, 8 % (the
  project's choice).
* **Crown width**: Hasenauer 1997 (Forest Ecology and Management 96:197) open-grown trees,
  ``cd = exp(b0 + b1 ln d + mse/2)``, the coefficients as the Prognaus simulator ships them.
* **Crown ratio**: Hasenauer & Monserud 1996 (Ecological Modelling 90) logistic model with
  Hasenauer 2000's coefficients as Prognaus ships them; ``cr = 1 / (1 + exp(a0 + b1 100h/d +
  b2 h + b3 d² + c1 BAL + c2 ln CCF))`` at elevation and slope 0 (birch: "other broadleaves").
  Crown base = h (1 - cr): it rises with the stand's density through BAL and CCF.
* **Foliage**: dry mass from Repola 2009 (Silva Fennica 43:625; pine, spruce) and Repola 2008
  (Silva Fennica 42:605; birch over 11 cm, Johansson 1999 below, as Majasalmi et al. 2013 use
  it), ``ln W = b0 + b1 ds/(ds + k) + b2 h/(h + 1) + (su² + se²)/2`` with ds = 2 + 1.25 d,
  times the specific leaf area Majasalmi et al. 2013 (Forest Ecology and Management 292:10)
  use: pine 6.2, spruce 4.95, birch 13.55 m²/kg. One-sided area (hemi-surface for needles).
  Beech and oak: no per-tree equation was at hand; their leaf area is 0.31 m² per cm² of
  basal area, the project's calibration that gives a stand at the yield tables' basal area
  (beech 12-20 m²/ha at 8 m) a leaf area index of 3.7-6.2, Asner, Scurlock & Hicke 2003's
  temperate broadleaf range (3-6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.grow import exact


@dataclass(frozen=True)
class Allometry:
    """One species' published equations (see the module docstring for sources)."""

    name: str
    latin: str
    naslund: tuple[float, float, float]  # (p, a, b)
    crown: tuple[float, float, float]  # Hasenauer 1997: (b0, b1, mse)
    crown_ratio: tuple[float, float, float, float, float, float]  # a0, b1, b2, b3, c1, c2
    foliage: tuple[str, tuple[float, ...]]  # ("repola", (b0, b1, k, b2, bias)) or ("basal", (k,))
    sla: float = 0.0  # m²/kg (repola)
    height_sd: float = 0.08  # lognormal residual of height about the curve
    crown_sd: float = 0.15  # lognormal residual of the crown width (Hasenauer's mse ~ 0.03-0.06)

    def height(self, d: np.ndarray) -> np.ndarray:
        """Mean height (m) of trees of DBH ``d`` (cm)."""
        p, a, b = self.naslund
        d = np.asarray(d, dtype=float)
        return 1.3 + exact.power(d, p) / exact.power(a + b * d, p)

    def dbh(self, h: np.ndarray) -> np.ndarray:
        """The DBH (cm) whose mean height is ``h`` (the curve's inverse)."""
        p, a, b = self.naslund
        x = exact.power(np.maximum(np.asarray(h, dtype=float) - 1.3, 1e-6), 1.0 / p)
        # d / (a + b d) = x  ->  d = a x / (1 - b x)
        return a * x / np.maximum(1.0 - b * x, 1e-6)

    def crown_radius(self, d: np.ndarray) -> np.ndarray:
        """Open-grown crown radius (m) of DBH ``d`` (cm), Hasenauer 1997."""
        b0, b1, mse = self.crown
        return 0.5 * exact.exp(b0 + b1 * exact.log(np.asarray(d, dtype=float)) + 0.5 * mse)

    def crown_ratio_of(
        self, d: np.ndarray, h: np.ndarray, bal: np.ndarray | float = 0.0, ccf: float = 100.0
    ) -> np.ndarray:
        """Crown length / height, Hasenauer & Monserud 1996 (elevation and slope 0)."""
        a0, b1, b2, b3, c1, c2 = self.crown_ratio
        d = np.asarray(d, dtype=float)
        h = np.asarray(h, dtype=float)
        x = (
            a0
            + b1 * 100.0 * h / d
            + b2 * h
            + b3 * d**2
            + c1 * np.asarray(bal)
            + c2 * math.log(max(ccf, 1.0))
        )
        return 1.0 / (1.0 + exact.exp(x))

    def leaf_area(self, d: np.ndarray, h: np.ndarray) -> np.ndarray:
        """One-sided leaf area (m²) of a tree of DBH ``d`` (cm) and height ``h`` (m)."""
        d = np.asarray(d, dtype=float)
        h = np.asarray(h, dtype=float)
        kind, c = self.foliage
        if kind == "basal":
            return c[0] * math.pi * (d / 200.0) ** 2
        b0, b1, k, b2, bias = c
        ds = 2.0 + 1.25 * d
        mass = exact.exp(b0 + b1 * ds / (ds + k) + b2 * h / (h + 1.0) + bias)
        if self.name == "silver-birch":  # Repola 2008 only above 11 cm (Majasalmi et al. 2013)
            mass = np.where(d > 11.0, mass, 0.00371 * exact.power(10.0 * ds, 1.11993))
        return mass * self.sla


ALLOMETRY: dict[str, Allometry] = {
    a.name: a
    for a in (
        Allometry(
            "scots-pine",
            "Pinus sylvestris",
            (2.0, 0.894, 0.185),
            (-0.1797, 0.6267, 0.037),
            (-1.676984, 0.002942, 0.026387, 0.0, 0.013054, 0.245749),
            ("repola", (-6.303, 14.472, 6.0, -3.976, (0.109 + 0.118) / 2)),
            sla=6.2,
        ),
        Allometry(
            "norway-spruce",
            "Picea abies",
            (3.0, 1.811, 0.308),
            (-0.3232, 0.6441, 0.026),
            (-3.893748, 0.011232, 0.02687, -0.6358e-4, 0.010574, 0.404436),
            ("repola", (-2.994, 12.251, 10.0, -3.415, (0.107 + 0.089) / 2)),
            sla=4.95,
        ),
        Allometry(
            "european-beech",
            "Fagus sylvatica",
            (2.0, 1.3505, 0.2067),  # Söderberg 1992, fitted (module docstring)
            (0.2662, 0.6072, 0.058),
            (-3.853739, 0.007435, 0.024684, -1.35686e-4, 0.0, 0.384344),
            ("basal", (0.31e4,)),  # m² of leaves per m² of basal area (0.31 m²/cm²)
        ),
        Allometry(
            "sessile-oak",
            "Quercus petraea",
            (2.0, 1.444, 0.1922),  # Söderberg 1992, fitted (module docstring)
            (-0.3973, 0.7328, 0.038),
            (-1.985395, 0.005525, 0.013867, -1.10735e-4, 0.006856, 0.201014),
            ("basal", (0.31e4,)),
        ),
        Allometry(
            "silver-birch",
            "Betula pendula",
            (2.0, 0.898, 0.242),
            (0.1783, 0.5665, 0.025),
            (-1.995385, 0.00649, 0.019637, -1.2235e-4, 0.003633, 0.158546),
            ("repola", (-29.566, 33.372, 2.0, 0.0, 0.077 / 2)),
            sla=13.55,
        ),
    )
}


def weibull_for(mean: float, cv: float) -> tuple[float, float]:
    """Weibull (shape, scale) with the given mean and coefficient of variation."""
    from scipy.optimize import brentq
    from scipy.special import gamma

    def cv_of(k: float) -> float:
        g1, g2 = gamma(1 + 1 / k), gamma(1 + 2 / k)
        return math.sqrt(max(g2 / g1**2 - 1.0, 0.0))

    k = brentq(lambda k: cv_of(k) - cv, 0.3, 50.0)
    return k, mean / gamma(1 + 1 / k)

"""The understorey: shrubs and the regeneration of the stand's own species, between the
ground vegetation and the crowns, where light comes through.

**Shrubs** (``[shrubs]``) are the ``hazel`` and ``bramble`` presets (L-system shrubs dressed
with the CAD templates, as the trees are): a multi-stemmed common hazel 2.5-4 m tall and a
bramble of arching canes 1.4-2 m. The recipe gives the fraction of the ground under their
crowns (``cover``); they stand one to a cell of ``cell`` metres (so no two overlap), in cells
drawn with weights ``light ** light_response``, until their crowns' footprints add up to
``cover`` of the region (the last one scaled to the remainder).

**Regeneration** (``[regeneration]``) is the stand's species as saplings and small trees,
at least 0.2 m tall and under 7 cm DBH: the German NFI's regeneration (BWI 2012 counts such
trees on small circles apart from the overstory; its method as described in *Forests* 2018,
9:212, doi:10.3390/f9040212). ``density`` stems per hectare stand in cells drawn (with
repetition) with weights ``light ** light_response``; heights are log-uniform between
``height`` (more small than tall); each species comes in proportion to its stems in the
overstory. Each species is grown in ``classes`` height classes (geometric steps) by its
allometry (a sapling under breast height with the inventory's sapling slenderness); each
plant is its class scaled to its height.

Light is the ground vegetation's (:func:`usdforest.grow.groundcover.floor_light`): Beer-
Lambert under the crowns at each cell's centre. Nothing stands within ``clearance`` of a
living stem.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import RecipeError
from usdforest.grow import exact
from usdforest.grow.groundcover import cells_in, floor_light
from usdforest.grow.obstacles import Stems
from usdforest.seeds import stream

SHRUB_FORMS = ("hazel", "bramble")
SHRUB_SCALE = (0.8, 1.2)  # uniform scale of a shrub about its variant's size
MAX_TRIES = 50  # places tried in a cell before it is given up


@dataclass(frozen=True)
class ShrubSpec:
    """A recipe's ``[shrubs]`` table (see the module docstring).

    Attributes
    ----------
    cover
        Fraction of the region under the shrubs' crowns (their footprints seen from above).
    hazel, bramble
        Shares of that cover (sum 1).
    variants
        Shrub assets grown per form.
    cell
        Side of a cell (metres): at most one shrub per cell.
    light_response
        Exponent of the light the cells are drawn by (0: any cell alike).
    clearance
        Metres kept between a shrub's base and a living stem.
    """

    cover: float = 0.08
    hazel: float = 0.6
    bramble: float = 0.4
    variants: int = 3
    cell: float = 5.0
    light_response: float = 1.0
    clearance: float = 0.5

    @property
    def shares(self) -> np.ndarray:
        return np.array([self.hazel, self.bramble], dtype=float)


@dataclass(frozen=True)
class RegenerationSpec:
    """A recipe's ``[regeneration]`` table (see the module docstring).

    Attributes
    ----------
    density
        Young trees per hectare (0.2 m tall and up, under 7 cm DBH).
    height
        ``(low, high)`` metres: heights are log-uniform between them.
    classes
        Height classes (tree assets) per species.
    cell
        Side of the cells the light is taken at (metres).
    light_response
        Exponent of the light the cells are drawn by (0: any cell alike).
    clearance
        Metres kept between a young tree and a living stem.
    """

    density: float = 1500.0
    height: tuple[float, float] = (0.2, 4.0)
    classes: int = 3
    cell: float = 2.0
    light_response: float = 1.0
    clearance: float = 0.3


@dataclass(frozen=True, eq=False)
class Plants:
    """Understorey plants in recipe coordinates, each an instance of a prototype.

    Attributes
    ----------
    proto
        ``int32[n]`` index into the layer's prototypes.
    xy
        ``(n, 2)`` base positions.
    yaw
        ``(n,)`` degrees about +Z.
    scale
        ``(n,)`` uniform scale of the prototype.
    height
        ``(n,)`` metres.
    light
        ``(n,)`` relative light at its cell's centre.
    """

    proto: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    scale: np.ndarray
    height: np.ndarray
    light: np.ndarray

    def __len__(self) -> int:
        return len(self.proto)

    @staticmethod
    def empty() -> Plants:
        z = np.zeros(0)
        return Plants(np.zeros(0, np.int32), np.zeros((0, 2)), z, z, z, z)

    @staticmethod
    def concat(parts: list[Plants]) -> Plants:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Plants.empty()
        fields = ("proto", "xy", "yaw", "scale", "height", "light")
        return Plants(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields))


def _lit_cells(
    region, cell: float, crowns: tuple[np.ndarray, np.ndarray, np.ndarray], response: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The region's whole cells of side ``cell``: their centres, the light at each
    (:func:`~usdforest.grow.groundcover.floor_light`) and ``light ** response``."""
    centre = cells_in(region, cell)
    light = floor_light(centre, *crowns)
    return centre, light, exact.power(light, response)


def place_shrubs(
    spec: ShrubSpec,
    region,
    seed: int,
    crowns: tuple[np.ndarray, np.ndarray, np.ndarray],
    stems: tuple[np.ndarray, np.ndarray],
    footprint: np.ndarray,
    reach: np.ndarray,
) -> Plants:
    """The shrubs of ``spec`` over ``region``: ``footprint`` and ``reach`` are each shrub
    prototype's crown footprint (m²) and largest horizontal distance from its base (m) at
    scale 1, prototypes ordered form by form (``spec.variants`` each, :data:`SHRUB_FORMS`
    order); ``crowns`` as :func:`~usdforest.grow.groundcover.floor_light` takes them;
    ``stems`` the living stems' xy and base radii. The same recipe and seed give the same
    shrubs."""
    rng = stream(seed, "shrubs")
    centre, light, weight = _lit_cells(region, spec.cell, crowns, spec.light_response)
    if not len(centre) or spec.cover <= 0:
        return Plants.empty()
    target = spec.cover * float(region.area)
    stems_at = Stems(*stems)
    order = _weighted_order(weight, rng)
    rows = []
    covered = 0.0
    for c in order:
        if covered >= target:
            break
        form = int(rng.choice(len(SHRUB_FORMS), p=spec.shares / spec.shares.sum()))
        proto = form * spec.variants + int(rng.integers(spec.variants))
        # the crown fits its cell: no two shrubs overlap
        s = min(rng.uniform(*SHRUB_SCALE), spec.cell / (2 * reach[proto]))
        s = min(s, math.sqrt((target - covered) / footprint[proto]))  # the last one fits
        slack = max(spec.cell / 2 - s * reach[proto], 0.0)
        for _ in range(MAX_TRIES):
            xy = centre[c] + rng.uniform(-slack, slack, 2)
            if stems_at.clear(xy, xy, 0.0, spec.clearance):
                break
        else:
            continue
        rows.append((proto, xy, rng.uniform(0, 360), s, light[c]))
        covered += s * s * footprint[proto]
    if covered < target * (1 - 1e-9):
        most = covered / float(region.area)
        raise RecipeError(
            f"shrubs.cover: {spec.cover:.4g} is more than the cells hold ({most:.3f} of the "
            f"region with cell = {spec.cell:g} m, one shrub a cell); lower shrubs.cover or "
            "shrubs.cell"
        )
    return _plants(rows, np.zeros(len(rows)))


def _weighted_order(weight: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Cells in a random order that draws heavier ones first (weighted sampling without
    replacement: Efraimidis and Spirakis's keys u^(1/w)); cells of weight 0 never."""
    w = np.asarray(weight, float)
    u = rng.uniform(size=len(w))
    ok = w > 0
    key = np.full(len(w), -np.inf)
    key[ok] = exact.log(u[ok]) / w[ok]
    return np.argsort(-key, kind="stable")[: int(ok.sum())]


def _plants(rows: list, height: np.ndarray) -> Plants:
    if not rows:
        return Plants.empty()
    proto, xy, yaw, scale, light = zip(*rows, strict=True)
    return Plants(
        np.array(proto, np.int32),
        np.array(xy, float).reshape(-1, 2),
        np.array(yaw, float),
        np.array(scale, float),
        np.asarray(height, float),
        np.array(light, float),
    )


def regeneration_heights(spec: RegenerationSpec) -> np.ndarray:
    """The height (m) each size class is grown to: geometric midpoints of ``spec.classes``
    equal log-steps of ``spec.height``."""
    lo, hi = (math.log(h) for h in spec.height)
    edges = np.linspace(lo, hi, spec.classes + 1)
    return exact.exp((edges[:-1] + edges[1:]) / 2)


def place_regeneration(
    spec: RegenerationSpec,
    region,
    seed: int,
    crowns: tuple[np.ndarray, np.ndarray, np.ndarray],
    stems: tuple[np.ndarray, np.ndarray],
    shares: np.ndarray,
) -> Plants:
    """The young trees of ``spec`` over ``region``, species ``k`` with probability
    ``shares[k]``; prototype ``k * spec.classes + c`` is species ``k`` in height class ``c``
    (:func:`regeneration_heights`). ``crowns`` and ``stems`` as for :func:`place_shrubs`."""
    rng = stream(seed, "regeneration")
    centre, light, weight = _lit_cells(region, spec.cell, crowns, spec.light_response)
    n = round(spec.density * float(region.area) / 1e4)
    shares = np.asarray(shares, float)
    if not len(centre) or n == 0 or not len(shares) or shares.sum() <= 0:
        return Plants.empty()
    if weight.sum() <= 0:
        weight = np.ones(len(centre))
    counts = rng.multinomial(n, weight / weight.sum())
    cell_of = np.repeat(np.arange(len(centre)), counts)
    species = rng.choice(len(shares), size=n, p=shares / shares.sum())
    lo, hi = (math.log(h) for h in spec.height)
    height = exact.exp(rng.uniform(lo, hi, n))
    classes = regeneration_heights(spec)
    cls = np.argmin(np.abs(exact.log(height)[:, None] - exact.log(classes)[None]), axis=1)
    stems_at = Stems(*stems)
    rows, kept = [], []
    for i, c in enumerate(cell_of):
        for _ in range(MAX_TRIES):
            xy = centre[c] + rng.uniform(-spec.cell / 2, spec.cell / 2, 2)
            if stems_at.clear(xy, xy, 0.0, spec.clearance):
                break
        else:
            continue  # a cell filled by a trunk
        proto = int(species[i]) * spec.classes + int(cls[i])
        rows.append((proto, xy, rng.uniform(0, 360), height[i] / classes[cls[i]], light[c]))
        kept.append(height[i])
    return _plants(rows, np.array(kept))

"""Ground vegetation: patches of grass, herbs, ferns and moss whose cover follows the light
that reaches the forest floor.

The herb layer's cover is, of everything a stand's structure sets, most closely tied to the
light under the canopy: across 75 beech, beech-pine and spruce plots in three German regions
(the Biodiversity Exploratories) understorey cover rose with measured light transmittance
(Dormann et al. 2020, *BMC Ecology* 20:43), and light was the strongest driver of herb-layer
cover in managed mixed forests in western Hungary (Márialigeti et al. 2016, *Plant Ecology*
217:549). How much cover a stand has on average also depends on soil, browsing and history,
so the recipe gives it (``cover``, the fraction of the ground that vegetation hides from
above) and the light distributes it.

The region is cut into square cells of ``cell`` metres. Each cell's **relative light** is
Beer-Lambert's ``exp(-k sum(LAI_i))`` over the crowns above it (each crown a disc of the
area of its footprint holding its leaf area; ``k = 0.5``, leaves of random orientation).
Each cell holds one patch of one growth form (drawn by the form shares) whose **cover of
its cell** is proportional to ``light ** light_response``, scaled so that the region's mean
is ``cover`` exactly; no cell gets more than its patch can hold (a patch's disc fits its
cell, and a patch covers only part of its own disc: between 36 % and 64 % of the cell for
the shipped forms), the rest going to the other cells.

A patch is an instance of a CAD template (``templates/groundcover_<form>.usdc``, 1 m across
as authored) scaled across to the cell's cover and to its form's height (jittered by
``height_jitter``), turned at random and resting on the ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import RecipeError
from usdforest.grow import exact
from usdforest.seeds import stream

FORMS = ("grass", "herb", "fern", "moss")
EXTINCTION = 0.5  # k of Beer-Lambert for leaves of random (spherical) orientation
SINK = 0.01  # m: a patch's base goes this far below the lowest ground under it


@dataclass(frozen=True)
class GroundCoverSpec:
    """A recipe's ``[groundcover]`` table (see the module docstring).

    Attributes
    ----------
    cover
        Mean fraction of the region's ground hidden from above by the vegetation, 0-1.
    grass, herb, fern, moss
        Shares of the cells given to each growth form (sum 1).
    cell
        Side of a cell (metres): one patch per cell.
    light_response
        Exponent of the light a cell's cover follows (0: the same cover everywhere).
    height_jitter
        Each patch's height is its form's times a uniform factor in ``1 +- height_jitter``.
    litter
        Give the ground a leaf-litter material (when the forest has ground).
    """

    cover: float = 0.3
    grass: float = 0.3
    herb: float = 0.35
    fern: float = 0.1
    moss: float = 0.25
    cell: float = 2.0
    light_response: float = 1.0
    height_jitter: float = 0.25
    litter: bool = True

    @property
    def shares(self) -> np.ndarray:
        return np.array([self.grass, self.herb, self.fern, self.moss], dtype=float)


@dataclass(frozen=True, eq=False)
class PatchShape:
    """A ground-vegetation template in its own frame (unit height, footprint centred).

    Attributes
    ----------
    radius
        Largest horizontal distance of the mesh from its axis (unit frame).
    fill
        The fraction of the disc of that radius that the mesh hides from above.
    height
        The patch's height as authored (metres).
    """

    radius: float
    fill: float
    height: float

    @property
    def cap(self) -> float:
        """The most of a square cell this patch covers, its disc filling the cell."""
        return self.fill * math.pi / 4


@dataclass(frozen=True, eq=False)
class Patches:
    """Ground-vegetation patches in recipe coordinates.

    Attributes
    ----------
    form
        ``int8[n]`` index into :data:`FORMS`.
    base
        ``(n, 3)`` where the template's origin goes (its footprint's centre, on the ground).
    diameter
        ``(n,)`` metres across the patch's disc.
    height
        ``(n,)`` metres.
    yaw
        ``(n,)`` radians about +Z.
    cover
        ``(n,)`` the fraction of its cell the patch hides from above.
    light
        ``(n,)`` relative light at its cell's centre.
    """

    form: np.ndarray
    base: np.ndarray
    diameter: np.ndarray
    height: np.ndarray
    yaw: np.ndarray
    cover: np.ndarray
    light: np.ndarray
    cell: float

    def __len__(self) -> int:
        return len(self.form)

    @property
    def area(self) -> np.ndarray:
        """m² of ground each patch hides from above."""
        return self.cover * self.cell**2


def floor_light(
    points: np.ndarray, crowns_xy: np.ndarray, crowns_r: np.ndarray, crowns_lai: np.ndarray
) -> np.ndarray:
    """Relative light at ``points`` (m, 2) under crowns (discs at ``crowns_xy`` of radius
    ``crowns_r`` holding leaf area index ``crowns_lai`` over their disc): Beer-Lambert's
    ``exp(-k sum LAI)`` with ``k`` = :data:`EXTINCTION`."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, float).reshape(-1, 2)
    lai = np.zeros(len(pts))
    if len(crowns_xy) and len(pts):
        tree = cKDTree(pts)
        hits = tree.query_ball_point(np.asarray(crowns_xy, float), np.asarray(crowns_r, float))
        counts = np.array([len(h) for h in hits])
        if counts.sum():
            cells = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
            np.add.at(lai, cells, np.repeat(np.asarray(crowns_lai, float), counts))
    return exact.exp(-EXTINCTION * lai)


def cells_in(region, cell: float) -> np.ndarray:
    """Centres ``(m, 2)`` of the square cells of side ``cell`` that the region holds whole
    (centre and corners), on a grid from the region's lower-left bound."""
    x0, y0, x1, y1 = region.bounds
    nx, ny = max(math.ceil((x1 - x0) / cell), 1), max(math.ceil((y1 - y0) / cell), 1)
    gx, gy = np.meshgrid(x0 + cell * (np.arange(nx) + 0.5), y0 + cell * (np.arange(ny) + 0.5))
    centre = np.column_stack([gx.ravel(), gy.ravel()])
    inside = region.contains(centre[:, 0], centre[:, 1])
    for dx, dy in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
        inside &= region.contains(centre[:, 0] + dx * cell / 2, centre[:, 1] + dy * cell / 2)
    return centre[inside]


def _fill(weight: np.ndarray, cap: np.ndarray, total: float) -> np.ndarray:
    """Covers ``min(t * weight, cap)`` adding up to ``total`` (bisection on ``t``)."""
    if total <= 0:
        return np.zeros_like(weight)
    lo, hi = 0.0, 1.0
    while np.minimum(hi * weight, cap).sum() < total:
        hi *= 2.0
    for _ in range(100):
        mid = (lo + hi) / 2
        if np.minimum(mid * weight, cap).sum() < total:
            lo = mid
        else:
            hi = mid
    c = np.minimum(hi * weight, cap)
    free = c < cap
    # the last rounding: the uncapped cells take the remainder exactly
    if free.any():
        c[free] *= (total - c[~free].sum()) / c[free].sum()
    return c


def place_ground_cover(
    spec: GroundCoverSpec,
    region,
    seed: int,
    crowns: tuple[np.ndarray, np.ndarray, np.ndarray],
    shapes: dict[str, PatchShape],
    ground=None,
) -> Patches:
    """The ground vegetation of ``spec`` over ``region`` (recipe coordinates) under
    ``crowns`` (``xy (m, 2)``, radius, leaf area index of each crown's disc), on ``ground``
    (a :class:`~usdforest.sites.terrain.HeightField`, or the plane z = 0).

    ``shapes`` maps each form to its template's :class:`PatchShape`. The same recipe and
    seed give the same patches.
    """
    rng = stream(seed, "groundcover")
    a = spec.cell
    centre = cells_in(region, a)
    n = len(centre)
    total = spec.cover * float(region.area) / a**2  # in cells' worth of cover
    form = rng.choice(len(FORMS), size=n, p=spec.shares / spec.shares.sum()).astype(np.int8)
    cap = np.array([shapes[f].cap for f in FORMS])[form]
    if total > cap.sum() * (1 - 1e-9):
        most = cap.sum() * a**2 / float(region.area)
        raise RecipeError(
            f"groundcover.cover: {spec.cover:.4g} is more than these patches can hold "
            f"({most:.3f} of the region with these form shares and cell = {a:g} m); lower "
            "groundcover.cover or give more of the cells to herb and moss"
        )
    light = floor_light(centre, *crowns)
    weight = exact.power(light, spec.light_response)
    cover = _fill(weight, cap, total)
    fill = np.array([shapes[f].fill for f in FORMS])[form]
    diameter = 2 * a * np.sqrt(cover / (fill * math.pi))
    slack = (a - diameter) / 2
    xy = centre + rng.uniform(-1, 1, (n, 2)) * slack[:, None]
    yaw = rng.uniform(0, 2 * math.pi, n)
    jitter = rng.uniform(1 - spec.height_jitter, 1 + spec.height_jitter, n)
    height = np.array([shapes[f].height for f in FORMS])[form] * jitter
    z = _floor(ground, xy, diameter / 2)
    keep = cover > 0
    return Patches(
        form[keep],
        np.column_stack([xy, z])[keep],
        diameter[keep],
        height[keep],
        yaw[keep],
        cover[keep],
        light[keep],
        a,
    )


def _floor(ground, xy: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The lowest ground under each footprint (its centre and four rim points), less
    :data:`SINK`."""
    if ground is None or not len(xy):
        return np.full(len(xy), -SINK)
    offsets = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], float)
    pts = xy[:, None, :] + offsets[None] * r[:, None, None]
    z = ground.height(pts[..., 0].ravel(), pts[..., 1].ravel()).reshape(len(xy), 5)
    return z.min(axis=1) - SINK

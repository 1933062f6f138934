"""Dead wood: snags, stumps, lying logs and fallen branches, by volume per hectare.

A managed forest holds dead wood in three compartments that national inventories measure
separately. The defaults are the German National Forest Inventory's (BWI 2012, pieces of
at least 10 cm diameter): 20.6 m³/ha, 49 % of it lying, 23 % standing and 28 % stumps; about
half of it in the advanced or heavy decay classes (3-4 of 4) and 47 % of it in pieces of at
least 30 cm diameter (Thünen-Institut, *Dritte Bundeswaldinventur*, 2014). Reserves hold far
more: 130 m³/ha on average in European beech reserves (Christensen et al. 2005, *Biological
Conservation* 122:311).

Every piece is an instance of a CAD template (``templates/deadwood_<kind>_<decay>.usdc``):
unit length along +Z, scaled to its length and to its **diameter, that of the cylinder of
the same length and volume** (so a piece's volume is exactly ``pi d² l / 4`` of its mesh).
Diameters follow a Weibull distribution truncated at the inventory's threshold; the default
(mean 0.20 m, CV 0.5 before truncation at 0.10 m) puts 45 % of the volume in pieces of 30 cm
and more (BWI: 47 %). Lengths are uniform in the recipe's ranges. Each compartment is
filled to its volume exactly: the last piece is shortened to the remainder.

Pieces stand or lie where there is room: not within ``clearance`` of a living stem or of
another piece (their footprints are compared as 2-D capsules). Lying pieces follow the
ground's slope and rest on it; decay classes 3 and 4 sink into the litter by 10 % and 25 %
of their thickness, and a class-4 log lies on its flat side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.grow import exact
from usdforest.grow.allometry import weibull_for
from usdforest.grow.obstacles import Stems, point_segment
from usdforest.seeds import stream

KINDS = ("log", "snag", "stump", "branch")
DECAY_CLASSES = 4
SINK = (0.0, 0.0, 0.1, 0.25)  # fraction of its thickness a lying piece sinks, by decay class
MAX_TRIES = 5000  # places tried per piece before the plot is called too crowded


@dataclass(frozen=True)
class DeadWoodSpec:
    """A recipe's ``[deadwood]`` table (see the module docstring for the defaults' sources).

    Attributes
    ----------
    volume
        Dead wood, m³ per hectare of the region.
    lying, standing, stumps
        Shares of the volume (sum 1): logs and fallen branches; snags; stumps.
    decay
        Shares of the pieces in decay classes 1-4 (sum 1).
    diameter_mean, diameter_cv, min_diameter
        The Weibull distribution of diameters (metres) before truncation, and its
        truncation (the inventory's threshold).
    branch_diameter
        Lying pieces thinner than this are fallen branches (crooked), the rest logs.
    log_length, snag_height, stump_height
        ``(low, high)`` metres: uniform ranges of lengths.
    clearance
        Metres kept free between a piece and a living stem or another piece.
    """

    volume: float = 20.6
    lying: float = 0.49
    standing: float = 0.23
    stumps: float = 0.28
    decay: tuple[float, float, float, float] = (0.25, 0.25, 0.25, 0.25)
    diameter_mean: float = 0.20
    diameter_cv: float = 0.5
    min_diameter: float = 0.10
    branch_diameter: float = 0.15
    log_length: tuple[float, float] = (2.0, 10.0)
    snag_height: tuple[float, float] = (2.0, 12.0)
    stump_height: tuple[float, float] = (0.2, 0.6)
    clearance: float = 0.1


@dataclass(frozen=True, eq=False)
class PieceShape:
    """A dead-wood template in its own frame (base at the origin, axis +Z, unit length).

    Attributes
    ----------
    volume
        The unit mesh's volume.
    hull
        ``(v, 3)`` vertices of its convex hull (where it touches the ground).
    """

    volume: float
    hull: np.ndarray

    @property
    def radius(self) -> float:
        """Radius of the unit-length cylinder of the same volume."""
        return math.sqrt(self.volume / math.pi)

    @property
    def reach(self) -> float:
        """Largest distance of the mesh from its axis, over :attr:`radius`."""
        return float(np.linalg.norm(self.hull[:, :2], axis=1).max()) / self.radius


@dataclass(frozen=True, eq=False)
class Pieces:
    """Dead-wood pieces in recipe coordinates.

    Attributes
    ----------
    kind
        ``int8[n]`` index into :data:`KINDS`.
    decay
        ``int8[n]`` decay class 1-4.
    base
        ``(n, 3)`` where the template's origin goes (a standing piece's foot; a lying
        piece's one end, on its axis).
    axis
        ``(n, 3)`` unit direction of the piece's axis (the template's +Z).
    side
        ``(n, 3)`` unit direction of the template's +X (across the axis).
    length, diameter
        ``(n,)`` metres (diameter of the cylinder of equal volume).
    """

    kind: np.ndarray
    decay: np.ndarray
    base: np.ndarray
    axis: np.ndarray
    side: np.ndarray
    length: np.ndarray
    diameter: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    @property
    def volume(self) -> np.ndarray:
        """m³ of each piece."""
        return math.pi / 4 * self.diameter**2 * self.length

    @property
    def centre(self) -> np.ndarray:
        """``(n, 3)`` middle of each piece's axis."""
        return self.base + self.axis * (self.length / 2)[:, None]


def _diameters(spec: DeadWoodSpec, rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` diameters from the Weibull truncated below at ``min_diameter`` (inverse CDF)."""
    k, lam = weibull_for(spec.diameter_mean, spec.diameter_cv)
    lo = 1.0 - math.exp(-((spec.min_diameter / lam) ** k))
    u = lo + (1.0 - lo) * rng.random(n)
    return lam * exact.power(-exact.log1p(-np.minimum(u, 1 - 1e-12)), 1 / k)


def _sizes(
    target: float,
    span: tuple[float, float],
    spec: DeadWoodSpec,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Diameters and lengths of pieces whose volumes add up to ``target`` m³ (the last piece
    shortened, or thinned at the shortest length, to the remainder; a remainder too small
    for the thinnest piece is left out)."""
    ds, ls = [], []
    left = target
    while left > 0:
        d = _diameters(spec, rng, 256)
        ln = rng.uniform(span[0], span[1], 256)
        v = math.pi / 4 * d**2 * ln
        run = np.cumsum(v)
        full = int(np.searchsorted(run, left, side="right"))
        ds.append(d[:full])
        ls.append(ln[:full])
        left -= float(run[full - 1]) if full else 0.0
        if full < len(d):  # the remainder: this piece, shorter or thinner
            dk, lk = float(d[full]), left / (math.pi / 4 * float(d[full]) ** 2)
            if lk < span[0]:
                lk = span[0]
                dk = math.sqrt(left / (math.pi / 4 * lk))
            if dk >= spec.min_diameter:
                ds.append(np.array([dk]))
                ls.append(np.array([lk]))
            break
    return np.concatenate(ds), np.concatenate(ls)


class _Room:
    """Footprints (2-D capsules) already taken: living stems and placed pieces."""

    def __init__(self, stems_xy: np.ndarray, stems_r: np.ndarray, clearance: float) -> None:
        self.stems = Stems(stems_xy, stems_r)
        self.clearance = clearance
        self.cell = 4.0
        self.grid: dict[tuple[int, int], list[int]] = {}
        self.a: list[np.ndarray] = []
        self.b: list[np.ndarray] = []
        self.r: list[float] = []

    def _cells(self, a: np.ndarray, b: np.ndarray, r: float):
        lo = np.floor((np.minimum(a, b) - r) / self.cell).astype(int)
        hi = np.floor((np.maximum(a, b) + r) / self.cell).astype(int)
        for i in range(lo[0], hi[0] + 1):
            for j in range(lo[1], hi[1] + 1):
                yield i, j

    def free(self, a: np.ndarray, b: np.ndarray, r: float) -> bool:
        """Whether the capsule ``a``-``b`` of radius ``r`` keeps clear of everything."""
        c = self.clearance
        if not self.stems.clear(a, b, r, c):
            return False
        seen = set()
        for key in self._cells(a, b, r + c):
            for k in self.grid.get(key, ()):
                if k in seen:
                    continue
                seen.add(k)
                if _segment_segment(a, b, self.a[k], self.b[k]) < r + self.r[k] + c:
                    return False
        return True

    def take(self, a: np.ndarray, b: np.ndarray, r: float) -> None:
        k = len(self.r)
        self.a.append(a)
        self.b.append(b)
        self.r.append(r)
        for key in self._cells(a, b, r):
            self.grid.setdefault(key, []).append(k)


def _segment_segment(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> float:
    """Distance between the 2-D segments ``a``-``b`` and ``c``-``d``."""

    def cross(u, v):
        return u[0] * v[1] - u[1] * v[0]

    r, s = b - a, d - c
    den = cross(r, s)
    if abs(den) > 1e-12:
        t, u = cross(c - a, s) / den, cross(c - a, r) / den
        if 0 <= t <= 1 and 0 <= u <= 1:
            return 0.0
    ends = (
        point_segment(c[None], a, b)[0],
        point_segment(d[None], a, b)[0],
        point_segment(a[None], c, d)[0],
        point_segment(b[None], c, d)[0],
    )
    return float(min(ends))


def _frames(axis: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Unit side vectors (the template's +X) across each ``axis``, turned ``roll`` radians
    from the direction nearest world up (for a vertical axis: from world +X)."""
    up = np.array([0.0, 0.0, 1.0])
    ref = up - exact.dot(axis, up)[:, None] * axis
    vertical = np.linalg.norm(ref, axis=1) < 1e-6
    ref[vertical] = [1.0, 0.0, 0.0]
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    other = np.cross(axis, ref)
    return np.cos(roll)[:, None] * ref + np.sin(roll)[:, None] * other


def _lowest(
    shape: PieceShape, axis: np.ndarray, side: np.ndarray, length: np.ndarray, across: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest points (world z, relative to the template's origin) of each
    placed hull: its thickness along world up."""
    lo = np.empty(len(axis))
    hi = np.empty(len(axis))
    third = np.cross(axis, side)
    for s in range(0, len(axis), 2048):
        e = slice(s, s + 2048)
        z = (
            np.outer(side[e, 2] * across[e], shape.hull[:, 0])
            + np.outer(third[e, 2] * across[e], shape.hull[:, 1])
            + np.outer(axis[e, 2] * length[e], shape.hull[:, 2])
        )
        lo[e], hi[e] = z.min(axis=1), z.max(axis=1)
    return lo, hi


def place_dead_wood(
    spec: DeadWoodSpec,
    region,
    seed: int,
    stems_xy: np.ndarray,
    stems_r: np.ndarray,
    shapes: dict[tuple[str, int], PieceShape],
    ground=None,
) -> Pieces:
    """The dead wood of ``spec`` over ``region`` (recipe coordinates), clear of the living
    stems (``stems_xy`` (m, 2), base radii ``stems_r``), on ``ground`` (a
    :class:`~usdforest.sites.terrain.HeightField`, or the plane z = 0).

    ``shapes`` maps ``(kind, decay)`` to its template's :class:`PieceShape`. The same
    recipe and seed give the same pieces.
    """
    rng = stream(seed, "deadwood")
    area_ha = float(region.area) / 1e4
    total = spec.volume * area_ha
    jobs = [
        ("standing", spec.snag_height, spec.standing * total),
        ("stumps", spec.stump_height, spec.stumps * total),
        ("lying", spec.log_length, spec.lying * total),
    ]
    room = _Room(
        np.asarray(stems_xy, float).reshape(-1, 2), np.asarray(stems_r, float), spec.clearance
    )
    x0, y0, x1, y1 = region.bounds
    out: dict[str, list] = {k: [] for k in ("kind", "decay", "base", "axis", "roll", "len", "d")}
    for compartment, span, target in jobs:
        if target <= 0:
            continue
        ds, ls = _sizes(target, span, spec, rng)
        order = np.argsort(-ds, kind="stable")  # the thickest find room first
        decay = rng.choice(DECAY_CLASSES, size=len(ds), p=np.asarray(spec.decay)) + 1
        for k in order:
            d, ln, dc = float(ds[k]), float(ls[k]), int(decay[k])
            if compartment == "lying":
                kind = "branch" if d < spec.branch_diameter else "log"
            else:
                kind = "snag" if compartment == "standing" else "stump"
            shape = shapes[(kind, dc)]
            r = d / 2 * shape.reach  # its footprint: root flare, ridges, a slumped width
            for _ in range(MAX_TRIES):
                c = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
                if compartment == "lying":
                    yaw = rng.uniform(0.0, 2 * math.pi)
                    h = np.array([math.cos(yaw), math.sin(yaw)]) * ln / 2
                    a, b = c - h, c + h
                else:
                    a = b = c
                ends = np.stack([a, b, c])
                if not region.contains(ends[:, 0], ends[:, 1]).all():
                    continue
                if room.free(a, b, r):
                    break
            else:
                raise UsdForestError(
                    f"deadwood: no room for a {kind} of {d:.2f} m x {ln:.1f} m clear of the "
                    f"stems and the other pieces after {MAX_TRIES} tries; lower "
                    "deadwood.volume or deadwood.clearance"
                )
            room.take(a, b, r)
            if compartment == "lying":
                za, zb = (
                    (float(ground.height(np.array([p[0]]), np.array([p[1]]))[0]) for p in (a, b))
                    if ground is not None
                    else (0.0, 0.0)
                )
                axis = np.array([b[0] - a[0], b[1] - a[1], zb - za])
                # a class-4 log lies on its flat side (the template's +Y, its thin axis, up)
                roll = -math.pi / 2 if dc == 4 else rng.uniform(0.0, 2 * math.pi)
                base = np.array([a[0], a[1], za])
            else:
                axis = np.array([0.0, 0.0, 1.0])
                roll = rng.uniform(0.0, 2 * math.pi)
                base = np.array([c[0], c[1], _foot(ground, c, r)])
            out["kind"].append(KINDS.index(kind))
            out["decay"].append(dc)
            out["base"].append(base)
            out["axis"].append(axis / exact.norm(axis))
            out["roll"].append(roll)
            out["len"].append(ln)
            out["d"].append(d)
    if not out["kind"]:
        z = np.zeros((0, 3))
        return Pieces(np.zeros(0, np.int8), np.zeros(0, np.int8), z, z, z, np.zeros(0), np.zeros(0))
    kind = np.array(out["kind"], np.int8)
    decay = np.array(out["decay"], np.int8)
    base = np.array(out["base"])
    axis = np.array(out["axis"])
    side = _frames(axis, np.array(out["roll"]))
    length, diameter = np.array(out["len"]), np.array(out["d"])
    lying = (kind == KINDS.index("log")) | (kind == KINDS.index("branch"))
    for key, shape in shapes.items():
        sel = np.flatnonzero(lying & (kind == KINDS.index(key[0])) & (decay == key[1]))
        if not sel.size:
            continue
        across = diameter[sel] / (2 * shape.radius)
        lo, hi = _lowest(shape, axis[sel], side[sel], length[sel], across)
        sink = np.array(SINK)[decay[sel] - 1] * (hi - lo)
        base[sel, 2] -= lo + sink  # its lowest point on the ground, then into the litter
    return Pieces(kind, decay, base, axis, side, length, diameter)


def _foot(ground, c: np.ndarray, r: float) -> float:
    """Where a standing piece's foot goes: the lowest ground under its footprint, 1 cm down
    (no sliver of air on a slope, no face on the ground's own plane)."""
    if ground is None:
        return -0.01
    x = c[0] + np.array([0.0, r, -r, 0.0, 0.0])
    y = c[1] + np.array([0.0, 0.0, 0.0, r, -r])
    return float(ground.height(x, y).min()) - 0.01

"""Stem form as the species grow it: taper, root flare, out-of-round sections, bark relief and
lean, and the trunk mesh an allometric tree's ``/Trunk`` references.

Pure numpy (no pxr). Each allometric species with a :data:`STEM_FORMS` entry gets, per tree
asset, a trunk of its own (:func:`stem_mesh`) in place of the shared conical template:

* **taper**: the diameter along the stem from a published taper curve, over bark:
  Laasasenaho's (1982) polynomial for Scots pine, Norway spruce and birch,
  ``d(l) / d(0.2 H) = sum b_i x**p_i`` with ``x = 1 - l / H`` (Communicationes Instituti
  Forestalis Fenniae 108), and Schmidt's (2001) Brink function for beech and oak (the
  TreeGrOSS/BWINPro forms of the Northwest German Forest Research Institute). Both are
  continuous through breast height and give the tree's diameter at 1.3 m exactly.
* **root flare**: Laasasenaho's curve swells below about 1 m by itself (d(0.1 m) / DBH 1.30 to
  1.45 for trees of 15-30 m, as Laasasenaho's (1975) stump diameter 2 + 1.25 DBH cm gives);
  Schmidt's hardwood curves are fitted above the stump (d(0.1 m) / DBH about 1.04), so beech
  and oak carry a flare ``1 + F (exp(-z / 0.3) - exp(-1.3 / 0.3))`` below breast height with F
  set to reach the stump ratio (a stated choice).
* **out-of-round sections**: an ellipse of the section's area whose ratio of largest to
  smallest diameter at 1.3 m is drawn per tree (1 + a gamma variate of mean ``ovality[0]`` and
  standard deviation ``ovality[1]``), larger towards the stump (Williamson 1975: out-of-round
  is greatest at stump height), its orientation the trunk's roll; and irregular beyond the
  ellipse by four lobes (orders 3-6, each a normal share of the radius of standard deviation
  :data:`LOBES`, growing towards the stump with the ovality): a stated choice.
* **bark**: a relief cut into the surface, a Voronoi network of fissures between plates on
  the unrolled stem (plates of ``cell`` metres; fissures ``fissure`` of a cell wide), as deep
  as ``depth`` of the single bark thickness where the bark is rough and ``upper`` above it.
  The bark thickness is the BWINPro double-bark function of the local diameter (Schmidt
  2001); the rough bark reaches ``zone`` of the tree's height (Scots pine's bark transition:
  Wilms et al. 2021, Forests 12: 1386; birch's fissured base).
* **lean**: each tree's stem leans from the vertical by a Rayleigh angle of scale ``lean``
  degrees (a stated choice: no stand's distribution was reachable here; most stems of
  managed stands lean less than 2-3 degrees), towards its crown's one-sided side where it
  has one (trunks lean towards light: Lamprecht et al. 2020, Remote Sensing 12: 3744) and
  down the slope where the ground slopes (:func:`usdforest.sites.local.downslope_yaw`).

A girth tape reads the hull of a section: :meth:`StemMesh.girth_dbh` gives it, perpendicular to the
stem, at any height of the mesh, and the tree's ``trees.csv`` DBH is that (the equivalent
circle: the tape's perimeter over pi).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.grow import exact

BREAST = 1.3
LAASASENAHO_POWERS = (1, 2, 3, 5, 8, 13, 21, 34)
FLARE_DECAY = 0.3  # m: the hardwoods' flare falls by e over this height
SECTIONS = 96  # vertices round a ring
LOBES = 0.012  # standard deviation of each lobe's share of the radius
DENSE_TOP = 2.5  # m: rings every DENSE_STEP up to here (the scanned and taped stem)
DENSE_STEP = 0.015
ZONE_STEP = 0.075  # within the rough bark above DENSE_TOP
UPPER_STEP = 0.25  # above it
SAPLING = 0.85  # a stem whose breast height is above this share of it is a sapling's
TIP = 0.98  # the last ring at this share of the stem; an apex vertex at its end


@dataclass(frozen=True)
class Bark:
    """A species' bark relief. ``double_bark`` (a, b, c): double bark thickness in mm of the
    over-bark diameter D in cm, ``a + b D + c D**2`` (BWINPro); ``depth`` and ``upper``: the
    fissures' depth as a share of the single bark thickness in the rough bark (up to
    ``zone`` of the tree's height, fading over a tenth of it) and above; ``cell``: a plate's
    width and height (m); ``fissure``: a fissure's width as a share of a plate's."""

    double_bark: tuple[float, float, float]
    depth: float
    zone: float
    upper: float = 0.0
    cell: tuple[float, float] = (0.05, 0.12)
    fissure: float = 0.3

    def thickness(self, diameter_m: np.ndarray) -> np.ndarray:
        """Single bark thickness (m) at over-bark diameters (m)."""
        d = np.asarray(diameter_m, dtype=float) * 100.0
        a, b, c = self.double_bark
        return np.maximum(a + b * d + c * d * d, 0.0) / 2000.0

    def share(self, z: np.ndarray, height: float) -> np.ndarray:
        """Fissure depth as a share of the bark thickness at heights ``z``."""
        top = self.zone * height
        fade = max(0.1 * height, 1e-6)
        t = np.clip((np.asarray(z, dtype=float) - top) / fade, 0.0, 1.0)
        return self.depth + (self.upper - self.depth) * t


@dataclass(frozen=True)
class StemForm:
    """A species' stem form (see the module docstring). ``taper`` is ``laasasenaho`` (eight
    coefficients) or ``brink`` (a0, a1, a2); ``flare`` the hardwoods' extra diameter share at
    the ground; ``ovality`` the mean and standard deviation of Dmax / Dmin - 1 at 1.3 m;
    ``lean`` the Rayleigh scale of the stem's lean in degrees."""

    taper: str
    coefficients: tuple[float, ...]
    bark: Bark
    ovality: tuple[float, float] = (0.045, 0.02)
    lean: float = 1.5
    flare: float = 0.0


# Laasasenaho (1982) via the coefficients of dmela/Laasasenaho; Schmidt (2001) via TreeGrOSS's
# TaperFunctionBySchmidt; double bark from BWINPro's barkreduce (beech, sessile oak, spruce,
# pine and birch groups)
STEM_FORMS: dict[str, StemForm] = {
    "scots-pine": StemForm(
        "laasasenaho",
        (2.1288, -0.63157, -1.6082, 2.4886, -2.4147, 2.3619, -1.7539, 1.0817),
        Bark((-2.13785, 0.91597, -0.00375), 0.8, 0.35, 0.1, (0.06, 0.15), 0.3),
    ),
    "norway-spruce": StemForm(
        "laasasenaho",
        (2.3366, -3.2684, 3.6513, -2.2608, 0.0, 2.1501, -2.7412, 1.8876),
        Bark((0.85149, 0.60934, -0.00228), 0.3, 1.0, 0.3, (0.03, 0.03), 0.2),
    ),
    "silver-birch": StemForm(
        "laasasenaho",
        (0.93838, 4.1060, -7.8517, 7.8993, -7.5018, 6.3863, -4.3918, 2.1604),
        Bark((1.63138, 0.78958, 0.0), 0.8, 0.1, 0.0, (0.05, 0.12), 0.3),
    ),
    "european-beech": StemForm(
        "brink",
        (0.694614, 0.086273, 0.135984),
        Bark((2.61029, 0.28522, 0.0), 0.0, 0.0, 0.0),
        ovality=(0.06, 0.025),
        flare=0.22,
    ),
    "sessile-oak": StemForm(
        "brink",
        (0.569877, 0.045065, 0.245294),
        Bark((14.31589, 0.72699, 0.0), 0.7, 0.6, 0.3, (0.035, 0.2), 0.25),
        ovality=(0.06, 0.025),
        flare=0.22,
    ),
}


def _laasasenaho(b: tuple[float, ...], x: np.ndarray) -> np.ndarray:
    return sum(bi * exact.power(x, p) for bi, p in zip(b, LAASASENAHO_POWERS, strict=True))


def _brink_radius(a: tuple[float, ...], h: np.ndarray, height: float, dbh_cm: float):
    """Schmidt's (2001) hardwood taper (TreeGrOSS): the radius (cm) at heights ``h`` (m) of a
    tree of ``height`` m and ``dbh_cm``; exactly DBH / 2 at 1.3 m."""
    a0, a1, a2 = a
    r = dbh_cm / 2.0
    i = a0 * r
    e1 = 1.0 - math.exp(a1 * (BREAST - height))
    e2 = 1.0 - math.exp(a2 * (BREAST - height))
    u = i / e2 + (r - i) * (1.0 - 1.0 / e1)
    v = (r - i) * math.exp(BREAST * a1) / e1
    w = i * math.exp(-a2 * height) / e2
    return u + v * exact.exp(-a1 * h) - w * exact.exp(a2 * h)


def relative_diameter(form: StemForm, z: np.ndarray, height: float, dbh: float) -> np.ndarray:
    """Diameter over bark at heights ``z`` (m) as a share of the diameter at 1.3 m, on a tree
    of ``height`` (m, above 1.3 / 0.9) and ``dbh`` (m); the flare included."""
    z = np.asarray(z, dtype=float)
    if form.taper == "laasasenaho":
        b = form.coefficients
        x = np.clip(1.0 - z / height, 0.0, 1.0)
        d = _laasasenaho(b, x) / float(_laasasenaho(b, np.array(1.0 - BREAST / height)))
    else:
        r = _brink_radius(form.coefficients, np.clip(z, 0.0, height), height, dbh * 100.0)
        d = np.maximum(r, 0.0) / (dbh * 50.0)
    if form.flare:
        e = exact.exp(-z / FLARE_DECAY) - math.exp(-BREAST / FLARE_DECAY)
        d = d * (1.0 + form.flare * np.maximum(e, 0.0))
    return np.maximum(d, 0.0)


def taper_from_base(form: StemForm, z: np.ndarray, height: float) -> np.ndarray:
    """Diameter at heights ``z`` as a share of the diameter at the ground (for the skeleton's
    trunk radii; a tree of 20 cm DBH stands in for the hardwoods' size-dependent shape)."""
    h = max(height, BREAST / 0.9)
    zs = np.asarray(z, dtype=float) * (h / height)
    return relative_diameter(form, zs, h, 0.2) / float(relative_diameter(form, 0.0, h, 0.2))


def ovality_draw(form: StemForm, rng: np.random.Generator) -> float:
    """A tree's ratio of largest to smallest diameter at 1.3 m."""
    m, s = form.ovality
    k, theta = (m / s) ** 2, s * s / m
    return 1.0 + min(float(rng.gamma(k, theta)), 0.25)


def lean_draw(form: StemForm, rng: np.random.Generator) -> tuple[float, float]:
    """A tree's lean from the vertical and its azimuth (degrees from +x)."""
    return float(rng.rayleigh(form.lean)), float(rng.uniform(0.0, 360.0))


def lean_matrix(angle_deg: float, azimuth_deg: float) -> np.ndarray:
    """The rotation (column vectors) tilting +Z by ``angle`` towards ``azimuth``."""
    t, a = math.radians(angle_deg), math.radians(azimuth_deg)
    axis = np.array([-math.sin(a), math.cos(a), 0.0])  # +Z tips towards (cos a, sin a)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1.0 - math.cos(t)) * exact.matmul(k, k)


@dataclass(frozen=True, eq=False)
class StemMesh:
    """A trunk as rings: ``z`` (k,) heights, ``xy`` (k, n, 2) ring vertices (the stem's frame:
    base centre at the origin, axis +Z), an apex at ``length``; ``depth`` (k, n) the bark
    relief cut at each vertex (m), ``ovality`` its Dmax / Dmin at 1.3 m on the asset."""

    z: np.ndarray
    xy: np.ndarray
    length: float
    depth: np.ndarray
    ovality: float

    def vertices(self) -> np.ndarray:
        _k, n = self.xy.shape[:2]
        ring = np.concatenate([self.xy, np.repeat(self.z[:, None, None], n, axis=1)], axis=2)
        return np.concatenate([ring.reshape(-1, 3), [[0.0, 0.0, 0.0], [0.0, 0.0, self.length]]])

    def faces(self) -> np.ndarray:
        k, n = self.xy.shape[:2]
        i, j = np.meshgrid(np.arange(k - 1), np.arange(n), indexing="ij")
        a = (i * n + j).ravel()
        b = (i * n + (j + 1) % n).ravel()
        side = np.stack([np.stack([a, b, b + n], 1), np.stack([a, b + n, a + n], 1)], 1)
        ring = np.arange(n)
        bottom, apex, last = k * n, k * n + 1, (k - 1) * n
        foot = np.stack([np.full(n, bottom), (ring + 1) % n, ring], 1)
        top = np.stack([np.full(n, apex), last + ring, last + (ring + 1) % n], 1)
        return np.concatenate([side.reshape(-1, 3), foot, top]).astype(np.int64)

    def section(self, z: float) -> np.ndarray:
        """The mesh's cut at height ``z``: the points where its edges cross it (vertical
        and diagonal edges between the rings about ``z``)."""
        i = int(np.clip(np.searchsorted(self.z, z, side="right") - 1, 0, len(self.z) - 2))
        t = (z - self.z[i]) / (self.z[i + 1] - self.z[i])
        lo, hi = self.xy[i], self.xy[i + 1]
        return np.concatenate([(1 - t) * lo + t * hi, (1 - t) * lo + t * np.roll(hi, -1, 0)])

    def girth_dbh(self, z: np.ndarray) -> np.ndarray:
        """Girth-tape diameters (the section's hull perimeter over pi) at heights ``z`` of
        the stem's frame; 0 above its last ring."""
        z = np.atleast_1d(np.asarray(z, dtype=float))
        out = np.zeros(len(z))
        uniq, inv = np.unique(z, return_inverse=True)
        vals = np.array(
            [hull_perimeter(self.section(h)) / math.pi if h < self.z[-1] else 0.0 for h in uniq]
        )
        out[:] = vals[inv.reshape(-1)] if len(uniq) else 0.0
        return out


def hull_perimeter(xy: np.ndarray) -> float:
    """Perimeter of the convex hull of 2-D points (0 for fewer than three)."""
    from scipy.spatial import ConvexHull, QhullError

    if len(xy) < 3:
        return 0.0
    try:
        p = xy[ConvexHull(xy).vertices]
    except QhullError:  # a degenerate section
        return 0.0
    return float(np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1).sum())


def sections(dbh: float) -> int:
    """Vertices round a ring: about 1.2 cm apart on the breast-height girth, a multiple of
    8 from 24 to :data:`SECTIONS`."""
    return int(np.clip(8 * round(math.pi * dbh / 0.012 / 8), 24, SECTIONS))


def _rings(length: float, rough_top: float, dbh: float) -> np.ndarray:
    """Ring heights: every 1.5 cm up to 2.5 m on a stem of 15 cm and more (coarser on
    thinner ones, to 5 cm), 7.5 cm in the rough bark above, 25 cm above it."""
    top = TIP * length
    step = min(DENSE_STEP * max(1.0, 0.15 / max(dbh, 1e-3)), 0.05, length / 30.0)
    dense = np.arange(0.0, min(DENSE_TOP, top), step)
    z0 = dense[-1] + step if len(dense) else 0.0
    zone = np.arange(z0, min(rough_top, top), ZONE_STEP)
    z1 = zone[-1] + ZONE_STEP if len(zone) else z0
    upper = np.arange(z1, top, UPPER_STEP)
    return np.unique(np.concatenate([dense, zone, upper, [top]]))


def _relief(
    bark: Bark, u: np.ndarray, z: np.ndarray, circumference: float, rng: np.random.Generator
) -> np.ndarray:
    """Fissure profile in 0..1 (1: a fissure's floor) at unrolled coordinates ``u`` (m
    round the stem, periodic over ``circumference``) and ``z`` (m): Voronoi plates, the
    fissures along their borders."""
    cw, ch = bark.cell
    cols = max(3, round(circumference / cw))
    cw = circumference / cols
    rows = math.ceil(float(z.max()) / ch) + 2
    seeds = rng.uniform(0.0, 1.0, size=(rows + 2, cols, 2))  # rows -1 .. rows
    gu, gz = u / cw, z / ch
    iu, iz = np.floor(gu).astype(np.int64), np.floor(gz).astype(np.int64)
    f1 = np.full(u.shape, np.inf)
    f2 = np.full(u.shape, np.inf)
    for du in (-1, 0, 1):
        for dz in (-1, 0, 1):
            cu, cz = iu + du, iz + dz
            s = seeds[np.clip(cz + 1, 0, rows + 1), cu % cols]
            d = np.sqrt((cu + s[..., 0] - gu) ** 2 + (cz + s[..., 1] - gz) ** 2)
            f2 = np.where(d < f1, f1, np.minimum(f2, d))
            f1 = np.minimum(f1, d)
    edge = 0.5 * (f2 - f1)  # about the distance to the nearest border, in cells
    t = np.clip(1.0 - edge / (0.5 * bark.fissure), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)  # smooth walls, a flat floor


def stem_mesh(
    form: StemForm,
    length: float,
    height: float,
    breast: float,
    dbh: float,
    ovality: float,
    rng: np.random.Generator,
) -> StemMesh:
    """A trunk ``length`` m long for a tree ``height`` m tall whose girth tape reads ``dbh``
    (m) at ``breast`` (m up the stem: 1.3 m, or where 1.3 m falls on an asset its instances
    scale by 1.3 / ``breast``), with the section ovality ``ovality`` at breast height and the
    species' taper, flare and bark (see the module docstring), all in the scaled tree's
    terms."""
    s = BREAST / breast  # the scale the asset is drawn for
    h = max(height, length)
    z = _rings(length, (form.bark.zone + 0.1) * h, dbh * BREAST / breast)
    sapling = breast >= SAPLING * length
    if sapling:  # no breast height on the stem: ``dbh`` is its diameter at the ground
        share = taper_from_base(form, z, length)
        s = 1.0
    else:
        share = relative_diameter(form, z * s, h * s, dbh * s)
    d_world = dbh * s
    ang = np.linspace(0.0, 2 * math.pi, sections(dbh * s), endpoint=False)
    cos = np.array([math.cos(a) for a in ang])
    sin = np.array([math.sin(a) for a in ang])
    # out of round: Dmax / Dmin of e at 1.3 m, (e - 1) doubled towards the stump
    e = 1.0 + (ovality - 1.0) * (1.0 + exact.exp(-z * s / 0.5)) / (1.0 + math.exp(-2.6))
    a, b = np.sqrt(e)[:, None], 1.0 / np.sqrt(e)[:, None]
    rho = 1.0 / np.sqrt((cos[None] / a) ** 2 + (sin[None] / b) ** 2)
    # and irregular beyond the ellipse: lobes of orders 3 to 6, about 1.7 % of the radius (RMS)
    amp = rng.normal(0.0, LOBES, size=4)
    phase = rng.uniform(0.0, 2 * math.pi, size=4)
    lobes = sum(
        amp[j] * np.array([math.cos((j + 3) * t + phase[j]) for t in ang]) for j in range(4)
    )
    rho = rho * (1.0 + ((e - 1.0) / max(ovality - 1.0, 1e-9))[:, None] * lobes[None])
    outer = 0.5 * dbh * share[:, None] * rho
    thick = form.bark.thickness(share * d_world) / s * form.bark.share(z, h)
    if float(thick.max(initial=0.0)) > 0:
        c_ref = math.pi * dbh
        uu = np.broadcast_to(ang[None] / (2 * math.pi) * c_ref, outer.shape)
        zz = np.broadcast_to(z[:, None], outer.shape)
        depth = thick[:, None] * _relief(form.bark, uu, zz, c_ref, rng)
    else:
        depth = np.zeros_like(outer)
    r = outer - depth
    xy = np.stack([r * cos[None], r * sin[None]], axis=2)
    mesh = StemMesh(z, xy, length, depth, ovality)
    if not sapling:  # the tape at breast height reads dbh exactly
        k = dbh / float(mesh.girth_dbh(np.array([breast]))[0])
        mesh = StemMesh(z, xy * k, length, depth * k, ovality)
    return mesh

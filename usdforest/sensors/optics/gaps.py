"""Canopy cover and gap fraction as a sensor measures them: parallel rays through the composed
forest, and the clumping they imply.

A gap is a ray from above the canopy that meets no leaf and no wood before the ground (or
meets nothing). ``P(theta)``, the gap fraction at zenith angle ``theta``, is the share of
parallel rays at that angle that pass: at nadir on a grid of ``NADIR_SPACING`` over the
plot (canopy cover is ``1 - P(0)``, what a camera straight down or an airborne lidar's first
returns see), off nadir from four azimuths on a grid of ``OBLIQUE_SPACING`` (what a
hemispherical photo or an LAI-2200 reads in a ring), each ray entering the canopy and
reaching the ground inside the plot (the plot is cut on the side the rays come from by
``tan(theta)`` times the canopy's height; an angle that leaves no plot gives no figure).

With the stand's one-sided leaf area index ``L`` and its leaves' projection function
``G(theta)`` (the mean projected area of unit leaf area towards ``theta``, over azimuths:
0.5 for leaves at random angles), leaves at random places would let through
``P_random = exp(-G L / cos(theta))`` (Beer-Lambert); the effective clumping index is
``Omega = ln P / ln P_random`` (Chen et al. 2005, Remote Sensing of Environment 97:447):
1 for leaves at random, below 1 where they are clumped (crowns, shoots, gaps between trees).
Wood that stops rays counts as foliage in ``P``, so it lowers ``Omega`` a little.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from usdforest.sensors.scene.scenetypes import CLASS_ID, Scene

if TYPE_CHECKING:
    from pxr import Usd

ZENITHS = (0.0, 30.0, 45.0, 60.0)  # degrees: nadir, and the rings instruments read
AZIMUTHS = (0.0, 90.0, 180.0, 270.0)
NADIR_SPACING = 0.05  # m
OBLIQUE_SPACING = 0.30  # m: each ring is still 100,000s of rays over a hectare
SAMPLE_LEAVES = 400  # a prototype's leaves G is measured on (G to about 0.005 over a stand)
Bounds = tuple[float, float, float, float]
# hits that are not canopy: the ground and what lies or grows on it
BELOW_CANOPY = (CLASS_ID["ground"], CLASS_ID["dead_wood"], CLASS_ID["ground_vegetation"])
UNDERSTOREY = "/Understorey/"  # prims under a forest's understorey layer (usd.undergrowth)
ANGLE_BIN = 10.0  # degrees: the leaf inclination distribution's classes, 0-10 ... 80-90
ANGLE_BINS = 9


@dataclass(frozen=True)
class Gaps:
    """Gap fractions ``gap`` (None where the plot is too small for the angle) at zenith
    angles ``zenith`` (degrees), from ``rays`` rays each."""

    zenith: tuple[float, ...]
    gap: tuple[float | None, ...]
    rays: tuple[int, ...]

    @property
    def cover(self) -> float | None:
        """Canopy cover by rays: the share of nadir rays that meet living leaf or wood."""
        at = self.zenith.index(0.0) if 0.0 in self.zenith else None
        g = None if at is None else self.gap[at]
        return None if g is None else 1.0 - g


def _grid(bounds: Bounds, spacing: float) -> np.ndarray:
    """Cell centres (n, 2) of a grid of ``spacing`` over ``bounds``."""
    x0, y0, x1, y1 = bounds
    gx = np.arange(x0 + spacing / 2, x1, spacing)
    gy = np.arange(y0 + spacing / 2, y1, spacing)
    xx, yy = np.meshgrid(gx, gy)
    return np.column_stack([xx.ravel(), yy.ravel()])


def gap_fractions(
    scene: Scene,
    caster,
    bounds: Bounds,
    zeniths: tuple[float, ...] = ZENITHS,
    *,
    nadir_spacing: float = NADIR_SPACING,
    oblique_spacing: float = OBLIQUE_SPACING,
    progress: Callable[[str, int, int], None] | None = None,
) -> Gaps:
    """``P(theta)`` of ``scene`` (cast with ``caster``, a
    :class:`~usdforest.sensors.cast.raycast.SceneCaster` of it) over the plot ``bounds`` (x0, y0,
    x1, y1 in the scene's metres; see the module docstring)."""
    top = float(scene.bounds[1, 2]) + 1.0
    depth = top - float(scene.bounds[0, 2])
    x0, y0, x1, y1 = bounds
    tasks = [(z, a) for z in zeniths for a in (AZIMUTHS if z > 0 else (0.0,))]
    passed: dict[float, int] = dict.fromkeys(zeniths, 0)
    cast: dict[float, int] = dict.fromkeys(zeniths, 0)
    for k, (zenith, azimuth) in enumerate(tasks):
        if progress is not None:
            progress("casting gap rays", k, len(tasks))
        t, p = math.radians(zenith), math.radians(azimuth)
        d = np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), -math.cos(t)])
        reach = math.tan(t) * depth  # how far a ray runs sideways from above to the ground
        # the plot less the side the rays come from: they enter and land inside it
        box = (
            x0 + max(reach * d[0], 0.0) if d[0] > 1e-12 else x0,
            y0 + max(reach * d[1], 0.0) if d[1] > 1e-12 else y0,
            x1 + min(reach * d[0], 0.0) if d[0] < -1e-12 else x1,
            y1 + min(reach * d[1], 0.0) if d[1] < -1e-12 else y1,
        )
        if box[2] <= box[0] or box[3] <= box[1]:
            continue
        xy = _grid(box, nadir_spacing if zenith == 0 else oblique_spacing)
        # rays start above the canopy, placed so that each lands at its grid point's x, y
        origin = np.column_stack([xy - d[:2] * (depth / max(-d[2], 1e-9)), np.full(len(xy), top)])
        gaps = 0
        under = understorey_paths(scene)
        for start in range(0, len(xy), 1 << 20):
            o = origin[start : start + (1 << 20)]
            h = caster.first_hit(o, np.broadcast_to(d, o.shape))
            # a gap is a ray through the trees' canopy: to the ground, to dead wood (logs,
            # stumps and snags are not canopy; a snag's side intercepts a few rays at most),
            # to the ground vegetation, or to the understorey's shrubs and young trees
            below = np.isin(h.cls, BELOW_CANOPY) | under[h.path]
            gaps += int(np.count_nonzero(~h.hit | below))
        passed[zenith] += gaps
        cast[zenith] += len(xy)
    if progress is not None:
        progress("casting gap rays", len(tasks), len(tasks))
    return Gaps(
        tuple(zeniths),
        tuple(passed[z] / cast[z] if cast[z] else None for z in zeniths),
        tuple(cast[z] for z in zeniths),
    )


def _area_vectors(tri: np.ndarray) -> np.ndarray:
    """Area vectors (n, 3) of triangles (n, 3, 3)."""
    return 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def _closed(tri: np.ndarray) -> bool:
    """Whether the triangles close a surface (every edge shared by two): a shoot's mesh,
    whose one-sided area is half its surface."""
    if not len(tri):
        return False
    _, ids = np.unique(np.round(tri.reshape(-1, 3), 6), axis=0, return_inverse=True)
    ids = ids.reshape(-1, 3)
    edges = np.sort(np.concatenate([ids[:, [0, 1]], ids[:, [1, 2]], ids[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(count == 2))


def _directions(zeniths: tuple[float, ...]) -> np.ndarray:
    """(zeniths, 24, 3): unit directions down at each zenith angle, every 15 degrees of
    azimuth."""
    phi = np.radians(np.arange(0, 360, 15.0))
    t = np.radians(np.asarray(zeniths, dtype=float))[:, None]
    return np.stack(
        [np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), -np.cos(t) * np.ones_like(phi)], -1
    )


def _area_sums(a: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Per zenith angle, the azimuth-mean of ``sum |a . d|`` over area vectors ``a``; then
    the areas by leaf inclination (the normal's angle from the vertical) in ``ANGLE_BINS``,
    and the area-weighted sum of the inclinations (degrees)."""
    # each distinct direction projected once: at nadir the 24 azimuths are one direction
    flat, back = np.unique(dirs.reshape(-1, 3) + 0.0, axis=0, return_inverse=True)
    g = np.abs(a @ flat.T).sum(axis=0)[back.ravel()].reshape(dirs.shape[:2]).mean(axis=1)
    area = np.linalg.norm(a, axis=1)
    angle = np.degrees(np.arccos(np.clip(np.abs(a[:, 2]) / np.maximum(area, 1e-300), 0, 1)))
    bins = np.bincount(
        np.minimum((angle // ANGLE_BIN).astype(np.int64), ANGLE_BINS - 1),
        weights=area,
        minlength=ANGLE_BINS,
    )
    return np.concatenate([g, bins, [float(angle @ area)]])


def _leaf_sums(shapes, li, rows, dirs) -> tuple[np.ndarray, float]:
    """Projected (per zenith) and one-sided areas of leaf instances ``rows`` of ``li``: each
    shape's area vectors moved by its instances' cofactor matrices (an area vector ``a`` of a
    shape under ``p -> p M`` becomes ``det(M) a M^-T``), a closed shape's halved (the sums
    of :func:`_area_sums`)."""
    num, den = np.zeros(dirs.shape[0] + ANGLE_BINS + 1), 0.0
    for s in np.unique(li.shape[rows]):
        at = rows[li.shape[rows] == s]
        tri = np.asarray(shapes[s].triangles, dtype=float)
        a = _area_vectors(tri)
        half = 0.5 if _closed(tri) else 1.0
        step = max(1, (1 << 20) // max(len(a), 1))  # about a million area vectors at once
        for start in range(0, len(at), step):
            m = li.matrix[at[start : start + step], :3, :3]
            cof = np.linalg.det(m)[:, None, None] * np.linalg.inv(m).transpose(0, 2, 1)
            moved = np.einsum("tj,njk->ntk", a, cof).reshape(-1, 3)
            num += half * _area_sums(moved, dirs)
            den += half * float(np.linalg.norm(moved, axis=1).sum())
    return num, den


def understorey_paths(scene: Scene) -> np.ndarray:
    """``bool[len(scene.paths) + 1]``: which prim paths are the understorey's shrubs and young
    trees (the last entry, for path -1 of a miss, is False)."""
    return np.array([UNDERSTOREY in p for p in scene.paths] + [False], dtype=bool)


def leaf_projection(scene: Scene, zeniths: tuple[float, ...] = ZENITHS) -> np.ndarray:
    """``G(theta)`` of the scene's leaves at each of ``zeniths`` (degrees): the projected
    area of their triangles towards ``theta``, averaged over azimuths, over their one-sided
    area (a closed shoot's surface counted half). Measured on up to ``SAMPLE_LEAVES`` leaves
    a tree prototype, each prototype weighted by its instances' scale squared (a tree
    instance is turned about z and scaled, which leaves its G as it is)."""
    return leaf_angles(scene, zeniths)[0]


def leaf_angles(
    scene: Scene, zeniths: tuple[float, ...] = ZENITHS
) -> tuple[np.ndarray, np.ndarray, float]:
    """``G(theta)`` (see :func:`leaf_projection`), the leaf inclination distribution (the
    share of the one-sided leaf area whose normal leans 0-10, ..., 80-90 degrees from the
    vertical) and the area-weighted mean leaf inclination (degrees), from the same sample."""
    dirs = _directions(zeniths)
    rng = np.random.default_rng(0)
    a = _area_vectors(scene.triangles[scene.cls == CLASS_ID["leaf"]].astype(float))
    num = _area_sums(a, dirs) if len(a) else np.zeros(len(zeniths) + ANGLE_BINS + 1)
    den = float(np.linalg.norm(a, axis=1).sum())
    li = scene.leaf_instances
    if len(li):
        n, d = _leaf_sums(scene.shapes, li, np.arange(len(li)), dirs)
        num, den = num + n, den + d
    inst = scene.instances
    under = understorey_paths(scene)
    scale2 = np.abs(np.linalg.det(inst.matrix[:, :3, :3])) ** (2 / 3) if len(inst) else None
    for k, proto in enumerate(scene.protos):
        li = proto.leaf_instances
        # the trees' leaves only, not the understorey's
        if len(proto.path) and under[proto.path].any():
            continue
        weight = float(np.sum(scale2[inst.proto == k])) if scale2 is not None else 0.0
        if weight == 0 or not len(li):
            continue
        rows = np.arange(len(li))
        if len(rows) > SAMPLE_LEAVES:
            rows = np.sort(rng.choice(rows, SAMPLE_LEAVES, replace=False))
        share = len(li) / len(rows)  # the sample stands for all the prototype's leaves
        n, d = _leaf_sums(scene.shapes, li, rows, dirs)
        num, den = num + weight * share * n, den + weight * share * d
    if not den > 0:
        return np.full(len(zeniths), np.nan), np.full(ANGLE_BINS, np.nan), math.nan
    z = len(zeniths)
    return num[:z] / den, num[z : z + ANGLE_BINS] / den, float(num[-1] / den)


def clumping(gap: float | None, lai: float, g: float, zenith: float) -> float | None:
    """The effective clumping index ``ln P / ln P_random`` (see the module docstring)."""
    if gap is None or not lai > 0 or not g > 0 or not 0 < gap < 1:
        return None
    return math.log(gap) / (-g * lai / math.cos(math.radians(zenith)))


def canopy_figures(
    stage_path,
    bounds: Bounds,
    lai: float,
    *,
    zeniths: tuple[float, ...] = ZENITHS,
    progress: Callable[[str, int, int], None] | None = None,
    opened: Usd.Stage | None = None,
) -> dict:
    """What ``usdforest stats`` reports of a forest's canopy, measured by rays over the plot
    ``bounds`` with the stand's one-sided ``lai``: ``canopy_cover`` (1 - P(0)), the leaves'
    mean inclination and inclination distribution (:func:`leaf_angles`), and per zenith
    angle the gap fraction, ``G`` and the effective clumping index (keys: degrees).
    ``opened``: the stage already opened as :func:`usdforest.usd.layers.open_stage` opens it
    with ``sound`` and ``full`` (not opened again)."""
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.scene.extraction import extract_scene

    scene = extract_scene(stage_path, reflectors=False, progress=progress, opened=opened)
    caster = SceneCaster(scene, progress=progress)
    gaps = gap_fractions(scene, caster, bounds, zeniths, progress=progress)
    g, lid, mean_angle = leaf_angles(scene, zeniths)
    key = [f"{z:g}" for z in zeniths]
    return {
        "canopy_cover": gaps.cover,
        "mean_leaf_angle_deg": mean_angle,
        "leaf_angle_distribution": {
            f"{k * ANGLE_BIN:g}-{(k + 1) * ANGLE_BIN:g}": float(v) for k, v in enumerate(lid)
        },
        "gap_fraction": dict(zip(key, gaps.gap, strict=True)),
        "leaf_projection_g": {k: float(v) for k, v in zip(key, g, strict=True)},
        "clumping_index": {
            k: clumping(p, lai, float(v), z)
            for k, p, v, z in zip(key, gaps.gap, g, zeniths, strict=True)
        },
        "gap_rays": dict(zip(key, gaps.rays, strict=True)),
    }

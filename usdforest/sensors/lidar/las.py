"""Lidar points as LAS 1.4 (point format 6, as ASPRS defines it): the returns of a flight or
survey with their GPS time, scan angle, ASPRS class by height above the ground and the
project's own fields as extra dimensions; and what those fields are computed from (the
ground under each point, the stage's georeference)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from usdforest.atomic import atomic_path
from usdforest.errors import UsdForestError
from usdforest.sensors.scene.scenetypes import CLASSES, Scene

# ASPRS LAS classes for our semantic classes: unclassified, ground, and vegetation (trunk,
# branch, leaf, ground vegetation) by its height above the ground: low (3) under 2 m, medium
# (4) under 5 m, high (5) above; ASPRS sets no heights, these are the LAStools lasheight
# README's "-classify_between 0.5 2 3 -classify_between 2 5 4" (and high above 5 m). Dead
# wood is unclassified (1); our own class stays in the extra dimension "usdforest_class".
ASPRS = {"unknown": 1, "ground": 2, "dead_wood": 1}
VEGETATION = ("trunk", "branch", "leaf", "ground_vegetation")
VEGETATION_HEIGHTS = (2.0, 5.0)  # m: low below the first, medium below the second, high above


@dataclass(frozen=True, eq=False)
class FlightReturns:
    """Lidar returns of a whole flight."""

    points: np.ndarray
    gps_time: np.ndarray
    range: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    path: np.ndarray
    paths: tuple[str, ...]
    n_rays: int
    sweeps: int
    ring: np.ndarray  # the laser (channel) of each return, 0 the lowest
    azimuth: np.ndarray  # its azimuth from the sensor's forward axis, degrees in [-180, 180)
    intensity: np.ndarray  # uint16, see usdforest.sensors.lidar.scanners.counts
    return_number: np.ndarray  # uint8, 1-based, by range among its pulse's returns
    number_of_returns: np.ndarray  # uint8, of its pulse
    scan_angle: np.ndarray  # ASPRS: from straight down, positive to the right (see scan_angles)
    height: np.ndarray  # above the ground under it, metres (see ground_height)
    system: str = "OTHER"  # the sensor's name (LAS system identifier)

    def __len__(self) -> int:
        return len(self.range)

    @staticmethod
    def concat(parts: list[FlightReturns]) -> FlightReturns:
        """``parts`` (one sensor's, at least one) as one: their points in order, their rays
        and sweeps summed."""
        arrays = {
            f.name: np.concatenate([getattr(p, f.name) for p in parts])
            for f in fields(FlightReturns)
            if isinstance(getattr(parts[0], f.name), np.ndarray)
        }
        return replace(
            parts[0], **arrays, n_rays=sum(p.n_rays for p in parts),
            sweeps=sum(p.sweeps for p in parts),
        )  # fmt: skip


def scan_angles(dirs: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """LAS 1.4's scan angle of rays along ``dirs`` (n, 3) from a platform heading along
    ``forward`` (n, 3), degrees in (-180, 180]: the ray's angle from straight down (the data's
    vertical) in the plane across the track, positive counter-clockwise seen from behind the
    sensor facing along the track (towards its right), so a ray level to the right is +90."""
    along = np.asarray(forward, dtype=float) * [1.0, 1.0, 0.0]
    flat = np.linalg.norm(along, axis=1) < 1e-9  # heading straight up or down: x is along
    along[flat] = [1.0, 0.0, 0.0]
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    right = np.column_stack([along[:, 1], -along[:, 0], np.zeros(len(along))])  # along x up
    return np.degrees(np.arctan2(np.sum(dirs * right, axis=1), -dirs[:, 2]))


def ground_height(scene: Scene, xy: np.ndarray) -> np.ndarray:
    """The height of the scene's ground (its ``ground`` class triangles) under each of ``xy``
    (n, 2): linear between the ground's vertices, the nearest vertex's beyond them, 0 where
    the scene has no ground."""
    tri = scene.triangles[scene.cls == CLASSES.index("ground")]
    if not len(tri) or not len(xy):
        return np.zeros(len(xy))
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    v = np.unique(np.asarray(tri, dtype=float).reshape(-1, 3), axis=0)
    if len(v) < 3:
        return np.full(len(xy), float(v[:, 2].mean()))
    try:
        z = LinearNDInterpolator(v[:, :2], v[:, 2])(xy)
    except Exception:  # the ground's vertices on a line (QhullError): no plane to interpolate
        z = np.full(len(xy), np.nan)
    far = np.isnan(z)
    if far.any():
        z[far] = NearestNDInterpolator(v[:, :2], v[:, 2])(xy[far])
    return z


def asprs_classes(cls: np.ndarray, height: np.ndarray) -> np.ndarray:
    """ASPRS classification of returns of our classes ``cls`` at ``height`` above the ground:
    vegetation low (3), medium (4) or high (5) by :data:`VEGETATION_HEIGHTS`, the others by
    :data:`ASPRS`."""
    lut = np.array([ASPRS.get(c, 0) for c in CLASSES], dtype=np.uint8)
    out = lut[cls]
    veg = np.isin(cls, [CLASSES.index(c) for c in VEGETATION])
    low, mid = VEGETATION_HEIGHTS
    out[veg] = np.where(height[veg] < low, 3, np.where(height[veg] < mid, 4, 5))
    return out


# The tree-segmentation benchmarks' classes (FOR-instance, NIBIO; read by TreeLearn,
# ForestFormer3D and others): 0 unclassified, 1 low vegetation, 2 terrain, 3 out-points,
# 4 stem, 5 live branches, 6 woody branches. A tree's trunk is its stem, its branches woody
# branches and its leaves or needles the live branches that carry them; everything alive
# under the trees that is no tree (ground vegetation, shrubs, regeneration) and dead wood on
# the floor are low vegetation; a simulation has no out-points.
FOR_INSTANCE = {"unknown": 0, "ground": 2, "ground_vegetation": 1, "dead_wood": 1}
FOR_INSTANCE_TREE = {"trunk": 4, "branch": 6, "leaf": 5}
LABELS = ("asprs", "for-instance")


def for_instance_classes(cls: np.ndarray, tree: np.ndarray) -> np.ndarray:
    """FOR-instance classification of returns of our classes ``cls`` on trees ``tree``
    (-1: on none): a tree's trunk, branches and leaves 4, 6 and 5, the same classes on no
    tree (shrubs, regeneration) low vegetation (1), the rest by :data:`FOR_INSTANCE`."""
    on_tree = np.asarray(tree) >= 0
    lut = np.array([FOR_INSTANCE.get(c, 1) for c in CLASSES], dtype=np.uint8)
    tree_lut = np.array([FOR_INSTANCE_TREE.get(c, FOR_INSTANCE.get(c, 1)) for c in CLASSES],
                        dtype=np.uint8)  # fmt: skip
    cls = np.asarray(cls, dtype=np.int64)
    return np.where(on_tree, tree_lut[cls], lut[cls]).astype(np.uint8)


def map_shift(origin: np.ndarray | None) -> np.ndarray:
    """What the stage's points are moved by into the map frame the point files share: the
    stage origin's map position ``origin`` (x, y; None: none) and no change in z."""
    shift = np.zeros(3)
    if origin is not None:
        shift[:2] = origin
    return shift


def benchmark_tree_ids(tree: np.ndarray) -> np.ndarray:
    """The tree-segmentation benchmarks' instance label (``treeID``, int32) of returns on
    trees ``tree`` (-1: on none): ``tree + 1``, 0 on no tree, so ``treeID - 1`` is the tree's
    ``id`` in ``trees.csv``."""
    tree = np.asarray(tree)
    return np.where(tree >= 0, tree.astype(np.int64) + 1, 0).astype(np.int32)


def stage_georeference(stage: str | Path) -> tuple[str | None, np.ndarray]:
    """The CRS a forest's root layer records (``customLayerData`` ``crs``, e.g. "EPSG:32633")
    and where the stage's origin is in it (``crsOrigin``, x and y); ``(None, 0)`` for a stage
    that is not georeferenced."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(stage))
    data = dict(layer.customLayerData) if layer is not None else {}
    crs = data.get("crs")
    origin = np.array(list(data.get("crsOrigin", (0.0, 0.0))), dtype=float)
    return (str(crs) if crs else None), origin


def gps_times(t: np.ndarray, start_time: str | None) -> np.ndarray:
    """LAS GPS times of path times ``t`` (seconds): Adjusted Standard GPS Time with the path's
    t = 0 at ``start_time`` (ISO 8601 UTC, e.g. ``2026-06-21T10:00:00Z``); without one, the
    seconds themselves, as GPS week time (the week starting at t = 0)."""
    if start_time is None:
        return np.asarray(t, dtype=float)
    from usdforest.sensors.lidar.gpstime import ADJUSTMENT, gps_seconds, parse_utc

    return gps_seconds(parse_utc(start_time)) - ADJUSTMENT + np.asarray(t, dtype=float)


def write_las(
    r: FlightReturns,
    out: Path,
    *,
    crs: str | None = None,
    origin: np.ndarray | None = None,
    flight_line: int = 1,
    start_time: str | None = None,
    labels: str = "asprs",
    point_source: np.ndarray | None = None,
) -> Path:
    """LAS 1.4, point format 6, as the ASPRS specification defines it and point-cloud tools
    read it (checked with laspy): x, y, z (0.1 mm; in ``crs`` with the stage origin's map
    position ``origin`` added to x and y); GPS time (Adjusted Standard GPS Time from
    ``start_time``, see :func:`gps_times`; without one the path's seconds as GPS week time);
    return number and number of returns of each pulse; intensity (the lidar equation, see
    :func:`usdforest.sensors.lidar.scanners.counts`); scan angle (:func:`scan_angles`: from straight
    down, positive to the right); ASPRS classification (:func:`asprs_classes`: vegetation
    low, medium or high by its height above the ground); point source and file source =
    ``flight_line``; system identifier the sensor's model, generating software "usdforest
    <version>"; and the extra dimensions ``ring`` (uint16, the laser: 0 the lowest),
    ``azimuth`` (float32, degrees from the platform's forward axis), ``height`` (float32, m
    above the ground), ``tree_id`` (int32, -1 off any tree), ``usdforest_class`` (0
    unknown, 1 trunk, 2 branch, 3 leaf, 4 ground, 5 dead wood, 6 ground vegetation) and
    ``treeID`` (int32, the tree-segmentation benchmarks' instance label: ``tree_id + 1``, 0
    off any tree, so ``treeID - 1`` is the tree's ``id`` in ``trees.csv``). ``labels =
    "for-instance"`` writes the benchmarks' classification instead of ASPRS's
    (:func:`for_instance_classes`). With a ``crs`` the global encoding's WKT bit is set and a
    WKT CRS record written (pyproj). A name ending ``.laz`` is written compressed (laspy's
    lazrs backend, ``usdforest[laz]``). ``point_source``: each point's source instead of
    ``flight_line`` (a merged survey's stations or lines)."""
    import laspy

    if labels not in LABELS:
        raise UsdForestError(f"labels: {labels!r} is not one of {', '.join(LABELS)}")
    from usdforest import __version__

    gps = gps_times(r.gps_time, start_time)  # checks start_time before any work
    shift = map_shift(origin)
    points = r.points + shift
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(points.min(axis=0)) if len(r) else shift
    header.system_identifier = r.system[:32]
    header.generating_software = f"usdforest {__version__}"[:32]
    header.file_source_id = flight_line
    if start_time is not None:
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    if crs is not None:
        try:
            import pyproj
        except ImportError:
            raise UsdForestError(
                f"{out}: a georeferenced flight ({crs}) needs pyproj for the LAS CRS record: "
                "pip install 'usdforest[geo]'"
            ) from None
        header.add_crs(pyproj.CRS.from_user_input(crs))
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams(name="ring", type=np.uint16),
            laspy.ExtraBytesParams(name="azimuth", type=np.float32),
            laspy.ExtraBytesParams(name="height", type=np.float32),
            laspy.ExtraBytesParams(name="tree_id", type=np.int32),
            laspy.ExtraBytesParams(name="usdforest_class", type=np.uint8),
            laspy.ExtraBytesParams(
                name="treeID", type=np.int32, description="tree instance, 0: none"
            ),
        ]
    )
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.gps_time = gps
    las.return_number = r.return_number
    las.number_of_returns = r.number_of_returns
    las.intensity = r.intensity
    las.scan_angle = np.round(r.scan_angle / 0.006).astype(np.int16)  # 0.006 degree units
    las.point_source_id = (
        np.full(len(r), flight_line, np.uint16)
        if point_source is None
        else np.asarray(point_source, np.uint16)
    )
    las.classification = (
        asprs_classes(r.cls, r.height) if labels == "asprs" else for_instance_classes(r.cls, r.tree)
    )
    las.ring = r.ring
    las.azimuth = r.azimuth.astype(np.float32)
    las.height = r.height.astype(np.float32)
    las.tree_id = r.tree
    las.usdforest_class = r.cls
    las.treeID = benchmark_tree_ids(r.tree)
    compress = Path(out).suffix.lower() == ".laz"
    backend = None
    if compress:
        if laspy.LazBackend.Lazrs not in laspy.LazBackend.detect_available():
            raise UsdForestError(
                f"{out}: LAZ needs laspy's lazrs backend: pip install 'usdforest[laz]'"
            )
        backend = laspy.LazBackend.Lazrs  # one thread: the same bytes on every machine
    with atomic_path(out) as tmp:
        las.write(str(tmp), do_compress=compress, laz_backend=backend)
    return out

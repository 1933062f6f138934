"""Inhomogeneous Poisson processes on planar regions: intensities, Lewis-Shedler thinning, marks.

Intensities are in trees per square metre. Thinning (Lewis and Shedler, 1979): draw a
homogeneous Poisson process of rate lambda* on the region's bounding box, keep the points
inside the region, and keep each point s with probability lambda(s) / lambda*. The result is a
Poisson process of intensity lambda exactly when lambda(s) <= lambda* everywhere; every kept
candidate is checked, and a point where lambda(s) > lambda* is an error, never a silent bias.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from usdforest.errors import RecipeError, UsdForestError
from usdforest.expr import Expression, compile_expression
from usdforest.grow import exact

MAX_CANDIDATES = 50_000_000  # thinning candidates drawn at most (memory: ~16 bytes each)
CHUNK = 4_000_000
GRID = 512  # quadrature grid per axis for integrals and bounds


# --------------------------------------------------------------------------- regions


MAX_COORDINATE = 1e8  # metres: no projected CRS reaches further


@dataclass(frozen=True)
class Rectangle:
    """An axis-aligned rectangle ``[x0, x1] x [y0, y1]`` in metres."""

    x0: float
    y0: float
    x1: float
    y1: float

    def __post_init__(self) -> None:
        vals = (self.x0, self.y0, self.x1, self.y1)
        if not all(math.isfinite(v) and abs(v) <= MAX_COORDINATE for v in vals):
            raise RecipeError(
                f"region: bounds must be finite numbers within {MAX_COORDINATE:.0e} m, got "
                f"{list(vals)}"
            )
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            raise RecipeError(
                f"region: bounds [x0, y0, x1, y1] = {list(vals)} are empty (need x1 > x0, y1 > y0)"
            )

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return (self.x0, self.y0, self.x1, self.y1)

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (x >= self.x0) & (x <= self.x1) & (y >= self.y0) & (y <= self.y1)

    def describe(self) -> dict:
        return {"kind": "rectangle", "bounds": list(self.bounds)}


@dataclass(frozen=True)
class Polygon:
    """A simple polygon (no self-intersections), vertices in order, metres."""

    vertices: tuple[tuple[float, float], ...]
    _path: object = field(init=False, repr=False, compare=False)  # matplotlib's Path

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=float)
        if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3:
            raise RecipeError("region.vertices: a polygon needs at least 3 [x, y] vertices")
        if not np.all(np.isfinite(v)) or np.abs(v).max() > MAX_COORDINATE:
            raise RecipeError(
                f"region.vertices: vertices must be finite numbers within {MAX_COORDINATE:.0e} m"
            )
        if np.allclose(v[0], v[-1]) and len(v) > 3:
            v = v[:-1]
        crossing = _self_intersection(v)
        if crossing is not None:
            i, j = crossing
            raise RecipeError(
                f"region.vertices: the polygon intersects itself (edge {i} crosses edge {j})"
            )
        if abs(_shoelace(v)) <= 1e-12:
            raise RecipeError("region.vertices: the polygon has zero area")
        object.__setattr__(self, "vertices", tuple(map(tuple, v.tolist())))
        from matplotlib.path import Path as MplPath  # imported only where a polygon is used

        object.__setattr__(self, "_path", MplPath(np.vstack([v, v[:1]]), closed=True))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        v = np.asarray(self.vertices)
        return (
            float(v[:, 0].min()),
            float(v[:, 1].min()),
            float(v[:, 0].max()),
            float(v[:, 1].max()),
        )

    @property
    def area(self) -> float:
        return abs(_shoelace(np.asarray(self.vertices)))

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        pts = np.column_stack([np.ravel(x), np.ravel(y)])
        if len(pts) == 0:
            return np.zeros(0, dtype=bool)
        return self._path.contains_points(pts).reshape(np.shape(x))

    def describe(self) -> dict:
        return {"kind": "polygon", "vertices": [list(p) for p in self.vertices]}


@dataclass(frozen=True, eq=False)
class Shape:
    """A region read from a vector file: one or more polygons, holes allowed (shapely), in
    the file's coordinates (``crs``, when the file names one)."""

    geometry: object  # shapely Polygon or MultiPolygon
    source: str
    crs: str | None = None
    layer: str | None = None

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return tuple(float(b) for b in self.geometry.bounds)

    @property
    def area(self) -> float:
        return float(self.geometry.area)

    @property
    def rings(self) -> list[np.ndarray]:
        """Every exterior and interior ring, as ``(k, 2)`` closed outlines."""
        polys = getattr(self.geometry, "geoms", [self.geometry])
        return [np.asarray(r.coords)[:, :2] for p in polys for r in (p.exterior, *p.interiors)]

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        import shapely

        return shapely.intersects_xy(self.geometry, np.asarray(x), np.asarray(y))

    def describe(self) -> dict:
        layer = {} if self.layer is None else {"layer": self.layer}
        return {"kind": "file", "file": self.source, **layer}


def read_shape(path: Path, where: str, layer: str | None = None) -> Shape:
    """The polygons of a vector file as one region: GeoJSON (a geometry, feature or feature
    collection; a legacy ``crs`` member such as ``urn:ogc:def:crs:EPSG::32633`` names its
    CRS) read here, any other format GDAL reads (Shapefile, GeoPackage, ...) with pyogrio.
    A file of several layers (a GeoPackage of stands and roads) needs ``layer``, its name."""
    import json

    from shapely.geometry import shape as to_shape

    from usdforest.paths import require_file

    if path.suffix.lower() not in (".geojson", ".json"):
        return _read_vector(path, where, layer)
    if layer is not None:
        raise RecipeError(
            f"{where}: {path.name} is GeoJSON, one layer; layer = {layer!r} is for files of "
            "several (GeoPackage, a folder of Shapefiles): remove it"
        )
    try:
        require_file(path, "vector file", RecipeError)
        data = json.loads(path.read_text(encoding="utf-8"))
    except RecipeError as exc:
        raise RecipeError(f"{where}: {exc}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecipeError(f"{where}: {path.name} is not GeoJSON: {exc}") from None
    except RecursionError:
        raise RecipeError(f"{where}: {path.name} is nested too deeply to be a stand") from None
    if not isinstance(data, dict):
        raise RecipeError(f"{where}: {path.name} is not a GeoJSON object")
    polys = []

    def walk(g) -> None:
        """Every Polygon and MultiPolygon in features, collections and geometry collections."""
        if not isinstance(g, dict):
            return
        kind = g.get("type")
        if kind == "FeatureCollection":
            for f in g.get("features") or []:
                walk(f)
        elif kind == "Feature":
            walk(g.get("geometry"))
        elif kind == "GeometryCollection":
            for part in g.get("geometries") or []:
                walk(part)
        elif kind in ("Polygon", "MultiPolygon"):
            try:
                polys.append(to_shape(g))
            except Exception as exc:
                raise RecipeError(f"{where}: {path.name} has a malformed polygon: {exc}") from None

    try:
        walk(data)
    except RecursionError:
        raise RecipeError(f"{where}: {path.name} is nested too deeply to be a stand") from None
    geometry = _union(polys, path, where)
    crs = _geojson_crs(data.get("crs"), path, where)
    x0, y0, x1, y1 = geometry.bounds
    lonlat = -180 <= x0 <= x1 <= 180 and -90 <= y0 <= y1 <= 90
    # (in metres such a file would be a plot narrower than 5 m or smaller than 0.1 ha)
    if crs is None and lonlat and (x1 - x0 < 5 or geometry.area < 1e3):
        raise RecipeError(
            f"{where}: {path.name} names no CRS and its coordinates look like degrees "
            "(GeoJSON without a crs member is longitude/latitude, RFC 7946); usdforest needs "
            "projected metres: reproject it (e.g. ogr2ogr -t_srs EPSG:32633) and name the CRS, "
            'or give a plot in local metres as [region] kind = "polygon"'
        )
    if max(abs(v) for v in (x0, y0, x1, y1)) > MAX_COORDINATE:
        raise RecipeError(
            f"{where}: {path.name} has coordinates beyond {MAX_COORDINATE:.0e} m "
            f"(bounds {[float(f'{v:.3g}') for v in (x0, y0, x1, y1)]})"
        )
    return Shape(geometry, path.name, crs)


def _read_vector(path: Path, where: str, layer: str | None = None) -> Shape:
    """A Shapefile, GeoPackage or any vector file GDAL reads (pyogrio): the polygons of its
    one layer, or of ``layer``; a file of several layers without ``layer`` is refused with
    their names rather than read from the first (GDAL's default)."""
    import warnings

    import shapely

    from usdforest.paths import require_file

    try:
        require_file(path, "vector file", RecipeError)
    except RecipeError as exc:
        raise RecipeError(f"{where}: {exc}") from None
    try:
        from pyogrio.raw import read
    except ImportError:
        raise RecipeError(
            f"{where}: reading {path.name} needs pyogrio: pip install 'usdforest[geo]' "
            "(or give the stand as GeoJSON)"
        ) from None
    from pyogrio import list_layers

    try:
        with warnings.catch_warnings():  # the choices pyogrio warns of are refused below
            warnings.simplefilter("ignore")
            names = [str(n) for n in list_layers(path)[:, 0]]
            if layer is None and len(names) > 1:
                raise RecipeError(
                    f"{where}: {path.name} has {len(names)} layers "
                    f'({", ".join(map(repr, names))}); name the stand\'s with layer = "..."'
                )
            if layer is not None and layer not in names:
                raise RecipeError(
                    f"{where}: {path.name} has no layer {layer!r}; its layers are "
                    f"{', '.join(map(repr, names))}"
                )
            meta, _, wkb, _ = read(path, layer=layer)
        geoms = shapely.from_wkb(wkb)
    except RecipeError:
        raise
    except Exception as exc:
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    polys = [
        p
        for g in geoms
        if g is not None
        for p in getattr(g, "geoms", [g])
        if p.geom_type in ("Polygon", "MultiPolygon")
    ]
    return Shape(_union(polys, path, where), path.name, meta.get("crs") or None, layer)


def _union(polys: list, path: Path, where: str):
    """One region of a file's polygons: each valid, together of non-zero area."""
    import shapely
    from shapely.validation import explain_validity

    if not polys:
        raise RecipeError(f"{where}: {path.name} has no Polygon or MultiPolygon geometry")
    for p in polys:
        if not p.is_valid:
            raise RecipeError(f"{where}: {path.name}: invalid polygon ({explain_validity(p)})")
    geometry = shapely.union_all(polys)
    if geometry.is_empty or geometry.area <= 0:
        raise RecipeError(f"{where}: {path.name}: the polygons have zero area")
    return geometry


def _geojson_crs(member, path: Path, where: str) -> str | None:
    """The CRS a legacy GeoJSON ``crs`` member names (``urn:ogc:def:crs:EPSG::32633`` ->
    ``EPSG:32633``), None without one."""
    if member is None:
        return None
    props = member.get("properties") if isinstance(member, dict) else None
    name = props.get("name") if isinstance(props, dict) else None
    if not isinstance(name, str) or not name:
        raise RecipeError(
            f"{where}: {path.name}'s crs member is not "
            '{"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32633"}}'
        )
    parts = name.split(":")
    return f"EPSG:{parts[-1]}" if "EPSG" in name.upper() and parts[-1].isdigit() else name


Region = Rectangle | Polygon | Shape


def _shoelace(v: np.ndarray) -> float:
    x, y = v[:, 0], v[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _self_intersection(v: np.ndarray) -> tuple[int, int] | None:
    """First pair (i < j) of non-adjacent edges that intersect, or None.

    Edges go into a GEOS R-tree (shapely ``STRtree``); only pairs whose boxes overlap are
    tested exactly, so time and memory grow about as n log n, not n² (a 30,000-vertex boundary
    took over 24 GB with all pairs).
    """
    import shapely

    n = len(v)
    edges = shapely.linestrings(np.stack([v, np.roll(v, -1, axis=0)], axis=1))
    i, j = shapely.STRtree(edges).query(edges, predicate="intersects")
    keep = (j > i + 1) & ~((i == 0) & (j == n - 1))  # neighbours share a vertex
    i, j = i[keep], j[keep]
    if i.size == 0:
        return None
    k = np.lexsort((j, i))[0]
    return int(i[k]), int(j[k])


# --------------------------------------------------------------------------- intensities


def region_grid(region: Region, n: int = GRID) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Midpoints of an n x n grid over the region's bounds, the inside mask and cell area."""
    x0, y0, x1, y1 = region.bounds
    xs = x0 + (np.arange(n) + 0.5) * (x1 - x0) / n
    ys = y0 + (np.arange(n) + 0.5) * (y1 - y0) / n
    gx, gy = np.meshgrid(xs, ys)
    inside = region.contains(gx, gy)
    return gx, gy, inside, (x1 - x0) * (y1 - y0) / n**2


@dataclass(frozen=True)
class Constant:
    """lambda(s) = value."""

    value: float

    def __post_init__(self) -> None:
        if not math.isfinite(self.value) or self.value < 0:
            raise RecipeError(f"intensity.value: must be a finite number >= 0, got {self.value}")

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.full(np.shape(x), self.value)

    def bound(self, region: Region) -> float:
        return self.value

    def integral(self, region: Region) -> float:
        return self.value * region.area

    def describe(self) -> dict:
        return {"kind": "constant", "value": self.value}


@dataclass(frozen=True)
class Bump:
    x: float
    y: float
    sigma: float
    peak: float  # added intensity at the centre (trees/m^2); negative carves a clearing


@dataclass(frozen=True)
class GaussianMixture:
    """lambda(s) = base + sum_k peak_k exp(-|s - c_k|^2 / (2 sigma_k^2)), clipped at 0."""

    base: float
    bumps: tuple[Bump, ...]

    def __post_init__(self) -> None:
        if not math.isfinite(self.base) or self.base < 0:
            raise RecipeError(f"intensity.base: must be a finite number >= 0, got {self.base}")
        for i, b in enumerate(self.bumps):
            for k in ("x", "y", "sigma", "peak"):
                if not math.isfinite(getattr(b, k)):
                    raise RecipeError(f"intensity.bumps[{i}].{k}: must be a finite number")
            if b.sigma <= 0:
                raise RecipeError(f"intensity.bumps[{i}].sigma: must be > 0, got {b.sigma}")

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.full(np.shape(x), self.base, dtype=float)
        for b in self.bumps:
            out += b.peak * exact.exp(-((x - b.x) ** 2 + (y - b.y) ** 2) / (2 * b.sigma**2))
        return np.maximum(out, 0.0)

    def bound(self, region: Region) -> float:
        return self.base + sum(max(b.peak, 0.0) for b in self.bumps)

    def integral(self, region: Region) -> float:
        if isinstance(region, Rectangle) and self._never_negative():
            from scipy.special import erf  # not math.erf: its last bits differ

            total = self.base * region.area
            for b in self.bumps:
                s = b.sigma * math.sqrt(2)
                fx = 0.5 * (erf((region.x1 - b.x) / s) - erf((region.x0 - b.x) / s))
                fy = 0.5 * (erf((region.y1 - b.y) / s) - erf((region.y0 - b.y) / s))
                total += b.peak * 2 * math.pi * b.sigma**2 * fx * fy
            return total
        return _grid_integral(self, region)

    def _never_negative(self) -> bool:
        return self.base >= sum(-min(b.peak, 0.0) for b in self.bumps)

    def describe(self) -> dict:
        return {
            "kind": "gaussian-mixture",
            "base": self.base,
            "bumps": [{"x": b.x, "y": b.y, "sigma": b.sigma, "peak": b.peak} for b in self.bumps],
        }


@dataclass(frozen=True)
class ExpressionIntensity:
    """lambda(x, y) given as a safe arithmetic expression (never Python eval)."""

    source: str
    declared_bound: float | None = None
    _expr: Expression = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        from usdforest.errors import ExpressionError

        try:
            e = compile_expression(self.source, ("x", "y"), what="intensity.expr")
        except ExpressionError as exc:
            raise RecipeError(str(exc)) from None
        object.__setattr__(self, "_expr", e)
        if self.declared_bound is not None and (
            not math.isfinite(self.declared_bound) or self.declared_bound <= 0
        ):
            raise RecipeError(
                f"intensity.bound: must be a finite number > 0, got {self.declared_bound}"
            )

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        v = np.broadcast_to(
            np.asarray(self._expr.evaluate({"x": x, "y": y}), dtype=float), np.shape(x)
        )
        return v

    def bound(self, region: Region) -> float:
        grid_max = self._grid_stats(region)[0] / 1.1
        if self.declared_bound is not None:
            # a bound below the intensity thins with too few candidates: refuse it up front
            # (where no candidate falls, no site could be checked against it)
            if grid_max > self.declared_bound:
                raise RecipeError(
                    f"intensity.bound: {self.declared_bound:g} is below the intensity's "
                    f"maximum over the region ({grid_max:.6g}); thinning would be biased. "
                    "Give a bound at least that large, or leave it out"
                )
            return self.declared_bound
        return self._grid_stats(region)[0]

    def integral(self, region: Region) -> float:
        return self._grid_stats(region)[1]

    @functools.lru_cache(maxsize=8)  # noqa: B019 - instances are immutable and few
    def _grid_stats(self, region: Region) -> tuple[float, float]:
        """(bound, integral) from one quadrature grid: the grid's maximum plus a 10% margin
        (every kept site is checked against it) and the midpoint-rule integral."""
        gx, gy, inside, cell = region_grid(region)
        v = self.evaluate(gx[inside], gy[inside])
        _check_values(v, self.source)
        return (float(v.max()) * 1.1 if v.size else 0.0, float(v.sum() * cell))

    def describe(self) -> dict:
        d = {"kind": "expression", "expr": self.source}
        if self.declared_bound is not None:
            d["bound"] = self.declared_bound
        return d


@dataclass(frozen=True, eq=False)
class Raster:
    """lambda from a grid of cells over the region's bounds (row 0 = north, i.e. max y).

    Each cell's value is the intensity anywhere inside it (piecewise constant).
    """

    values: np.ndarray
    bounds: tuple[float, float, float, float]
    source: str = "array"
    crs: str | None = None  # a GeoTIFF's coordinate reference system

    def __post_init__(self) -> None:
        raw = np.asarray(self.values)
        if raw.dtype.kind not in "biuf":
            raise RecipeError(
                f"intensity.file: {self.source} holds {raw.dtype} values; an intensity is "
                "real numbers (trees/m²)"
            )
        v = raw.astype(float)
        if v.ndim != 2 or v.size == 0:
            raise RecipeError(f"intensity.file: {self.source} must be a non-empty 2D grid")
        _check_values(v, self.source)
        v = v.copy()
        v.setflags(write=False)
        object.__setattr__(self, "values", v)

    def evaluate(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        from usdforest.sites.rasters import cell_values

        return cell_values(self.values, self.bounds, x, y)

    def bound(self, region: Region) -> float:
        return float(self.values.max())

    def integral(self, region: Region) -> float:
        if isinstance(region, Rectangle) and region.bounds == self.bounds:
            return float(self.values.mean() * region.area)
        return _grid_integral(self, region, n=max(GRID, 2 * max(self.values.shape)))

    def describe(self) -> dict:
        return {"kind": "raster", "file": self.source}


Intensity = Constant | GaussianMixture | ExpressionIntensity | Raster


def _check_values(v: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(v)):
        raise RecipeError(f"intensity {what!r} is not finite somewhere in the region")
    if np.any(v < 0):
        raise RecipeError(
            f"intensity {what!r} is negative somewhere in the region (min {float(v.min()):.4g})"
        )


def _grid_integral(intensity: Intensity, region: Region, n: int = GRID) -> float:
    gx, gy, inside, cell = region_grid(region, n)
    v = intensity.evaluate(gx[inside], gy[inside])
    _check_values(v, getattr(intensity, "source", type(intensity).__name__))
    return float(v.sum() * cell)


def load_raster(
    path: Path, bounds: tuple[float, float, float, float], peak: float | None
) -> Raster:
    """A raster intensity from ``.npy`` (trees/m^2, over the region's ``bounds``), a GeoTIFF
    (trees/m^2 times ``peak`` if given, over its own georeferenced cells, which must cover the
    region; no-data cells hold no trees) or an image (grey 0..1 scaled by ``peak``)."""
    from usdforest.sites.rasters import GEOTIFF, covers, read_geotiff, read_grey, read_npy

    where = "intensity.file"
    geo = read_geotiff(path, where, box=bounds) if path.suffix.lower() in GEOTIFF else None
    if geo is not None:  # the region's window of it
        if not covers(geo.bounds, bounds):
            raise RecipeError(
                f"{where}: {path.name} covers {list(geo.extent)}, not the region "
                f"{list(bounds)} (coordinates in the raster's CRS, {geo.crs or 'none given'})"
            )
        valid = np.isfinite(geo.values)
        if not valid.any():
            raise RecipeError(
                f"{where}: {path.name} has no valid cell over the region (every cell is "
                "no-data or NaN)"
            )
        if np.isinf(geo.values).any():
            raise RecipeError(f"{where}: {path.name} has infinite intensities")
        values = np.nan_to_num(geo.values, nan=0.0) * (1.0 if peak is None else peak)
        return Raster(values, geo.bounds, path.name, geo.crs)
    if path.suffix.lower() == ".npy":
        values = np.asarray(read_npy(path, "intensity.file"))
        if peak is not None:
            values = values * peak
    else:
        if peak is None:
            raise RecipeError("intensity.max: an image raster needs 'max' (trees/m² for white)")
        values = read_grey(path, "intensity.file") * peak
    return Raster(values, bounds, path.name)


# --------------------------------------------------------------------------- sampling


def thin(
    region: Region,
    intensity: Intensity,
    rng: np.random.Generator,
    *,
    bound: float | None = None,
    max_candidates: int = MAX_CANDIDATES,
) -> np.ndarray:
    """Sample an inhomogeneous Poisson process by Lewis-Shedler thinning.

    Parameters
    ----------
    region, intensity
        Where, and how many trees per square metre.
    rng
        Seeded generator.
    bound
        lambda*; by default ``intensity.bound(region)``.
    max_candidates
        Refuse (before drawing) when lambda* x bounding-box area would exceed this.

    Returns
    -------
    numpy.ndarray
        ``float64[n, 2]`` sites (x, y).

    Raises
    ------
    UsdForestError
        If lambda exceeds lambda* at a candidate, or the candidates would not fit in memory.
    """
    lam_star = intensity.bound(region) if bound is None else bound
    if not math.isfinite(lam_star) or lam_star < 0:
        raise RecipeError(f"intensity bound lambda* = {lam_star} is not a finite number >= 0")
    x0, y0, x1, y1 = region.bounds
    box = (x1 - x0) * (y1 - y0)
    mean = lam_star * box
    if mean > max_candidates:
        raise UsdForestError(
            f"thinning would draw about {mean:,.0f} candidates (lambda* {lam_star:.4g} x "
            f"{box:,.0f} m²), more than {max_candidates:,}; lower the intensity or region"
        )
    n = int(rng.poisson(mean)) if mean > 0 else 0
    out = []
    for start in range(0, n, CHUNK):
        m = min(CHUNK, n - start)
        x = rng.uniform(x0, x1, m)
        y = rng.uniform(y0, y1, m)
        u = rng.uniform(0.0, 1.0, m)
        if not isinstance(region, Rectangle):  # a rectangle holds every draw from its box
            inside = region.contains(x, y)
            x, y, u = x[inside], y[inside], u[inside]
        lam = intensity.evaluate(x, y)
        # two reductions check it all (a NaN makes both fail); the message is worked out
        # only when one does
        if len(lam) and not (lam.min() >= 0 and lam.max() <= lam_star * (1 + 1e-9)):
            _refuse(x, y, lam, lam_star)
        keep = u * lam_star < lam
        out.append(np.column_stack([x[keep], y[keep]]))
    if len(out) == 1:
        return out[0]
    return np.concatenate(out) if out else np.zeros((0, 2))


def _refuse(x: np.ndarray, y: np.ndarray, lam: np.ndarray, lam_star: float) -> None:
    """Raise the error for intensities ``lam`` at candidates ``x, y`` that thinning cannot
    use: negative or not finite, or above the bound ``lam_star``."""
    if not np.all(np.isfinite(lam)) or np.any(lam < 0):
        raise RecipeError("intensity is negative or not finite at a sampled site")
    k = int(np.argmax(lam > lam_star * (1 + 1e-9)))
    raise UsdForestError(
        f"intensity {float(lam[k]):.6g} at ({x[k]:.2f}, {y[k]:.2f}) exceeds the bound "
        f"lambda* = {lam_star:.6g}; thinning would be biased. Give a larger "
        "'bound' in [intensity]"
    )


def matern_ii(sites: np.ndarray, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Matérn type II hard-core thinning: ``bool[n]`` of sites kept.

    Every site gets a uniform random birth time; a site is removed if another site within
    ``radius`` was born earlier. The result keeps a minimum spacing and is no longer Poisson:
    its intensity is lower than lambda, most where lambda is high.
    """
    n = len(sites)
    if radius <= 0 or n < 2:
        return np.ones(n, dtype=bool)
    return matern_keep(sites, radius, rng.uniform(size=n))


def matern_keep(sites: np.ndarray, radius: float, birth: np.ndarray) -> np.ndarray:
    """Matérn II with the given birth times: ``bool[n]``, a site dropped when a site within
    ``radius`` was born earlier."""
    from scipy.spatial import cKDTree

    n = len(sites)
    if radius <= 0 or n < 2:
        return np.ones(n, dtype=bool)
    pairs = cKDTree(sites).query_pairs(radius, output_type="ndarray")
    keep = np.ones(n, dtype=bool)
    if len(pairs):
        a, b = pairs[:, 0], pairs[:, 1]
        younger = np.where(birth[a] > birth[b], a, b)
        keep[younger] = False
    return keep


@dataclass(frozen=True)
class Marks:
    """Per-site marks: species index, variant, yaw (degrees) and scale."""

    species: np.ndarray
    variant: np.ndarray
    yaw: np.ndarray
    scale: np.ndarray


def species_weights(
    weights: Sequence[float | Expression],
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray | None = None,
    names: Sequence[str] | None = None,
    region: Sequence[float] | None = None,
) -> np.ndarray:
    """``(n, k)`` non-negative species weights at each site (numbers or expressions in x, y
    and z, the ground's height there: 0 without one). A weight that is negative or not finite
    at a site is refused naming its species (``names``), expression, value, the site and the
    ``region`` bounds: an expression written for one plot may not hold on a larger one."""
    env = {"x": x, "y": y, "z": np.zeros(np.shape(x)) if z is None else z}
    cols = []
    for w in weights:
        if isinstance(w, Expression):
            v = np.broadcast_to(np.asarray(w.evaluate(env), float), np.shape(x))
        else:
            v = np.full(np.shape(x), float(w))
        cols.append(v)
    out = np.stack(cols, axis=1) if cols else np.zeros((len(x), 0))
    bad = ~np.isfinite(out) | (out < 0)
    if bad.any():
        i, k = (int(v) for v in np.argwhere(bad)[0])
        name = names[k] if names is not None else str(k)
        w = weights[k]
        what = repr(w.source) if isinstance(w, Expression) else f"{float(w):g}"
        where = (
            f" of the region {[float(f'{b:.6g}') for b in region]}" if region is not None else ""
        )
        raise RecipeError(
            f"mix.{name}: {what} is {out[i, k]:.3g} at ({float(x[i]):.2f}, {float(y[i]):.2f})"
            f"{where}; a weight must be a finite number >= 0 everywhere trees may stand "
            "(write max(0, ...) to let a species fade out)"
        )
    return out


def draw_marks(
    sites: np.ndarray,
    weights: Sequence[float | Expression],
    variants: Sequence[int],
    scale: tuple[str, float, float],
    rng: np.random.Generator,
    height=None,
    names: Sequence[str] | None = None,
    region: Sequence[float] | None = None,
) -> Marks:
    """Species (from the mixture at each site, which may use the ground's ``height(x, y)``
    as ``z``), variant, yaw in [0, 360) and scale."""
    n = len(sites)
    x, y = sites[:, 0], sites[:, 1]
    uses_z = any(isinstance(w, Expression) and "z" in w.variables for w in weights)
    z = height(x, y) if uses_z and height is not None else None
    w = species_weights(weights, x, y, z, names, region)
    total = w.sum(axis=1)
    if n and np.any(total <= 0):
        k = int(np.argmax(total <= 0))
        raise RecipeError(
            f"mix: all species weights are 0 at ({sites[k, 0]:.2f}, {sites[k, 1]:.2f})"
        )
    cdf = np.cumsum(w, axis=1) / np.where(total > 0, total, 1)[:, None]
    u = rng.uniform(size=n)
    species = np.minimum((u[:, None] > cdf).sum(axis=1), len(weights) - 1).astype(np.int32)
    nvar = np.asarray(variants, dtype=np.int64)[species] if n else np.zeros(0, np.int64)
    variant = np.floor(rng.uniform(size=n) * nvar).astype(np.int32)
    yaw = rng.uniform(0.0, 360.0, n)
    kind, a, b = scale
    if kind == "uniform":
        s = rng.uniform(a, b, n)
    elif kind == "lognormal":
        sigma = math.sqrt(math.log(1 + (b / a) ** 2))
        s = rng.lognormal(math.log(a) - sigma**2 / 2, sigma, n)
    else:
        s = np.full(n, a)
    return Marks(species, variant, yaw, s)

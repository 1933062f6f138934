"""Real-world site data: GeoTIFF intensity and elevation rasters (rasterio), GeoJSON stand
boundaries (shapely) and the projected CRS recorded in the forest's root layer."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from matplotlib.path import Path as MplPath
from pxr import Sdf, Usd, UsdGeom

from usdforest.errors import RecipeError
from usdforest.recipe import parse_recipe
from usdforest.sites.sampling import sample_sites
from usdforest.usd.forest import write_forest
from usdforest.usd.validate import validate

rasterio = pytest.importorskip("rasterio", reason="GeoTIFF inputs need rasterio (usdforest[geo])")
from rasterio.transform import from_origin  # noqa: E402

E0, N0 = 500_000.0, 5_000_000.0  # a UTM 33N corner (EPSG:32633)


def _tiff(path, values, west, north, pixel, crs="EPSG:32633", **kw):
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        height=values.shape[0],
        width=values.shape[1],
        count=1,
        dtype="float64",
        crs=crs,
        transform=from_origin(west, north, pixel, pixel),
        **kw,
    ) as ds:
        ds.write(values, 1)


def _plane(x, y):
    return 100.0 + 0.05 * (x - E0) + 0.02 * (y - N0)


def _dem(path, pixel=5.0, cells=40, **kw):
    """Elevations of a tilted plane at the centres of ``cells`` x ``cells`` cells."""
    xs = E0 + (np.arange(cells) + 0.5) * pixel
    ys = N0 + cells * pixel - (np.arange(cells) + 0.5) * pixel  # row 0 = north
    gx, gy = np.meshgrid(xs, ys)
    _tiff(path, _plane(gx, gy), E0, N0 + cells * pixel, pixel, **kw)


def _recipe(tmp_path, **tables):
    data = {
        "seed": 7,
        "region": {"bounds": [E0 + 20, N0 + 20, E0 + 180, N0 + 180]},
        "intensity": {"kind": "constant", "value": 0.01},
        "species": {"paper-rule-1": {}},
        "forest": {"variants": 1, "origin": "centre", "colliders": "none"},
        **tables,
    }
    return parse_recipe(data, tmp_path, str(tmp_path / "recipe.toml"))


def test_a_geotiff_dem_sets_tree_z_and_the_ground(tmp_path):
    _dem(tmp_path / "dem.tif")
    recipe = _recipe(tmp_path, crs="EPSG:32633", ground={"kind": "raster", "file": "dem.tif"})
    out = tmp_path / "f.usda"
    build = write_forest(recipe, out, thumbnail=False)
    assert build.n_trees > 150
    assert validate(out) == []
    stage = Usd.Stage.Open(str(out))
    # the root layer says where its origin is on the map
    data = Sdf.Layer.FindOrOpen(str(out)).customLayerData
    assert data["crs"] == "EPSG:32633"
    assert tuple(data["crsOrigin"]) == (E0 + 100, N0 + 100)
    # each tree, composed, stands on the plane at its map position (the plane is linear,
    # so the ground mesh's triangles hold it exactly; float32 positions)
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    xf = np.asarray(
        pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    to_world = np.asarray(
        UsdGeom.Xformable(pi.GetPrim()).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    )
    world = xf[:, 3, :3] @ to_world[:3, :3] + to_world[3, :3]
    east, north = world[:, 0] + E0 + 100, world[:, 1] + N0 + 100
    np.testing.assert_allclose(world[:, 2], _plane(east, north), atol=2e-3)
    with open(build.assets / "trees.csv") as f:
        rows = list(csv.DictReader(f))
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    np.testing.assert_allclose(np.column_stack([east, north]), xy, atol=2e-3)
    # the ground mesh spans the centres of the DEM's cells over the region and one more each
    # side (not the whole DEM), at the DEM's heights
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Forest/Ground/Mesh"))
    m = np.asarray(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=float) @ m[:3, :3] + m[3, :3]
    e, n = pts[:, 0] + E0 + 100, pts[:, 1] + N0 + 100
    assert e.min() == pytest.approx(E0 + 17.5) and e.max() == pytest.approx(E0 + 182.5)
    assert n.min() == pytest.approx(N0 + 17.5) and n.max() == pytest.approx(N0 + 182.5)
    np.testing.assert_allclose(pts[:, 2], _plane(e, n), atol=2e-3)


def _feature(rings):
    return {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": "Polygon", "coordinates": rings},
    }


def test_a_geojson_boundary_clips_the_sites(tmp_path):
    outer = [[E0, N0], [E0 + 300, N0], [E0 + 300, N0 + 200], [E0 + 60, N0 + 260], [E0, N0]]
    hole = [[E0 + 100, N0 + 50], [E0 + 180, N0 + 50], [E0 + 180, N0 + 120], [E0 + 100, N0 + 50]]
    far = [[E0 + 400, N0], [E0 + 450, N0], [E0 + 450, N0 + 50], [E0 + 400, N0 + 50], [E0 + 400, N0]]
    doc = {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32633"}},
        "features": [_feature([outer, hole]), _feature([far])],
    }
    (tmp_path / "stand.geojson").write_text(json.dumps(doc))
    recipe = _recipe(
        tmp_path,
        region={"kind": "file", "file": "stand.geojson"},
        intensity={"kind": "constant", "value": 0.05},
    )
    assert recipe.crs == "EPSG:32633"
    xy = sample_sites(recipe).xy
    inside = (MplPath(outer).contains_points(xy) & ~MplPath(hole).contains_points(xy)) | MplPath(
        far
    ).contains_points(xy)
    assert inside.all()

    def shoelace(ring):
        x, y = np.asarray(ring, dtype=float).T - [[E0], [N0]]
        return abs(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1])) / 2

    area = shoelace(outer) - shoelace(hole) + shoelace(far)
    assert area == pytest.approx(recipe.region.area)
    expected = 0.05 * area
    assert abs(len(xy) - expected) < 5 * np.sqrt(expected)
    assert np.count_nonzero(MplPath(far).contains_points(xy)) > 0.5 * 0.05 * 2500


def test_a_geotiff_intensity_places_trees_where_it_is_high(tmp_path):
    lam = np.zeros((20, 40))
    lam[:, 20:] = 0.08  # the east half
    lam[0, 0] = np.nan  # no data: no trees
    _tiff(tmp_path / "lambda.tif", lam, E0, N0 + 200, 10.0, nodata=np.nan)
    recipe = _recipe(
        tmp_path,
        region={"bounds": [E0, N0, E0 + 400, N0 + 200]},
        intensity={"kind": "raster", "file": "lambda.tif"},
    )
    assert recipe.crs == "EPSG:32633"
    xy = sample_sites(recipe).xy
    assert np.all(xy[:, 0] >= E0 + 200)
    expected = 0.08 * 200 * 200
    assert abs(len(xy) - expected) < 5 * np.sqrt(expected)


def test_geo_inputs_that_cannot_be_used_are_named(tmp_path):
    _dem(tmp_path / "dem.tif")
    _dem(tmp_path / "small.tif", cells=10)
    _dem(tmp_path / "dem32.tif", crs="EPSG:32632")
    dem = {"kind": "raster", "file": "dem.tif"}
    cases = [
        (dict(ground={**dem, "file": "small.tif"}), "small.tif's cells span"),
        (dict(crs="EPSG:32632", ground=dem), "ground.file: the file is in EPSG:32633, but crs"),
        (dict(ground={**dem, "bounds": [E0, N0, E0 + 400, N0 + 400]}), "dem.tif is georef"),
        (dict(region={"kind": "file", "file": "none.geojson"}), "region.file"),
        (
            dict(intensity={**dem, "file": "dem32.tif"}, ground=dem),
            "ground.file: the file is in EPSG:32633, but intensity.file says EPSG:32632",
        ),
    ]
    for tables, fragment in cases:
        with pytest.raises(RecipeError, match=None) as err:
            _recipe(tmp_path, **tables)
        assert fragment in str(err.value), (fragment, str(err.value))
    (tmp_path / "junk.tif").write_bytes(b"II*\x00" + bytes(range(256)) * 4)  # a torn TIFF
    with pytest.raises(RecipeError, match=r"ground\.file: cannot read junk\.tif"):
        _recipe(tmp_path, ground={"kind": "raster", "file": "junk.tif"})
    (tmp_path / "torn.geojson").write_text('{"type": "Polygon", "coordinates": [[')
    with pytest.raises(RecipeError, match=r"region\.file: torn\.geojson is not GeoJSON"):
        _recipe(tmp_path, region={"kind": "file", "file": "torn.geojson"})
    (tmp_path / "line.geojson").write_text(
        json.dumps({"type": "LineString", "coordinates": [[0, 0], [1, 1]]})
    )
    with pytest.raises(RecipeError, match="no Polygon or MultiPolygon"):
        _recipe(tmp_path, region={"kind": "file", "file": "line.geojson"})
    bow = [[0, 0], [10, 10], [10, 0], [0, 10], [0, 0]]
    (tmp_path / "bow.geojson").write_text(json.dumps({"type": "Polygon", "coordinates": [bow]}))
    with pytest.raises(RecipeError, match=r"invalid polygon \(Self-intersection"):
        _recipe(tmp_path, region={"kind": "file", "file": "bow.geojson"})


def test_a_corner_origin_forest_is_written_about_its_corner(tmp_path):
    """Composed coordinates stay small (float32 consumers: renderers, physics, sensors);
    crsOrigin says where the stage's origin is on the map."""
    _dem(tmp_path / "dem.tif")
    recipe = _recipe(tmp_path, ground={"kind": "raster", "file": "dem.tif"})
    recipe = parse_recipe(
        {**recipe.data, "forest": {"variants": 1, "colliders": "trunk"}},
        tmp_path,
        str(tmp_path / "recipe.toml"),
    )
    out = tmp_path / "c.usda"
    build = write_forest(recipe, out, thumbnail=False)
    data = Sdf.Layer.FindOrOpen(str(out)).customLayerData
    assert tuple(data["crsOrigin"]) == (E0 + 20, N0 + 20)
    stage = Usd.Stage.Open(str(out))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    xf = np.asarray(
        pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    local = xf[:, 3, :3]
    assert np.abs(local[:, :2]).max() < 200  # metres from the corner, not 5e6
    with open(build.assets / "trees.csv") as f:
        xy = np.array([[float(r["x"]), float(r["y"])] for r in csv.DictReader(f)])
    np.testing.assert_allclose(local[:, :2] + [E0 + 20, N0 + 20], xy, atol=1e-4)
    # the trunk colliders stand where the trees do
    caps = [
        p
        for p in stage.Traverse()
        if p.IsA(UsdGeom.Capsule) and p.GetPath().pathString.startswith("/Forest/Colliders")
    ]
    assert len(caps) >= build.n_trees
    base = np.array(
        [
            UsdGeom.Xformable(p)
            .ComputeLocalToWorldTransform(Usd.TimeCode.Default())
            .ExtractTranslation()
            for p in caps[: build.n_trees]
        ]
    )
    near = np.min(np.linalg.norm(base[:, None, :2] - local[None, :, :2], axis=2), axis=1)
    assert near.max() < 0.5


def test_geojson_collections_and_what_is_refused(tmp_path):
    sq = [[E0, N0], [E0 + 100, N0], [E0 + 100, N0 + 100], [E0, N0 + 100], [E0, N0]]
    sq2 = [[x + 200, y] for x, y in sq]
    crs = {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32633"}}
    doc = {
        "type": "Feature",
        "crs": crs,
        "geometry": {
            "type": "GeometryCollection",
            "geometries": [
                {"type": "Polygon", "coordinates": [sq]},
                {"type": "Polygon", "coordinates": [sq2]},
            ],
        },
    }
    (tmp_path / "gc.geojson").write_text(json.dumps(doc))
    r = _recipe(tmp_path, region={"kind": "file", "file": "gc.geojson"})
    assert r.region.area == pytest.approx(20_000)
    lonlat = {"type": "Polygon", "coordinates": [[[15, 45], [15.01, 45], [15.01, 45.01], [15, 45]]]}
    (tmp_path / "ll.geojson").write_text(json.dumps(lonlat))
    with pytest.raises(RecipeError, match="look like degrees"):
        _recipe(tmp_path, region={"kind": "file", "file": "ll.geojson"})
    (tmp_path / "badcrs.geojson").write_text(json.dumps({**doc, "crs": "EPSG:32633"}))
    with pytest.raises(RecipeError, match="crs member is not"):
        _recipe(tmp_path, region={"kind": "file", "file": "badcrs.geojson"})
    with pytest.raises(RecipeError, match="geographic CRS"):
        _recipe(tmp_path, crs="EPSG:4326")
    _dem(tmp_path / "wgs.tif", crs="EPSG:4326")
    with pytest.raises(RecipeError, match=r"wgs\.tif is in EPSG:4326, a geographic CRS"):
        _recipe(tmp_path, ground={"kind": "raster", "file": "wgs.tif"})


def test_a_plain_tiff_is_an_image_without_rasterio(tmp_path, monkeypatch):
    import builtins

    from PIL import Image

    from usdforest.sites.terrain import load_height_field

    Image.fromarray(np.arange(64, dtype=np.uint16).reshape(8, 8) * 1000).save(tmp_path / "p.tif")
    real = builtins.__import__

    def no_rasterio(name, *a, **k):
        if name.startswith("rasterio"):
            raise ImportError(name)
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_rasterio)
    field = load_height_field(tmp_path / "p.tif", (0.0, 0.0, 70.0, 70.0), peak=10.0)
    assert field.bounds == (0.0, 0.0, 70.0, 70.0)
    assert field.z.max() == pytest.approx(10 * 63_000 / 65_535, rel=1e-6)


def test_a_geopackage_stand(tmp_path):
    """Any vector file GDAL reads: a GeoPackage with a polygon and a multipolygon, its CRS
    from the file."""
    pyogrio = pytest.importorskip("pyogrio", reason="vector files need pyogrio (usdforest[geo])")
    import shapely

    a = shapely.box(E0, N0, E0 + 200, N0 + 100)
    b = shapely.MultiPolygon([shapely.box(E0 + 300, N0, E0 + 350, N0 + 50)])
    pyogrio.raw.write(
        tmp_path / "stand.gpkg",
        geometry=np.array([shapely.to_wkb(a), shapely.to_wkb(b)], dtype=object),
        field_data=[],
        fields=[],
        crs="EPSG:32633",
        geometry_type="Unknown",
        driver="GPKG",
    )
    r = _recipe(tmp_path, region={"kind": "file", "file": "stand.gpkg"})
    assert r.crs == "EPSG:32633" and r.region.area == pytest.approx(200 * 100 + 50 * 50)
    xy = sample_sites(r).xy
    assert np.all(shapely.contains_xy(a, xy[:, 0], xy[:, 1]) | shapely.contains_xy(b, *xy.T))
    (tmp_path / "junk.gpkg").write_bytes(b"not a geopackage")
    with pytest.raises(RecipeError, match=r"region\.file: cannot read junk\.gpkg"):
        _recipe(tmp_path, region={"kind": "file", "file": "junk.gpkg"})


def test_a_geopackage_of_several_layers_needs_the_stands_layer(tmp_path, capfd):
    """GDAL reads a multi-layer file's first layer when none is named; a recipe must name
    it (the error lists the layers), and pyogrio's warning about the choice never reaches
    the terminal."""
    pyogrio = pytest.importorskip("pyogrio", reason="vector files need pyogrio (usdforest[geo])")
    import shapely

    gpkg = tmp_path / "estate.gpkg"
    stand = shapely.box(E0 + 10, N0 + 10, E0 + 110, N0 + 60)
    road = shapely.LineString([(E0, N0), (E0 + 200, N0 + 5)])
    for name, geom, kind in (("roads", road, "LineString"), ("stands", stand, "Polygon")):
        pyogrio.raw.write(
            gpkg, geometry=np.array([shapely.to_wkb(geom)], dtype=object), field_data=[],
            fields=[], crs="EPSG:32633", geometry_type=kind, driver="GPKG", layer=name,
            append=gpkg.exists(),
        )  # fmt: skip
    assert [str(n) for n in pyogrio.list_layers(gpkg)[:, 0]] == ["roads", "stands"]
    capfd.readouterr()
    with pytest.raises(RecipeError) as err:
        _recipe(tmp_path, region={"kind": "file", "file": "estate.gpkg"})
    assert str(err.value).endswith(
        "region.file: estate.gpkg has 2 layers ('roads', 'stands'); "
        'name the stand\'s with layer = "..."'
    )
    r = _recipe(tmp_path, region={"kind": "file", "file": "estate.gpkg", "layer": "stands"})
    assert r.region.area == pytest.approx(100 * 50) and r.region.layer == "stands"
    with pytest.raises(RecipeError, match=r"region\.file: estate\.gpkg has no Polygon"):
        _recipe(tmp_path, region={"kind": "file", "file": "estate.gpkg", "layer": "roads"})
    with pytest.raises(RecipeError, match=r"has no layer 'lakes'; its layers are 'roads', "):
        _recipe(tmp_path, region={"kind": "file", "file": "estate.gpkg", "layer": "lakes"})
    with pytest.raises(RecipeError, match=r"region\.layer: expected"):
        _recipe(tmp_path, region={"kind": "file", "file": "estate.gpkg", "layer": 3})
    (tmp_path / "s.geojson").write_text(json.dumps(shapely.geometry.mapping(stand)))
    with pytest.raises(RecipeError, match=r"s\.geojson is GeoJSON, one layer; layer = 'x'"):
        _recipe(
            tmp_path, region={"kind": "file", "file": "s.geojson", "layer": "x"}, crs="EPSG:32633"
        )
    out, errs = capfd.readouterr()
    assert (out, errs) == ("", "")


def test_a_flight_over_a_georeferenced_forest_writes_map_coordinates_and_its_crs(tmp_path, runner):
    """A forest in UTM 33N whose stage origin is its plot's centre, flown 3 m over its ground
    (z is the DEM's elevation, about 107 m there): the flight's LAS carries
    the WKT bit and a CRS record that pyproj reads as EPSG:32633, every return's x and y in
    map metres inside the recipe's bounds, and its trajectory in the same coordinates."""
    pyproj = pytest.importorskip(
        "pyproj", reason="the LAS CRS record needs pyproj (usdforest[geo])"
    )
    import laspy

    from usdforest.cli import app

    _dem(tmp_path / "dem.tif")
    recipe = _recipe(tmp_path, crs="EPSG:32633", ground={"kind": "raster", "file": "dem.tif"})
    out = tmp_path / "f.usda"
    write_forest(recipe, out, thumbnail=False)
    # thin rays: a beam's echo mixing a low leaf and the ground within 1 m lies between
    # them (as a real sensor's does), which this test of map coordinates is not about
    (tmp_path / "thin.toml").write_text("[lidar]\ndivergence = 0.0\n")
    r = runner.invoke(
        app,
        ["fly", str(out), "--line", "-20,0,110:20,0,110", "--speed", "10",
         "-o", str(tmp_path / "g"), "--lidar-rate", "5", "-q",
         "--config", str(tmp_path / "thin.toml")],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    las = laspy.read(str(tmp_path / "g.las"))
    assert las.header.global_encoding.wkt
    assert pyproj.CRS(las.header.parse_crs()).to_epsg() == 32633
    x, y, z = (np.asarray(v) for v in (las.x, las.y, las.z))
    assert len(x) > 1000
    x0, y0, x1, y1 = E0 + 20, N0 + 20, E0 + 180, N0 + 180
    assert x.min() > x0 - 10 and x.max() < x1 + 10 and y.min() > y0 - 10 and y.max() < y1 + 10
    # ground returns lie on the DEM's plane at their map position
    ground = np.asarray(las.classification) == 2
    assert ground.sum() > 100
    np.testing.assert_allclose(z[ground], _plane(x[ground], y[ground]), atol=0.05)
    traj = np.genfromtxt(tmp_path / "g_trajectory.csv", delimiter=",", names=True)
    np.testing.assert_allclose(traj["x"][[0, -1]], [E0 + 80, E0 + 120], atol=1e-6)
    np.testing.assert_allclose(traj["y"], N0 + 100, atol=1e-6)

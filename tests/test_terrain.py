"""Height-field ground from a raster: trees stand on the composed ground mesh, measured with
pxr transforms and trimesh rays, plus the recipe's errors."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom, UsdPhysics

from usdforest.errors import RecipeError
from usdforest.recipe import parse_recipe, read_recipe
from usdforest.sites.terrain import MAX_NODES, HeightField, load_height_field
from usdforest.usd.forest import write_forest
from usdforest.usd.validate import validate


def _dem(rows: int = 31, cols: int = 41) -> np.ndarray:
    """A slope rising 0.1 m per metre to the east with a 6 m hill at (40, 25)."""
    x = np.linspace(-5.0, 85.0, cols)
    y = np.linspace(55.0, -5.0, rows)  # row 0 = north
    gx, gy = np.meshgrid(x, y)
    return 0.1 * gx + 6.0 * np.exp(-((gx - 40) ** 2 + (gy - 25) ** 2) / 200.0)


def _recipe(tmp_path, ground: dict, **extra):
    data = {
        "seed": 3,
        "region": {"bounds": [0.0, 0.0, 80.0, 50.0]},
        "intensity": {"kind": "constant", "value": 0.01},
        "species": {"paper-rule-1": {}},
        "forest": {"variants": 1},
        "ground": ground,
        **extra,
    }
    return parse_recipe(data, tmp_path, str(tmp_path / "recipe.toml"))


def _ground_mesh(stage: Usd.Stage) -> trimesh.Trimesh:
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Forest/Ground/Mesh"))
    m = np.asarray(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=float) @ m[:3, :3] + m[3, :3]
    tri = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    return trimesh.Trimesh(pts, tri, process=False)


def _down(mesh: trimesh.Trimesh, xy: np.ndarray) -> np.ndarray:
    """Height of the first hit of a ray straight down at each ``xy`` (NaN for a miss)."""
    origins = np.column_stack([xy, np.full(len(xy), 1e3)])
    hits, rays, _ = mesh.ray.intersects_location(origins, np.tile([0, 0, -1.0], (len(xy), 1)))
    z = np.full(len(xy), np.nan)
    z[rays] = hits[:, 2]
    return z


def test_height_is_on_the_mesh_triangles():
    """At random points, :meth:`HeightField.height` equals the height of the triangulated
    mesh found by ray casting, so no tree floats above or sinks into a cell's diagonal."""
    field = HeightField(_dem(), (-5.0, -5.0, 85.0, 55.0))
    pts, tri = field.mesh()
    assert len(tri) == 2 * 30 * 40
    mesh = trimesh.Trimesh(pts, tri, process=False)
    assert np.all(mesh.face_normals[:, 2] > 0)  # wound up
    rng = np.random.default_rng(0)
    xy = rng.uniform([-5, -5], [85, 55], size=(2000, 2))
    np.testing.assert_allclose(field.height(xy[:, 0], xy[:, 1]), _down(mesh, xy), atol=1e-9)
    # at the nodes it is the raster itself
    gx, gy = np.meshgrid(np.linspace(-5, 85, 41), np.linspace(55, -5, 31))
    np.testing.assert_allclose(field.height(gx, gy), _dem(), atol=1e-12)


def test_forest_trees_stand_on_a_raster_ground(tmp_path):
    np.save(tmp_path / "dem.npy", _dem())
    recipe = _recipe(tmp_path, {"kind": "raster", "file": "dem.npy", "bounds": [-5, -5, 85, 55]})
    out = tmp_path / "f.usda"
    build = write_forest(recipe, out, thumbnail=False)
    assert build.n_trees > 20
    assert validate(out) == []
    stage = Usd.Stage.Open(str(out))
    ground = stage.GetPrimAtPath("/Forest/Ground/Mesh")
    assert ground.HasAPI(UsdPhysics.CollisionAPI)
    assert list(ground.GetAttribute("semantics:labels:class").Get()) == ["ground"]
    mesh = _ground_mesh(stage)
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    xf = np.asarray(pi.ComputeInstanceTransformsAtTime(*[Usd.TimeCode.Default()] * 2))
    world = xf[:, 3, :3]
    below = _down(mesh, world[:, :2])
    assert np.all(np.isfinite(below))
    np.testing.assert_allclose(world[:, 2], below, atol=1e-4)  # every trunk on the ground
    assert np.ptp(world[:, 2]) > 4.0  # the slope and the hill are there
    with (tmp_path / "f_assets" / "trees.csv").open() as f:
        rows = list(csv.DictReader(f))
    np.testing.assert_allclose([float(r["z"]) for r in rows], world[:, 2], atol=1e-4)
    # the collision layer's trunk capsules start at the ground too
    caps = [p for p in stage.Traverse() if str(p.GetPath()).startswith("/Forest/Colliders/T_")]
    assert len(caps) == build.n_trees
    for p in caps[:10]:
        c = UsdGeom.Capsule(p)
        m = np.asarray(UsdGeom.Xformable(p).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
        axis = m[2, :3] / np.linalg.norm(m[2, :3])
        bottom = m[3, :3] - axis * (c.GetHeightAttr().Get() / 2 + c.GetRadiusAttr().Get())
        assert bottom[2] == pytest.approx(_down(mesh, bottom[None, :2])[0], abs=0.01)
    # the forest's extentsHint holds the terrain (its lowest point is the ground's) and trees
    hint = np.array(stage.GetPrimAtPath("/Forest").GetAttribute("extentsHint").Get())
    assert hint[0, 2] == pytest.approx(mesh.bounds[0, 2], abs=1e-5)
    assert np.all(hint[0] <= mesh.bounds[0] + 1e-5) and np.all(hint[1] >= mesh.bounds[1] - 1e-5)
    assert hint[1, 2] > world[:, 2].max() + 1.0
    # the resolved recipe rebases the raster's path and rebuilds the same forest
    again = tmp_path / "again.usda"
    write_forest(read_recipe(tmp_path / "f_assets" / "pipeline.toml"), again, thumbnail=False)
    assert (tmp_path / "again_assets" / "trees.csv").read_bytes() == (
        tmp_path / "f_assets" / "trees.csv"
    ).read_bytes()


def test_an_image_height_field_and_a_fine_raster(tmp_path):
    import matplotlib.pyplot as plt

    img = np.clip(_dem() / 15.0, 0, 1)
    plt.imsave(tmp_path / "dem.png", np.dstack([img] * 3))  # grey, 8 bits
    field = load_height_field(tmp_path / "dem.png", (-5, -5, 85, 55), 15.0)
    assert field.shape == img.shape
    np.testing.assert_allclose(field.z, img * 15.0, atol=15.0 / 255 + 1e-9)
    # a raster finer than the mesh budget is resampled on the same bounds, not cropped
    fine = np.add.outer(np.linspace(0, 1, 1500), np.linspace(0, 2, 2100))
    np.save(tmp_path / "fine.npy", fine)
    f2 = load_height_field(tmp_path / "fine.npy", (0, 0, 210, 150))
    assert max(f2.shape) == MAX_NODES and f2.bounds == (0, 0, 210, 150)
    full = HeightField(fine, (0, 0, 210, 150))
    xy = np.random.default_rng(1).uniform([0, 0], [210, 150], size=(500, 2))
    np.testing.assert_allclose(f2.height(*xy.T), full.height(*xy.T), atol=1e-9)  # linear


@pytest.mark.parametrize(
    ("ground", "setup", "fragment"),
    [
        ({"kind": "raster", "file": "missing.npy"}, None, "ground.file: .*missing.npy"),
        ({"kind": "raster", "file": "nan.npy"}, "nan", "nan.npy has 1 missing or non-finite"),
        ({"kind": "raster", "file": "flat.npy"}, "1d", "2D grid of at least 2 x 2"),
        ({"kind": "raster", "file": "dem.png"}, "png", "ground.max"),
        (
            {"kind": "raster", "file": "dem.npy", "bounds": [10, 0, 80, 50]},
            "ok",
            "does not cover the region",
        ),
        ({"kind": "raster", "file": "dem.npy", "bounds": [80, 0, 0, 50]}, "ok", "ground.bounds"),
        ({"kind": "plane", "file": "dem.npy"}, "ok", "ground.file"),
        ({"kind": "hill"}, None, "ground.kind"),
    ],
)
def test_bad_ground_rasters_name_the_key(tmp_path, ground, setup, fragment):
    if setup == "nan":
        z = _dem()
        z[3, 4] = np.nan
        np.save(tmp_path / "nan.npy", z)
    elif setup == "1d":
        np.save(tmp_path / "flat.npy", np.zeros(10))
    elif setup == "png":
        import matplotlib.pyplot as plt

        plt.imsave(tmp_path / "dem.png", np.zeros((4, 4)), cmap="gray")
    elif setup == "ok":
        np.save(tmp_path / "dem.npy", _dem())
    with pytest.raises(RecipeError, match=fragment):
        _recipe(tmp_path, ground)


def test_image_rasters_keep_their_scale_whatever_their_bit_depth(tmp_path):
    """A 16-bit TIFF and a dark 8-bit image are divided by their type's maximum (a guess from
    the values once gave 257 times the height of a 16-bit file)."""
    from PIL import Image

    from usdforest.sites.pointprocess import load_raster

    grey = np.linspace(0.0, 1.0, 12).reshape(3, 4)
    Image.fromarray(np.round(grey * 65535).astype(np.uint16)).save(tmp_path / "dem16.tif")
    field = load_height_field(tmp_path / "dem16.tif", (0, 0, 30, 20), 100.0)
    np.testing.assert_allclose(field.z, grey * 100.0, atol=1e-3)
    dark = np.array([[0, 1], [1, 0]], dtype=np.uint8)  # nearly black: 0 and 1/255
    Image.fromarray(dark).save(tmp_path / "dark.png")
    np.testing.assert_allclose(
        load_height_field(tmp_path / "dark.png", (0, 0, 1, 1), 100.0).z, dark / 255 * 100, atol=1e-4
    )
    # the intensity raster reads images the same way
    r = load_raster(tmp_path / "dem16.tif", (0, 0, 30, 20), 0.5)
    np.testing.assert_allclose(r.values, grey * 0.5, atol=1e-5)


def test_species_mix_on_the_ground_height(tmp_path):
    """Mix weights in z, the ground's height at the site: pines up the slope."""
    from usdforest.sites.sampling import sample_sites

    x = np.linspace(0.0, 100.0, 11)
    np.save(tmp_path / "slope.npy", np.tile(0.1 * x, (6, 1)))  # z = x / 10, 0 to 10 m
    data = {
        "seed": 2,
        "region": {"bounds": [0.0, 0.0, 100.0, 50.0]},
        "intensity": {"kind": "constant", "value": 0.2},
        "mix": {"pine": "z", "broadleaf": "10 - z"},
        "species": {"pine": {}, "broadleaf": {}},
        "ground": {"kind": "raster", "file": "slope.npy", "bounds": [0, 0, 100, 50]},
    }
    s = sample_sites(parse_recipe(data, tmp_path, str(tmp_path / "r.toml")))
    pine = s.species == s.names.index("pine")
    for lo, hi in ((0, 20), (40, 60), (80, 100)):
        band = (s.xy[:, 0] >= lo) & (s.xy[:, 0] < hi)
        expected = (lo + hi) / 2 / 100  # the mean of z / 10 over the band
        assert band.sum() > 150
        assert abs(pine[band].mean() - expected) < 0.08, (lo, pine[band].mean())

"""Canopy cover and gap fraction by rays (issue 43) on stands of known geometry: opaque discs
whose union's exact area is the cover, leaves at random places and spherical angles whose
gap fraction is Beer-Lambert's exp(-0.5 LAI / cos theta), and the same leaves clumped."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from pxr import Sdf, Usd, UsdGeom

from usdforest.sensors.cast.raycast import SceneCaster
from usdforest.sensors.optics.gaps import clumping, gap_fractions, leaf_angles, leaf_projection
from usdforest.sensors.scene.extraction import extract_scene


def _stage(path, quads: np.ndarray | None = None, polygons=(), label="leaf"):
    """A stage of one mesh: ``quads (n, 4, 3)`` and/or flat ``polygons`` (each (k, 2) at its
    own height, a (k, 3) array), labelled ``label``."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Stand")
    mesh = UsdGeom.Mesh.Define(stage, "/Stand/Foliage")
    points, counts, index = [], [], []
    if quads is not None:
        points.extend(quads.reshape(-1, 3))
        counts.extend([4] * len(quads))
        index.extend(range(4 * len(quads)))
    for poly in polygons:
        first = len(points)
        points.extend(poly)
        counts.append(len(poly))
        index.extend(range(first, first + len(poly)))
    mesh.CreatePointsAttr(np.asarray(points, dtype=np.float32))
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(index)
    mesh.GetPrim().CreateAttribute("semantics:labels:class", Sdf.ValueTypeNames.TokenArray).Set(
        [label]
    )
    stage.SetDefaultPrim(root.GetPrim())
    stage.Save()
    scene = extract_scene(path)
    return scene, SceneCaster(scene)


def _leaves(rng, centres: np.ndarray, side: float) -> np.ndarray:
    """Square leaves of ``side`` at ``centres``, their normals uniform on the sphere."""
    n = len(centres)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    helper = np.where(np.abs(normal[:, [2]]) < 0.9, [[0, 0, 1.0]], [[1.0, 0, 0]])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    h = side / 2
    corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
    return np.stack([centres + a * e1 + b * e2 for a, b in corners], axis=1)


def test_discs_cover_their_union_exactly(tmp_path):
    rng = np.random.default_rng(3)
    k = np.linspace(0, 2 * math.pi, 97)[:-1]
    discs, shapes = [], []
    for _ in range(40):
        x, y, r, z = (
            rng.uniform(1, 19),
            rng.uniform(1, 19),
            rng.uniform(0.3, 2.0),
            rng.uniform(2, 9),
        )
        ring = np.column_stack([x + r * np.cos(k), y + r * np.sin(k)])
        discs.append(np.column_stack([ring, np.full(len(k), z)]))
        shapes.append(shapely.Polygon(ring))
    scene, caster = _stage(tmp_path / "discs.usda", polygons=discs)
    box = (0.0, 0.0, 20.0, 20.0)
    union = shapely.union_all(shapes).intersection(shapely.box(*box)).area / 400.0
    g = gap_fractions(scene, caster, box, (0.0,), nadir_spacing=0.02)
    # a 2 cm grid over 20 m: the union's area to the grid's resolution along its edges
    assert g.cover == pytest.approx(union, abs=0.004)
    assert g.rays == (1_000_000,)


@pytest.fixture(scope="module")
def slab(tmp_path_factory):
    """LAI 2 of 10 cm square leaves at random in a 40 x 40 x 8 m slab, spherical angles."""
    rng = np.random.default_rng(5)
    side, lai, area = 0.1, 2.0, 40.0 * 40.0
    n = round(lai * area / side**2)
    centres = np.column_stack([rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.uniform(2, 10, n)])
    path = tmp_path_factory.mktemp("slab") / "slab.usda"
    return _stage(path, quads=_leaves(rng, centres, side)), lai


def test_random_leaves_follow_beer_lambert(slab):
    (scene, caster), lai = slab
    zen = (0.0, 30.0, 45.0, 60.0)
    g = leaf_projection(scene, zen)
    assert g == pytest.approx(0.5, abs=0.01)  # spherical angles: G = 1/2 at every angle
    gaps = gap_fractions(scene, caster, (0.0, 0.0, 40.0, 40.0), zen)
    for z, p in zip(zen, gaps.gap, strict=True):
        want = math.exp(-0.5 * lai / math.cos(math.radians(z)))
        assert p == pytest.approx(want, rel=0.05), z
        assert clumping(p, lai, 0.5, z) == pytest.approx(1.0, abs=0.05)


def test_leaf_inclination_of_spherical_and_of_tilted_leaves(slab, tmp_path):
    """The leaf inclination distribution and mean leaf angle `stats` reports: spherical
    normals put cos(a) - cos(b) of the area between inclinations a and b and have a mean of
    1 radian (57.3 degrees); leaves all tilted 35 degrees sit in one class, with
    G(theta) = cos(theta) cos(35 deg) while theta + 35 <= 90 (Ross 1981)."""
    (scene, _), _ = slab
    g, lid, mean = leaf_angles(scene, (0.0, 30.0))
    edges = np.radians(np.arange(0, 100, 10.0))
    np.testing.assert_allclose(lid, np.cos(edges[:-1]) - np.cos(edges[1:]), atol=0.006)
    assert mean == pytest.approx(math.degrees(1.0), abs=0.3)
    rng = np.random.default_rng(7)
    n, side = 2000, 0.1
    az = rng.uniform(0, 2 * np.pi, n)
    tilt = math.radians(35.0)
    normal = np.column_stack(
        [np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.full(n, np.cos(tilt))]
    )
    e1 = np.column_stack([-np.sin(az), np.cos(az), np.zeros(n)])  # horizontal, in the leaf
    e2 = np.cross(normal, e1)
    centres = rng.uniform(0, 10, (n, 3))
    h = side / 2
    quads = np.stack(
        [centres + a * e1 + b * e2 for a, b in [(-h, -h), (h, -h), (h, h), (-h, h)]], 1
    )
    tilted, _ = _stage(tmp_path / "tilted.usda", quads=quads)
    g, lid, mean = leaf_angles(tilted, (0.0, 30.0, 50.0))
    assert mean == pytest.approx(35.0, abs=0.01)
    assert lid[3] == pytest.approx(1.0, abs=1e-6)  # the 30-40 degree class
    np.testing.assert_allclose(g, np.cos(np.radians([0, 30, 50])) * math.cos(tilt), rtol=0.002)


def test_clumped_leaves_let_more_through(tmp_path):
    """The slab's leaf area in 1 m balls of leaves: gaps between the balls, Omega below 1."""
    rng = np.random.default_rng(6)
    side, lai, area = 0.1, 2.0, 40.0 * 40.0
    n = round(lai * area / side**2)
    balls = np.column_stack([rng.uniform(0, 40, 600), rng.uniform(0, 40, 600),
                             rng.uniform(3, 9, 600)])  # fmt: skip
    which = rng.integers(0, len(balls), n)
    offset = rng.normal(size=(n, 3))
    offset *= (rng.uniform(size=(n, 1)) ** (1 / 3)) / np.linalg.norm(offset, axis=1, keepdims=True)
    scene, caster = _stage(tmp_path / "clumps.usda",
                           quads=_leaves(rng, balls[which] + offset, side))  # fmt: skip
    p = gap_fractions(scene, caster, (0.0, 0.0, 40.0, 40.0), (0.0,)).gap[0]
    omega = clumping(p, lai, float(leaf_projection(scene, (0.0,))[0]), 0.0)
    assert p > 1.3 * math.exp(-0.5 * lai)
    assert 0.2 < omega < 0.8


def test_stats_cover_is_a_top_down_cameras(tmp_path, runner):
    """Four allometric trees on a 16 m plot: ``stats``' cover by nadir rays against the share
    of a camera's pixels on leaf or wood, the camera 1 km up looking down over the plot (its
    rays within 0.46 degrees of nadir)."""
    import json

    from stands import allometric_stand

    from usdforest.cli import app
    from usdforest.recipe import read_recipe
    from usdforest.sensors.lidar.scanners import DepthCamera
    from usdforest.sensors.optics import camera
    from usdforest.sensors.pose import Pose
    from usdforest.usd.forest import write_forest

    sites = [
        'x = 4, y = 5, species = "pine", dbh = 0.12, height = 13.5',
        'x = 12, y = 6, species = "beech", dbh = 0.1, height = 11.0',
        'x = 7, y = 12, species = "birch", dbh = 0.09, height = 10.5',
        'x = 13, y = 13, species = "spruce", dbh = 0.1, height = 11.5',
    ]
    (tmp_path / "r.toml").write_text(allometric_stand(5, 16, sites))
    out = tmp_path / "f.usda"
    write_forest(read_recipe(tmp_path / "r.toml"), out, thumbnail=False)
    run = runner.invoke(app, ["stats", str(out), "--json", "-q"])
    assert run.exit_code == 0, run.output
    f = json.loads(run.stdout)
    cover = f["canopy_cover"]
    scene = extract_scene(out, reflectors=False)
    cam = DepthCamera(800, 800, math.degrees(2 * math.atan(8 / 1000)), 2000.0, kind="camera")
    frame = camera.render(scene, cam, Pose(8, 8, 1000, 0, -90), np.zeros((0, 3)))
    seen = float(np.isin(frame.semantic, [1, 2, 3]).mean())  # trunk, branch, leaf
    assert 0.02 < cover < 0.9
    assert cover == pytest.approx(seen, abs=0.01), (cover, seen)
    assert f["crown_footprint_cover"] >= cover  # outlines hold more than the rays meet
    assert set(f["gap_fraction"]) == {"0", "30", "45", "60"}
    assert f["gap_fraction"]["0"] == pytest.approx(1 - cover)

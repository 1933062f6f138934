"""The camera: z-depth against ray-sphere and ray-plane intersections written here, pixels
against the OpenCV projection of known points, semantic and instance labels at each tree's
projected trunk, and the files a user opens (16-bit depth PNG, npz, contact sheet)."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from PIL import Image
from scenes import ball_and_wall

from usdforest.cli import app
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.sensors.lidar.scanners import DepthCamera
from usdforest.sensors.optics.camera import PRESETS, intrinsics, path_colours, render
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.scene.scenetypes import CLASS_ID
from usdforest.usd.forest import write_forest


def _world_rays(cam: DepthCamera, pose: Pose) -> np.ndarray:
    """Each pixel's ray from K (independent of the camera module's own directions; OpenCV:
    pixel centres at integer coordinates)."""
    k = intrinsics(cam)
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    # camera frame: x forward, y left, z up; image u right (-y), v down (-z)
    d = np.stack([np.ones(u.shape), -(u - k[0, 2]) / k[0, 0], -(v - k[1, 2]) / k[1, 1]], -1)
    return d @ pose.rotation().T  # not unit: x component 1 along the optical axis


def test_depth_is_the_z_depth_of_analytic_surfaces(tmp_path):
    """Sphere of radius 1 at (6, 1, 0.5), a wall at x = 20: every pixel's depth is the
    z-depth of the nearest intersection (the sphere is tessellated to 0.2 mm)."""
    scene = extract_scene(ball_and_wall(tmp_path / "s.usda"))
    cam = DepthCamera(160, 120, 90.0, 100.0, kind="camera")
    pose = Pose(0, 0, 0)
    frame = render(scene, cam, pose, path_colours(tmp_path / "s.usda", scene.paths))
    d = _world_rays(cam, pose)
    # ray p(s) = s d with d_x = 1, so s is the z-depth itself
    c = np.array([6.0, 1.0, 0.5])
    a = np.sum(d * d, -1)
    b = -2 * d @ c
    disc = b * b - 4 * a * (c @ c - 1.0)
    s_ball = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    s_wall = np.full(a.shape, 20.0)
    expected = np.minimum(s_ball, s_wall)
    # the silhouette's pixels may fall either side of the tessellated rim
    miss = np.sqrt(np.maximum(c @ c - (d @ c) ** 2 / a, 0))
    clear = np.abs(miss - 1.0) > 5e-3
    assert np.isfinite(frame.depth).all()
    on_ball = clear & (s_ball < np.inf)
    on_wall = clear & (s_ball == np.inf)
    assert on_ball.sum() > 500  # the ball covers many pixels
    np.testing.assert_allclose(frame.depth[on_wall], 20.0, atol=1e-4)
    # on the ball: the seen point lies on the sphere within 1 mm (along a grazing ray the
    # tessellation's 0.2 mm grows), and its depth is the analytic one within 2 mm
    seen = frame.depth[on_ball, None] * d[on_ball]
    np.testing.assert_allclose(np.linalg.norm(seen - c, axis=1), 1.0, atol=1e-3)
    np.testing.assert_allclose(frame.depth[on_ball], expected[on_ball], atol=2e-3)


def test_a_point_is_seen_where_K_projects_it(tmp_path):
    """A 5 cm ball off-axis, camera yawed and pitched: the ball's pixel indices centre on K's
    projection of its centre within half a pixel (OpenCV's convention)."""
    centre = np.array([8.0, 2.5, 2.0])
    scene = extract_scene(ball_and_wall(tmp_path / "s.usda", tuple(centre), 0.05))
    cam = DepthCamera(640, 480, 60.0, 100.0, kind="camera")
    pose = Pose(0.5, 0.2, 1.0, yaw=15, pitch=5, roll=3)
    frame = render(scene, cam, pose, np.zeros((len(scene.paths), 3)))
    ball = frame.depth < 15
    vs, us = np.nonzero(ball)
    assert len(us) > 20
    local = pose.rotation().T @ (centre - pose.position)  # camera frame
    k = intrinsics(cam)
    u = k[0, 2] - k[0, 0] * local[1] / local[0]
    v = k[1, 2] - k[1, 1] * local[2] / local[0]
    assert us.mean() == pytest.approx(u, abs=0.5)
    assert vs.mean() == pytest.approx(v, abs=0.5)
    np.testing.assert_allclose(k[:2, 2], [319.5, 239.5])


@pytest.fixture(scope="module")
def stand(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("stand")
    pipe = tmp / "stand.toml"
    text = (default_recipe_path().parent / "paper-two-tree-stand.toml").read_text()
    pipe.write_text(text + '\n[ground]\nkind = "plane"\nmargin = 20.0\n')
    out = tmp / "two.usda"
    write_forest(read_recipe(pipe), out, thumbnail=False)
    with (tmp / "two_assets" / "trees.csv").open() as f:
        rows = list(csv.DictReader(f))
    return out, rows


def test_each_trees_trunk_is_labelled_with_its_id(stand):
    """From (5, -3, 1) looking along +y: the pixel onto which K projects a point on each
    trunk's near side, 0.4 m up, is class trunk with that tree's id from trees.csv; the
    bottom row is ground; where nothing is hit, sky."""
    out, rows = stand
    scene = extract_scene(out)
    cam = PRESETS["pinhole-640"]
    pose = Pose(5.0, -3.0, 1.0, yaw=90)
    frame = render(scene, cam, pose, path_colours(out, scene.paths))
    k = intrinsics(cam)
    for row in rows:
        base = np.array([float(row["x"]), float(row["y"]), float(row["z"]) + 0.4])
        local = pose.rotation().T @ (base - pose.position)
        u = round(k[0, 2] - k[0, 0] * local[1] / local[0])
        v = round(k[1, 2] - k[1, 1] * local[2] / local[0])
        assert frame.semantic[v, u] == CLASS_ID["trunk"], row
        assert frame.instance[v, u] == int(row["id"])
        assert frame.depth[v, u] == pytest.approx(local[0], abs=0.5)  # the trunk's near side
    assert np.all(frame.semantic[-1] == CLASS_ID["ground"])
    assert np.all(frame.instance[-1] == -1)
    from usdforest.view.preview import SKY

    sky = np.isinf(frame.depth)
    assert sky[0].sum() > 100  # much of the top row sees sky between the crowns
    assert np.all(frame.semantic[sky] == 0) and np.all(frame.instance[sky] == -1)
    assert np.all(frame.rgb[sky] == np.round(SKY * 255).astype(np.uint8))
    # bark is brown, leaves green: each class keeps its material's colour
    rgb = frame.rgb.astype(int)
    trunk = rgb[frame.semantic == CLASS_ID["trunk"]].mean(axis=0)
    assert trunk[0] > trunk[2]
    leaf = frame.semantic == CLASS_ID["leaf"]
    if leaf.any():
        g = rgb[leaf].mean(axis=0)
        assert g[1] > g[0] and g[1] > g[2]


def test_camera_scan_writes_images_a_user_opens(stand, tmp_path, runner):
    out, _ = stand
    shot = tmp_path / "shot.npz"
    args = ["scan", str(out), "--sensor", "camera", "--pose", "5,-3,1.2,90,-5", "-o", str(shot)]
    r = runner.invoke(app, [*args, "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["trees_seen"] == 2 and summary["pixels"] == 640 * 480
    data = np.load(shot)
    assert data["depth"].shape == (480, 640) and data["rgb"].shape == (480, 640, 3)
    np.testing.assert_allclose(data["K"], intrinsics(PRESETS["pinhole-640"]))
    depth_png = np.asarray(Image.open(tmp_path / "shot_depth.png"))
    assert depth_png.dtype == np.uint16
    finite = np.isfinite(data["depth"]) & (data["depth"] < 65)
    np.testing.assert_array_equal(depth_png[finite], np.round(data["depth"][finite] * 1000))
    assert np.all(depth_png[~np.isfinite(data["depth"])] == 0)
    for name in ("rgb", "semantic", "instance"):
        assert Image.open(tmp_path / f"shot_{name}.png").size == (640, 480)
    # a second run refuses to overwrite any of the five files
    (tmp_path / "shot.npz").unlink()
    r = runner.invoke(app, args)
    assert r.exit_code != 0 and "shot_rgb.png exists" in r.output


def test_a_flight_films_frames_at_its_rate(stand, tmp_path, runner):
    out, _ = stand
    (tmp_path / "cam.toml").write_text("[camera]\nwidth = 96\nheight = 64\n")
    stem = tmp_path / "run.v2"  # a dot in the stem is part of the name, not a suffix
    r = runner.invoke(
        app,
        [
            "fly", str(out), "--line", "2,-4,1.5:8,-4,1.5", "--speed", "4", "-o", str(stem),
            "--lidar", "none", "--sonar", "none", "--camera", "pinhole-640",
            "--camera-rate", "4", "--config", str(tmp_path / "cam.toml"), "--json",
        ],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    data = np.load(tmp_path / "run.v2_camera.npz")
    n = math.floor(1.5 * 4) + 1  # 6 m at 4 m/s, 4 frames a second
    assert summary["camera"]["frames"] == n == len(data["t"])
    assert data["depth"].shape == (n, 64, 96) and data["rgb"].shape == (n, 64, 96, 3)
    np.testing.assert_allclose(data["position"][:, 0], 2 + 4 * data["t"])
    assert (tmp_path / "run.v2_camera.png").stat().st_size > 10_000
    assert sorted(p.name for p in tmp_path.glob("run*")) == [
        "run.v2_camera.npz",
        "run.v2_camera.png",
    ]


@pytest.mark.parametrize(
    ("table", "fragment"),
    [
        ("[camera]\nhfov = 200.0\n", "camera.hfov"),
        ("[camera]\nwidth = 0\n", "camera.width/height"),
        ("[camera]\nkind = 'spinning'\n", "camera.kind"),
        ("[camera]\nmax_range = -1.0\n", "camera.max_range"),
        ("[camera]\nrange_noise = 0.01\n", "camera.range_noise: not a camera setting"),
        ("[camera]\nbaseline = 0.1\nk1 = 0.1\n", "camera.baseline: a stereo pair is rectified"),
        ("[camera]\nnoise = -1.0\n", "camera.noise"),
    ],
)
def test_bad_camera_settings_are_named(stand, tmp_path, runner, table, fragment):
    out, _ = stand
    (tmp_path / "c.toml").write_text(table)
    shot = tmp_path / "x.npz"
    r = runner.invoke(
        app,
        ["scan", str(out), "--sensor", "camera", "--pose", "5,-3,1", "-o", str(shot),
         "--config", str(tmp_path / "c.toml")],
    )  # fmt: skip
    assert r.exit_code == 2, r.output
    assert fragment in r.stderr
    assert not list(tmp_path.glob("x*"))


def test_a_flights_frames_must_fit_in_memory(stand, tmp_path, runner):
    """A 1280 x 720 camera at 120 frames/s over 100 s would hold 99 GiB: refused up front,
    naming the option, nothing written."""
    out, _ = stand
    r = runner.invoke(
        app,
        ["fly", str(out), "--line", "0,0,2:100,0,2", "--speed", "1", "-o", str(tmp_path / "f"),
         "--lidar", "none", "--sonar", "none", "--camera", "fpv-1280", "--camera-rate", "120"],
    )  # fmt: skip
    assert r.exit_code == 2, r.output
    assert "--camera-rate" in r.stderr and "GiB" in r.stderr
    assert not list(tmp_path.glob("f*"))

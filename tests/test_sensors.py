"""Sensors: lidar against analytic scenes, labels and tree ids, sonar against the formulas."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hosts import host_stage
from pxr import Usd, UsdGeom, Vt
from stands import allometric_stand

from usdforest.cli import app
from usdforest.grow.species import get_species
from usdforest.recipe import read_recipe
from usdforest.sensors.lidar.scanners import DepthCamera, SpinningLidar, scan
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.scene.scenetypes import CLASS_ID, Leaves
from usdforest.sensors.sonar.backscatter import disk_backscatter
from usdforest.sensors.sonar.model import (
    SonarConfig,
    absorption_db_per_m,
    beam_amplitude,
    echo_from_leaves,
)
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


def wall_stage(path: Path, d: float) -> Path:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    m = UsdGeom.Mesh.Define(stage, "/Wall")
    pts = [(d, -100, -100), (d, 100, -100), (d, 100, 100), (d, -100, 100)]
    m.CreatePointsAttr(pts)
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    m.CreateExtentAttr(Vt.Vec3fArray([(d, -100, -100), (d, 100, 100)]))
    stage.SetDefaultPrim(m.GetPrim())
    stage.Save()
    return path


def test_spinning_lidar_on_a_wall(tmp_path):
    d = 7.5
    scene = extract_scene(wall_stage(tmp_path / "wall.usda", d))
    assert len(scene) == 2
    sensor = SpinningLidar(channels=8, vfov_min=-10, vfov_max=10, azimuth_step=1.0, max_range=200)
    r = scan(scene, sensor, Pose(0, 0, 0))
    assert r.n_rays == 8 * 360
    az, el = sensor.angles()
    np.testing.assert_allclose(np.unique(el), np.linspace(-10, 10, 8))
    assert np.allclose(np.diff(np.unique(az)), 1.0)
    a, e = np.radians(az[r.ray]), np.radians(el[r.ray])
    np.testing.assert_allclose(r.range, d / (np.cos(a) * np.cos(e)), rtol=1e-5)
    # every ray that meets the (200 m x 200 m) wall within range returns, and no other
    ca, ce = np.cos(np.radians(az)), np.cos(np.radians(el))
    with np.errstate(divide="ignore"):
        y_hit = d * np.tan(np.radians(az))
        z_hit = d * np.tan(np.radians(el)) / ca
        meets = (ca > 0) & (np.abs(y_hit) <= 100) & (np.abs(z_hit) <= 100) & (d / (ca * ce) <= 200)
    assert len(r) == int(meets.sum())
    np.testing.assert_allclose(r.points[:, 0], d, atol=1e-4)


def test_depth_camera_and_pose(tmp_path):
    d = 4.0
    scene = extract_scene(wall_stage(tmp_path / "wall.usda", d))
    cam = DepthCamera(width=64, height=48, hfov=90, max_range=50)
    r = scan(scene, cam, Pose(0, 0, 1.0))
    assert len(r) == r.n_rays == 64 * 48
    dirs = cam.directions()[r.ray]
    np.testing.assert_allclose(r.range * dirs[:, 0], d, rtol=1e-5)  # depth = distance to wall
    # yaw 180 looks away from the wall: nothing; pitch +90 looks up: nothing
    assert len(scan(scene, cam, Pose(0, 0, 0, yaw=180))) == 0
    np.testing.assert_allclose(Pose(0, 0, 0, pitch=90).forward, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(Pose(0, 0, 0, yaw=90).forward, [0, 1, 0], atol=1e-12)


def test_range_noise_is_seeded(tmp_path):
    scene = extract_scene(wall_stage(tmp_path / "wall.usda", 5.0))
    s = SpinningLidar(channels=16, azimuth_step=0.5, max_range=100, range_noise=0.02)
    a, b, c = (scan(scene, s, Pose(0, 0, 0), seed=k) for k in (1, 1, 2))
    assert np.array_equal(a.range, b.range) and not np.array_equal(a.range, c.range)
    clean = scan(scene, SpinningLidar(channels=16, azimuth_step=0.5, max_range=100), Pose(0, 0, 0))
    assert np.std(a.range - clean.range) == pytest.approx(0.02, rel=0.1)


@pytest.fixture(scope="module")
def stand(tmp_path_factory):
    out = tmp_path_factory.mktemp("stand") / "stand.usda"
    b = write_forest(read_recipe(PIPELINES / "paper-two-tree-stand.toml"), out, thumbnail=False)
    return out, b


def test_lidar_labels_and_tree_ids_agree_with_the_stage(stand):
    out, b = stand
    scene = extract_scene(out)
    assert set(scene.instances.tree) == {0, 1} and len(scene.protos) == 2
    assert len(scene.leaves) == sum(t.placement.n_leaves for t in b.trees.values())
    r = scan(
        scene,
        SpinningLidar(channels=32, vfov_min=-30, vfov_max=60, azimuth_step=0.5, max_range=30),
        Pose(5.25, 5.25, 2.0),
    )
    assert len(r) > 1000
    sites = b.sites.xy
    nearest = np.argmin(np.linalg.norm(r.points[:, None, :2] - sites[None], axis=2), axis=1)
    assert np.mean(nearest == r.tree) > 0.97  # returns belong to the tree they are next to
    trunk = r.cls == CLASS_ID["trunk"]
    assert trunk.any()
    gap = np.linalg.norm(r.points[trunk, :2] - sites[r.tree[trunk]], axis=1)
    assert gap.max() < 0.5  # trunk returns lie on a trunk
    leaf = r.cls == CLASS_ID["leaf"]
    assert leaf.any()
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(scene.leaves.centre).query(r.points[leaf])
    assert dist.max() < 0.2  # leaf returns lie on a leaf
    paths = np.array(r.paths)[r.path]
    assert all("/Leaves/" in p for p in paths[leaf])
    assert all("/Branches/" in p for p in paths[r.cls == CLASS_ID["branch"]])


def test_culling_expands_only_trees_in_range(tmp_path):
    out = tmp_path / "f.usda"
    write_forest(read_recipe(PIPELINES / "paper-ipp-medium.toml"), out, thumbnail=False)
    whole = extract_scene(out)
    corner = extract_scene(out, centre=np.array([2.0, 2.0, 1.5]), radius=15.0)
    assert 0 < len(corner.instances) < len(whole.instances)
    assert len(corner) < len(whole) / 3
    assert len(corner.protos) <= len(whole.protos) == 2  # prototypes gathered once


def test_instanced_and_copied_scenes_return_the_same_hits(stand):
    out, _ = stand
    sensor = SpinningLidar(channels=16, vfov_min=-20, vfov_max=40, azimuth_step=1.0, max_range=30)
    pose = Pose(5.25, 1.0, 2.0, yaw=90)
    inst = extract_scene(out)
    copy = extract_scene(out, instancing=False)
    assert len(copy.protos) == 0 and len(copy) == len(inst) == len(copy.triangles)
    a, b = scan(inst, sensor, pose), scan(copy, sensor, pose)
    assert np.array_equal(a.ray, b.ray) and len(a) > 100
    # float32 geometry in two frames: a ray grazing a triangle's edge may pick its neighbour
    same = np.abs(a.range - b.range) < 1e-4
    assert same.mean() > 0.99 and np.abs(a.range - b.range).max() < 0.05
    assert np.array_equal(a.cls[same], b.cls[same]) and np.array_equal(a.tree, b.tree)
    assert [a.paths[i] for i in a.path[same]] == [b.paths[i] for i in b.path[same]]
    np.testing.assert_allclose(np.sort(inst.leaves.area), np.sort(copy.leaves.area), rtol=1e-9)


# --------------------------------------------------------------------------- sonar


def disk(x: float, y: float = 0.0, z: float = 0.0, a: float = 0.03, normal=(-1.0, 0, 0)):
    return Leaves(
        np.array([[x, y, z]]), np.array([normal], float), np.array([math.pi * a * a]), np.array([0])
    )


def test_absorption_iso_9613_1():
    a = absorption_db_per_m(np.array([20e3, 40e3, 60e3, 80e3, 100e3]))
    assert np.all(np.diff(a) > 0)
    assert 1.8 < a[2] < 2.2  # about 2 dB/m at 60 kHz, 20 °C, 50 % RH
    assert absorption_db_per_m(np.array([60e3]), humidity=10)[0] != pytest.approx(a[2], rel=0.05)


def test_single_disk_at_normal_incidence():
    cfg = SonarConfig(leaf_model="disk")
    c = cfg.speed_of_sound
    r = 2.0
    e = echo_from_leaves(disk(r), Pose(0, 0, 0), cfg)
    env = np.abs(e.impulse)
    assert e.t[np.argmax(env)] == pytest.approx(2 * r / c, abs=1.5 / cfg.sample_rate)
    f = e.freqs[:: max(1, len(e.freqs) // 20)]
    h = e.transfer[:: max(1, len(e.freqs) // 20)]
    k = 2 * math.pi * f / c
    expected = k * 0.03**2 / 2 * 10 ** (-absorption_db_per_m(f) * 2 * r / 20) / r**2
    np.testing.assert_allclose(np.abs(h), expected, rtol=0.01)
    # phase: a plate's +pi/2 (physical optics: S = i k A / 2 pi) after a delay of 2r/c
    residual = np.angle(h * np.exp(2j * math.pi * f * 2 * r / c) / 1j)
    assert np.abs(residual).max() < 0.05


def test_disk_outside_the_beam_contributes_almost_nothing():
    cfg = SonarConfig()
    on = echo_from_leaves(disk(2.0), Pose(0, 0, 0), cfg)
    behind = echo_from_leaves(disk(-2.0, normal=(1, 0, 0)), Pose(0, 0, 0), cfg)
    assert np.abs(behind.transfer).max() / np.abs(on.transfer).max() < 1e-3
    # to the side: the beam narrows with frequency (its width scales as 1 / f)
    side = echo_from_leaves(disk(0.0, 2.0, normal=(0, -1, 0)), Pose(0, 0, 0), cfg)
    high = on.freqs >= 50e3
    assert (np.abs(side.transfer[high]) / np.abs(on.transfer[high])).max() < 1e-3
    half = math.radians(cfg.beam_width) / 2
    assert beam_amplitude(np.array([half]), np.array([cfg.f_ref]), cfg)[0] ** 2 == pytest.approx(
        0.5, rel=1e-9
    )  # half power (-3 dB) at the half width


def test_doubling_the_distance():
    cfg = SonarConfig()
    near = echo_from_leaves(disk(1.5), Pose(0, 0, 0), cfg)
    far = echo_from_leaves(disk(3.0), Pose(0, 0, 0), cfg)
    f = near.freqs
    expected = 0.25 * 10 ** (-absorption_db_per_m(f) * 2 * 1.5 / 20)
    np.testing.assert_allclose(np.abs(far.transfer) / np.abs(near.transfer), expected, rtol=0.01)


def test_disk_backscatter_directivity():
    c = 343.0
    a = np.array([0.03])
    on = disk_backscatter(np.array([60e3]), np.array([0.0]), a, c)
    tilted = disk_backscatter(np.array([60e3]), np.array([math.radians(30)]), a, c)
    x = 2 * 2 * math.pi * 60e3 / c * 0.03 * math.sin(math.radians(30))
    from scipy.special import j1

    assert tilted[0] / on[0] == pytest.approx(2 * j1(x) / x * math.cos(math.radians(30)))


def test_echo_from_a_tree_starts_at_the_nearest_leaf(tmp_path):
    out = tmp_path / "t.usda"
    write_tree(get_species("broadleaf"), out, seed=4)
    scene = extract_scene(out)
    cfg = SonarConfig(max_range=12)
    pose = Pose(-6.0, 0.0, 5.5)
    e = echo_from_leaves(scene.leaves, pose, cfg)
    c = cfg.speed_of_sound
    d = scene.leaves.centre - pose.position
    r = np.linalg.norm(d, axis=1)
    theta = np.degrees(np.arccos(d @ pose.forward / r))
    in_beam = theta < cfg.beam_width / 2
    r_first = r[in_beam].min()
    env = np.abs(e.impulse)
    rng = e.t * c / 2
    window = np.abs(rng - r_first) < 0.01
    assert env[window].max() > 0.01 * env.max()
    # before the nearest leaf only the band-limited pulse's precursor (< -40 dB)
    assert env[rng < r.min() - 0.05].max() < 1e-2 * env.max()
    # deterministic
    again = echo_from_leaves(scene.leaves, pose, cfg)
    assert np.array_equal(e.echo, again.echo)


# --------------------------------------------------------------------------- CLI


def test_scan_cli_outputs(stand, tmp_path, runner):
    out, _ = stand
    r = runner.invoke(
        app,
        [
            "scan",
            str(out),
            "--sensor",
            "lidar",
            "--pose",
            "5,1,2,90",
            "-o",
            str(tmp_path / "s.ply"),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["returns"] > 100 and data["trees_hit"] == 2
    head = (tmp_path / "s.ply").read_bytes()[:400]
    assert head.startswith(b"ply\nformat binary_little_endian 1.0")
    assert f"element vertex {data['returns']}".encode() in head
    r = runner.invoke(
        app,
        [
            "scan",
            str(out),
            "--sensor",
            "lidar",
            "--pose",
            "5,1,2,90",
            "-o",
            str(tmp_path / "s.npz"),
            "--preset",
            "depth-camera",
        ],
    )
    assert r.exit_code == 0, r.output
    npz = np.load(tmp_path / "s.npz")
    assert set(npz.files) >= {"points", "range", "cls", "tree", "path", "paths", "ray"}
    assert np.all(npz["return_number"] == 1) and np.all(npz["number_of_returns"] == 1)
    # up to three returns per pulse of a 19 sub-ray beam: numbered by range within each pulse
    (tmp_path / "all.toml").write_text(
        "[lidar]\nreturns = 'all'\nmax_returns = 3\nbeam_rings = 2\n"
    )
    args = ["scan", str(out), "--sensor", "lidar", "--pose", "5,1,2,90", "--json"]
    r = runner.invoke(
        app, [*args, "-o", str(tmp_path / "m.npz"), "--config", str(tmp_path / "all.toml")]
    )
    assert r.exit_code == 0, r.output
    m = np.load(tmp_path / "m.npz")
    per = np.bincount(m["ray"])
    assert per.max() <= 3 and np.all(m["number_of_returns"] == per[m["ray"]])
    assert json.loads(r.stdout)["pulses_with_several_returns"] == np.count_nonzero(per >= 2) > 0
    for k in range(2, 4):  # return k of a pulse lies beyond return k - 1
        later = np.flatnonzero(m["return_number"] == k)
        assert np.all(m["ray"][later - 1] == m["ray"][later])
        assert np.all(m["range"][later] > m["range"][later - 1] + 0.5)
    r = runner.invoke(
        app,
        [
            "scan",
            str(out),
            "--sensor",
            "sonar",
            "--pose",
            "5,1,3,90",
            "-o",
            str(tmp_path / "e.npz"),
            "--occlusion",
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert 0 < data["leaves_used"] <= data["leaves_in_range"]
    for suffix in (".npz", ".wav", ".png"):
        assert (tmp_path / f"e{suffix}").is_file()
    from scipy.io import wavfile

    rate, wav = wavfile.read(tmp_path / "e.wav")
    assert rate == 400_000 and wav.dtype == np.int16 and np.abs(wav).max() > 1000


@pytest.mark.parametrize(
    ("args", "config", "fragment"),
    [
        (["--sensor", "radar"], None, "'radar' is not lidar, sonar or camera"),
        (["--sensor", "lidar", "--preset", "vlp-99"], None, "unknown lidar preset 'vlp-99'"),
        (["--sensor", "sonar"], "[sonar]\nf_min = 0.0\n", "frequencies must be > 0"),
        (["--sensor", "sonar"], "[sonar]\nf_min = -5.0\n", "frequencies must be > 0"),
        (["--sensor", "sonar"], "[sonar]\nbeam_width = 0.0\n", "an empty beam"),
        (["--sensor", "sonar"], "[sonar]\nwood_segment = 0.0\n", "sonar.wood_segment: 0 must"),
        (["--sensor", "sonar"], "[sonar]\nground_patch = 0.005\nmax_range = 200.0\n", "facets"),
        (["--sensor", "sonar"], "[sonar]\nground_slope = -1.0\n", "sonar.ground_slope"),
        (["--sensor", "sonar"], "[sonar]\nground_lambert = 2.0\n", "sonar.ground_lambert"),
        (["--sensor", "sonar"], "[sonar]\nground = 'yes'\n", "sonar.ground"),
        (["--sensor", "lidar"], "[lidar]\nchannels = 0\n", "must be 1 to 1024"),
        (["--sensor", "lidar"], "[lidar]\nchanels = 4\n", "unknown key 'chanels'"),
        (["--sensor", "lidar"], "[lidar]\nreturns = 'both'\n", "lidar.returns: 'both' is not"),
        (["--sensor", "lidar"], "[lidar]\ndivergence = -1.0\n", "lidar.divergence"),
        (["--sensor", "lidar"], "[lidar]\nbeam_rings = 40\n", "lidar.beam_rings"),
        (["--sensor", "lidar"], "[lidar]\nmax_returns = 16\n", "LAS 1.4 holds 15"),
        (["--sensor", "lidar"], "[lidar]\nreturn_separation = 0.0\n", "return_separation"),
        (["--sensor", "lidar"], "[lidar]\nmin_range = 200.0\n", "lidar.min_range"),
        (["--sensor", "lidar"], "[lidar]\ndetect_range = -1.0\n", "lidar.detect_range"),
        (["--sensor", "lidar"], "[lidar]\ndetect_reflectance = 0.0\n", "detect_reflectance"),
        (["--sensor", "lidar"], "[lidar]\nintensity_noise = 2.0\n", "lidar.intensity_noise"),
        (["--sensor", "lidar"], "[lidar]\nnoise = 'off'\n", "lidar.noise"),
        (["--sensor", "lidar"], "[sonar]\nbeam = 'x'\n", "unknown key 'sonar'"),
    ],
)
def test_scan_bad_input(stand, tmp_path, runner, args, config, fragment):
    out, _ = stand
    extra = []
    if config is not None:
        (tmp_path / "c.toml").write_text(config)
        extra = ["--config", str(tmp_path / "c.toml")]
    r = runner.invoke(
        app, ["scan", str(out), "--pose", "5,1,2", "-o", str(tmp_path / "x.npz"), *args, *extra]
    )
    assert r.exit_code == 2, r.output
    assert fragment in r.stderr
    assert not (tmp_path / "x.npz").exists()


def test_scan_pose_checks(stand, tmp_path, runner):
    out, b = stand
    x, y = b.sites.xy[0]
    r = runner.invoke(
        app,
        [
            "scan",
            str(out),
            "--sensor",
            "lidar",
            "--pose",
            f"{x},{y},1.0",
            "-o",
            str(tmp_path / "x.npz"),
        ],
    )
    assert r.exit_code == 2 and "inside a trunk" in r.stderr
    r = runner.invoke(
        app,
        [
            "scan",
            str(out),
            "--sensor",
            "lidar",
            "--pose",
            "500,500,2",
            "-o",
            str(tmp_path / "y.npz"),
        ],
    )
    assert r.exit_code == 0 and "warning:" in r.stderr and "beyond the sensor's range" in r.stderr
    r = runner.invoke(
        app, ["scan", str(out), "--sensor", "lidar", "--pose", "1,2", "-o", str(tmp_path / "z.npz")]
    )
    assert r.exit_code == 2 and "expected 3 to 6 numbers" in r.stderr


@pytest.mark.parametrize("pose", [Pose(5.0, -3.0, 1.2, yaw=90), Pose(5.25, 5.25, 2.0, pitch=10)])
def test_instanced_casting_equals_casting_the_copied_triangles(stand, pose):
    """Casting through tree and leaf instances returns what Embree returns on every tree's
    triangles copied into one scene: the same hits, the same distances, classes and tree
    ids, for a spinning lidar and a camera's rays, from outside the stand and from between
    its trees."""
    out, _ = stand
    inst, flat, h, t, prim = _cast_both_ways(out, pose, 50.0)
    assert len(inst.instances) == 2 and len(flat.instances) == 0
    _same_as_copied(h, flat, t, prim, 500)


def _same_as_copied(h, flat, t: np.ndarray, prim: np.ndarray, at_least: int) -> None:
    """Hits through instances ``h`` against Embree's ``t``, ``prim`` on the copied triangles:
    float32 geometry in two frames, so a ray grazing a triangle's edge may pick its
    neighbour (at most 0.1 % of rays); every other ray has the same hit or miss, distance
    (1e-4 m), class and tree id."""
    hit = prim >= 0
    assert hit.sum() > at_least
    assert np.mean(h.hit == hit) > 0.999
    both = h.hit & hit
    same = np.abs(h.t[both] - t[both]) < 1e-4
    assert same.mean() > 0.999
    np.testing.assert_array_equal(h.cls[both][same], flat.cls[prim[both]][same])
    np.testing.assert_array_equal(h.tree[both][same], flat.tree[prim[both]][same])


@pytest.mark.parametrize("sensor", ["sonar", "camera"])
def test_a_pose_inside_a_lone_trees_trunk_is_refused(tmp_path, runner, sensor):
    """A tree stage that is not instanced: the check casts into its trunk alone (a sonar
    builds no acceleration structure for the leaves), and still finds the pose inside."""
    out = tmp_path / "t.usda"
    write_tree(get_species("broadleaf"), out, seed=4)
    r = runner.invoke(
        app,
        ["scan", str(out), "--sensor", sensor, "--pose", "0,0,1", "-o", str(tmp_path / "x.npz")],
    )
    assert r.exit_code == 2 and "inside a trunk" in r.stderr, r.output
    assert not list(tmp_path.glob("x*"))


def _cast_both_ways(stage: Path, pose: Pose, reach: float):
    """The rays of a spinning lidar and a camera at ``pose``, cast through the instances
    (Warp: trees, then leaves) and by Embree on every triangle copied into one scene."""
    from usdforest.sensors.cast.raycast import RayCaster, SceneCaster

    inst = extract_scene(stage, centre=pose.position, radius=reach, reflectors=False)
    flat = extract_scene(
        stage, centre=pose.position, radius=reach, instancing=False, reflectors=False
    )
    rays = (
        np.concatenate(
            [
                SpinningLidar(
                    channels=32, vfov_min=-30, vfov_max=60, azimuth_step=0.5
                ).directions(),
                DepthCamera(160, 120, 90.0).directions(),
            ]
        )
        @ pose.rotation().T
    )
    origins = np.broadcast_to(pose.position, rays.shape)
    h = SceneCaster(inst).first_hit(origins, rays, reach)
    t, prim = RayCaster(flat.triangles).first_hit(origins, rays, reach)
    return inst, flat, h, t, prim


@pytest.mark.parametrize("tiles", [False, True])
def test_leaf_instances_cast_like_their_triangles_copied(tmp_path, tiles):
    """Allometric trees whose shoots and leaves are instances inside tree instances (a tiled
    forest too): every ray meets what Embree meets on all the triangles copied - the same
    hit or miss, distance (1e-4 m), class and tree id - while the scene keeps one copy of
    each shoot."""
    sites = [
        'x = 4, y = 5, species = "pine", dbh = 0.12, height = 13.5',
        'x = 12, y = 6, species = "beech", dbh = 0.1, height = 11.0',
        'x = 7, y = 12, species = "birch", dbh = 0.09, height = 10.5',
    ]
    extra = '[ground]\nkind = "plane"\n' + ("[tiles]\nsize = 8\n" if tiles else "")
    (tmp_path / "r.toml").write_text(allometric_stand(5, 16, sites, extra))
    out = tmp_path / "f.usda"
    write_forest(read_recipe(tmp_path / "r.toml"), out, thumbnail=False)
    inst, flat, h, t, prim = _cast_both_ways(out, Pose(8.0, -2.0, 4.0, yaw=90, pitch=10), 40.0)
    assert len(inst.instances) == 3 and len(inst) == len(flat.triangles)
    kept = sum(len(p.leaf_instances) for p in inst.protos)
    assert kept > 1000 and len(inst.shapes) >= 3
    assert (h.cls[h.hit] == CLASS_ID["leaf"]).sum() > 1000
    _same_as_copied(h, flat, t, prim, 5000)


def test_a_lone_trees_leaves_cast_like_their_triangles_copied(tmp_path):
    """A tree stage that is not instanced: its leaves are instances in world space."""
    out = tmp_path / "t.usdc"
    write_tree(get_species("broadleaf"), out, seed=2)
    inst, flat, h, t, prim = _cast_both_ways(out, Pose(-6.0, 0.0, 3.0), 30.0)
    assert len(inst.leaf_instances) > 1000 and len(inst) == len(flat.triangles)
    assert len(inst.triangles) < len(flat.triangles) / 2
    _same_as_copied(h, flat, t, prim, 800)
    assert set(np.unique(h.tree[h.hit])) == {0}


@pytest.mark.parametrize(("up", "cm"), [("Y", True), ("Z", True), ("Y", False)])
def test_a_y_up_centimetre_host_scans_like_the_forest_itself(tmp_path, runner, up, cm):
    """A forest referenced into a host stage of other units or up axis, with the transform
    that corrects it: a lidar and a camera posed in the host's own units and axes (the same
    place: x, y, z in metres is 100 x, 100 z, -100 y in a Y-up centimetre stage) give the
    same returns (same rays, ranges within 1 mm, points in metres Z up) and the same images
    as the forest scanned itself."""
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.usd.forest import write_forest

    forest = tmp_path / "f.usda"
    pipe = default_recipe_path().parent / "paper-two-tree-stand.toml"
    write_forest(read_recipe(pipe), forest, thumbnail=False)
    host = host_stage(tmp_path / "host.usda", forest, up=up, cm=cm)
    x, y, z = 1.0, 2.0, 1.5
    hx, hy, hz = (x, z, -y) if up == "Y" else (x, y, z)
    k = 100.0 if cm else 1.0
    pose, host_pose = f"{x},{y},{z},0", f"{hx * k},{hy * k},{hz * k},0"
    got = {}
    for name, stage, where in (("own", forest, pose), ("host", host, host_pose)):
        for sensor in ("lidar", "camera"):
            out = tmp_path / f"{name}_{sensor}.npz"
            r = runner.invoke(
                app,
                ["scan", str(stage), "--sensor", sensor, "--pose", where, "-o", str(out), "--json"],
            )
            assert r.exit_code == 0, r.output
            got[name, sensor] = np.load(out)
    a, b = got["own", "lidar"], got["host", "lidar"]
    assert len(a["ray"]) > 500
    shared, ia, ib = np.intersect1d(a["ray"], b["ray"], return_indices=True)
    assert len(shared) >= 0.999 * max(len(a["ray"]), len(b["ray"]))
    np.testing.assert_allclose(b["range"][ib], a["range"][ia], atol=1e-3)
    np.testing.assert_allclose(b["points"][ib], a["points"][ia], atol=1e-3)
    assert np.mean(b["cls"][ib] == a["cls"][ia]) > 0.999
    a, b = got["own", "camera"], got["host", "camera"]
    seen = np.isfinite(a["depth"]) & np.isfinite(b["depth"])
    assert seen.sum() > 5000  # pixels on a tree
    assert np.mean(np.isfinite(a["depth"]) == np.isfinite(b["depth"])) > 0.999
    assert np.mean(np.abs(a["depth"][seen] - b["depth"][seen]) < 1e-3) > 0.999
    assert np.mean(a["semantic"] == b["semantic"]) > 0.999

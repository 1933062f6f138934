"""The survey scanners' patterns (issue 62) against the formulas they implement, on flat
ground: a line scanner's points where the mirror's angle at each pulse's time puts them (and
its along- and across-track spacing), the zig-zag of an oscillating mirror, a Palmer cone's
circle, the Risley-prism rosette (Li, Appl. Opt. 50, 679, 2011: the sum of two rotating
deflections), a terrestrial scanner's angular grid; and the 1550 nm reflectances against the
ASTER/JHU spectra they are scaled by."""

from __future__ import annotations

import math
from dataclasses import replace

import forestcache
import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom
from stands import beech_and_pine

from usdforest.cli import app
from usdforest.errors import UsdForestError
from usdforest.sensors.lidar.patterns import (
    ConicalScanner,
    LineScanner,
    OscillatingScanner,
    RosetteScanner,
    TerrestrialScanner,
)
from usdforest.sensors.lidar.presets import PRESETS, SURVEY
from usdforest.sensors.lidar.scanners import reflectances, scan
from usdforest.sensors.platforms.flight import Trajectory, fly_lidar
from usdforest.sensors.platforms.survey import planned_work, sensor_settings
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.scene.scenetypes import CLASS_ID

H = 50.0  # m above the ground
V = 5.0  # m/s
EXACT = {"noise": False, "beam_rings": 0, "max_range": 2000.0, "min_range": 0.0}


@pytest.fixture(scope="module")
def ground(tmp_path_factory):
    """A flat square of ground, 2 km a side, at z = 0."""
    path = tmp_path_factory.mktemp("ground") / "ground.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Ground")
    mesh = UsdGeom.Mesh.Define(stage, "/Ground/Plane")
    s = 1000.0
    mesh.CreatePointsAttr([(-s, -s, 0), (s, -s, 0), (s, s, 0), (-s, s, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.SetDefaultPrim(root.GetPrim())
    stage.Save()
    return extract_scene(path)


def _fly(scene, sensor, seconds=1.0):
    traj = Trajectory.line((0.0, 0.0, H), (V * seconds, 0.0, H), V)
    return fly_lidar(scene, sensor, traj, rate=10.0)


def _pulse_times(r, rate):
    """The pulse index of each return (its GPS time is k / rate)."""
    k = np.round(r.gps_time * rate)
    np.testing.assert_allclose(r.gps_time * rate, k, atol=1e-6)
    return k


def test_a_line_scanner_draws_lines_across_the_track_at_its_rates(ground):
    """Mirror angle theta = fov (frac(t f) - 1/2) at pulse time t (f lines a second),
    positive to the right: a point at (x0 + v t, -h tan theta, 0). Lines v / f apart along
    the track; at the nadir, pulses h tan(fov f / PRR) apart across it."""
    sensor = LineScanner(pulse_rate=20_000.0, scan_rate=50.0, fov=60.0, **EXACT)
    r = _fly(ground, sensor)
    assert r.n_rays == 20_000 and len(r) == 20_000  # every pulse of the second meets the ground
    k = _pulse_times(r, sensor.pulse_rate).astype(np.int64)
    t = k / sensor.pulse_rate
    theta = np.radians(60.0 * ((k * 50) % 20_000 / 20_000 - 0.5))  # frac(t f), in integers
    expected = np.column_stack([V * t, -H * np.tan(theta), np.zeros_like(t)])
    np.testing.assert_allclose(r.points, expected, atol=1e-3)
    np.testing.assert_allclose(r.scan_angle, np.degrees(theta), atol=1e-6)
    # the spacings a survey plan quotes
    line = k * 50 // 20_000
    nadir = np.array([r.points[line == k][np.argmin(np.abs(r.points[line == k, 1])), 0]
                      for k in range(50)])  # fmt: skip
    assert np.median(np.diff(nadir)) == pytest.approx(V / 50.0, rel=1e-3)
    first = r.points[line == 0]
    order = np.argsort(first[:, 1])
    gaps = np.diff(first[order, 1])
    mid = np.argmin(np.abs(first[order, 1][:-1]))
    assert gaps[mid] == pytest.approx(H * math.tan(math.radians(60.0 * 50.0 / 20_000.0)), rel=0.01)


def test_an_oscillating_mirror_zig_zags(ground):
    """A triangle wave: theta = fov (u - 1/2) for u = (t f) mod 2 below 1, fov (3/2 - u)
    above (one line each way, f lines a second)."""
    sensor = OscillatingScanner(pulse_rate=10_000.0, scan_rate=40.0, fov=40.0, **EXACT)
    r = _fly(ground, sensor, 0.5)
    k = _pulse_times(r, sensor.pulse_rate).astype(np.int64)
    u = (k * 40) % 20_000 / 10_000  # (t f) mod 2, in integers
    theta = np.radians(np.where(u < 1, 40.0 * (u - 0.5), 40.0 * (1.5 - u)))
    np.testing.assert_allclose(r.points[:, 1], -H * np.tan(theta), atol=1e-3)
    # consecutive lines run in opposite directions
    line = k * 40 // 10_000
    signs = {k: np.sign(np.mean(np.diff(r.points[line == k, 1]))) for k in range(4)}
    assert signs[0] == -signs[1] == signs[2] == -signs[3]


def test_a_palmer_scanner_draws_a_circle_about_the_nadir(ground):
    """The beam on a cone of full angle fov: points at h tan(fov / 2) from the point under
    the platform, their azimuth 360 f t (f turns a second) from the forward axis."""
    sensor = ConicalScanner(pulse_rate=5_000.0, scan_rate=20.0, fov=40.0, **EXACT)
    r = _fly(ground, sensor, 0.5)
    t = _pulse_times(r, sensor.pulse_rate) / sensor.pulse_rate
    d = r.points - np.column_stack([V * t, np.zeros((len(t), 2))])
    np.testing.assert_allclose(np.hypot(d[:, 0], d[:, 1]), H * math.tan(math.radians(20.0)),
                               rtol=1e-5)  # fmt: skip
    azimuth = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360
    np.testing.assert_allclose((azimuth - 360.0 * 20.0 * t + 180) % 360 - 180, 0.0, atol=1e-3)


def test_the_rosette_is_the_risley_prism_equation(ground):
    """Two prisms each deflecting by delta = fov / 4, at f1 and f2 turns a second: the
    pointing p(t) = delta (cos 2 pi f1 t + cos 2 pi f2 t, sin 2 pi f1 t + sin 2 pi f2 t),
    |p| from the nadir towards atan2(p): on the ground at h tan |p| from under the sensor;
    it fills its circle (the rosette is not a line) and never leaves it."""
    mid40 = replace(PRESETS["livox-mid-40"], **EXACT)
    r = scan(ground, mid40, Pose(0.0, 0.0, H))
    k = r.ray.astype(float)
    t = k / mid40.pulse_rate
    delta = math.radians(mid40.fov) / 4
    w1, w2 = 2 * math.pi * 121.567 * t, 2 * math.pi * -77.733 * t
    p = delta * np.column_stack([np.cos(w1) + np.cos(w2), np.sin(w1) + np.sin(w2)])
    off = np.hypot(p[:, 0], p[:, 1])
    expected = H * np.tan(off)[:, None] * p / np.maximum(off, 1e-12)[:, None]
    assert len(r) == r.n_rays == 10_000  # 0.1 s at 100 kHz
    np.testing.assert_allclose(r.points[:, :2], expected, atol=1e-3)
    radius = H * math.tan(math.radians(mid40.fov) / 2)
    reach = np.hypot(r.points[:, 0], r.points[:, 1])
    assert reach.max() <= radius + 1e-6 and reach.max() > 0.999 * radius
    # the circle's cells of 1/20 its radius: a rosette visits most in a tenth of a second
    cells = np.unique(np.floor(r.points[:, :2] / (radius / 20)), axis=0)
    assert len(cells) > 0.5 * math.pi * 20**2


def test_a_terrestrial_station_is_its_angular_grid(ground):
    """Vertical lines from vfov_min to vfov_max at the elevation step, the head turning by
    the azimuth step: n_az x n_el pulses, line by line; from 1.5 m above the ground every
    pulse below the horizon lands at 1.5 / tan(-elevation) in its azimuth."""
    tls = TerrestrialScanner(vfov_min=-40.0, vfov_max=60.0, azimuth_step=2.0,
                             elevation_step=1.0, **EXACT)  # fmt: skip
    assert tls.station_pulses() == 180 * 101
    az, el = tls.grid()
    np.testing.assert_allclose(np.diff(el[:101]), 1.0)
    np.testing.assert_allclose(az[::101], np.arange(180) * 2.0)
    r = scan(ground, tls, Pose(0.0, 0.0, 1.5))
    assert r.n_rays == 180 * 101
    e, a = np.radians(el[r.ray]), np.radians(az[r.ray])
    assert np.all(e < 0) and len(r) == 180 * 40  # the 40 elevations below the horizon
    rho = 1.5 / np.tan(-e)
    np.testing.assert_allclose(r.points[:, :2], np.column_stack([rho * np.cos(a), rho * np.sin(a)]),
                               atol=1e-4)  # fmt: skip
    np.testing.assert_allclose(tls.times()[:3], np.arange(3) / tls.pulse_rate)


def test_reflectances_at_1550_nm_follow_the_spectra():
    """Green leaves reflect less at 1550 nm, where their water absorbs: the ASTER/JHU
    deciduous-leaf spectrum has 0.554 at 905 nm and 0.253 at 1550 nm, green grass 0.509 and
    0.243; wood keeps its 905 nm value. 1064 nm is on the leaves' near-infrared plateau."""
    nir, swir = reflectances(905.0), reflectances(1550.0)
    leaf, grass, trunk = CLASS_ID["leaf"], CLASS_ID["ground_vegetation"], CLASS_ID["trunk"]
    assert swir[leaf] / nir[leaf] == pytest.approx(0.253 / 0.554, rel=0.01)
    assert swir[grass] / nir[grass] == pytest.approx(0.243 / 0.509, rel=0.01)
    assert swir[trunk] == nir[trunk]
    assert np.array_equal(reflectances(1064.0), nir)
    with pytest.raises(UsdForestError, match=r"lidar.wavelength: 532 nm is not modelled"):
        reflectances(532.0)


def test_a_1550_nm_scanner_sees_leaves_darker(tmp_path):
    """The same leaf-labelled plate at 905 and at 1550 nm: its intensity falls by the ratio
    of the two reflectances."""
    path = tmp_path / "leaf.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Leaf")
    mesh = UsdGeom.Mesh.Define(stage, "/Leaf/Plate")
    mesh.CreatePointsAttr([(-5, -5, 0), (5, -5, 0), (5, 5, 0), (-5, 5, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    label = mesh.GetPrim().CreateAttribute("semantics:labels:class", Sdf.ValueTypeNames.TokenArray)
    label.Set(["leaf"])
    stage.SetDefaultPrim(root.GetPrim())
    stage.Save()
    scene = extract_scene(path)
    near = RosetteScanner(pulse_rate=1000.0, fov=20.0, leaf_transmittance=0.0, **EXACT)
    a = scan(scene, near, Pose(0.0, 0.0, 3.0))  # near: thousands of counts, rounding 1e-3
    b = scan(scene, replace(near, wavelength=1550.0), Pose(0.0, 0.0, 3.0))
    assert len(a) == len(b) == 100 and np.all(a.cls == CLASS_ID["leaf"])
    ratio = b.intensity.astype(float) / a.intensity
    np.testing.assert_allclose(ratio, 0.215 / 0.47, rtol=1e-3)


def test_survey_presets_check_and_plan_their_pulses():
    """Every survey preset passes its checks; a flight plans pulse_rate x duration pulses of
    its sub-rays (1 + 3 k (k + 1) for k beam rings)."""
    assert {"vz-400", "vux-1uav", "livox-mid-40", "vq-780i", "als50-ii"} <= set(SURVEY)
    kinds = set()
    for name, s in SURVEY.items():
        s.check()
        kinds.add(s.kind)
        assert s.model and s.wavelength in (905.0, 1064.0, 1550.0), name
    assert kinds == {"tls", "line", "rosette", "oscillating"}
    traj = Trajectory.line((0, 0, 60), (80, 0, 60), 8.0)
    vux = PRESETS["vux-1uav"]
    work = planned_work(traj, vux, None, None, 10.0)
    assert work["lidar rays"] == math.ceil(10.0 * 275e3) * 7


def test_a_table_picks_a_pattern_kind_and_names_wrong_keys():
    s = sensor_settings("lidar", "vlp-16", {"kind": "line", "fov": 90.0, "pulse_rate": 1e5})
    assert isinstance(s, LineScanner) and s.fov == 90.0
    with pytest.raises(UsdForestError, match=r"lidar.*channels"):
        sensor_settings("lidar", "vlp-16", {"kind": "rosette", "channels": 16})
    with pytest.raises(UsdForestError, match=r"lidar.kind: 'zigzag' is not one of spinning"):
        sensor_settings("lidar", "vlp-16", {"kind": "zigzag"})
    with pytest.raises(UsdForestError, match=r"lidar.fov: must be in"):
        sensor_settings("lidar", "vux-1uav", {"fov": 0.0})
    with pytest.raises(UsdForestError, match=r"lidar.prism_rate_1/prism_rate_2"):
        sensor_settings("lidar", "livox-mid-40", {"prism_rate_1": 5.0, "prism_rate_2": 5.0})


def test_a_terrestrial_scanner_is_scanned_not_flown(ground, runner, tmp_path):
    from usdforest.sensors.platforms.survey import flight_settings

    with pytest.raises(UsdForestError, match=r"terrestrial scanner .* stands on its tripod"):
        flight_settings({"kind": "tls"})
    r = runner.invoke(app, ["fly", "x.usda", "--lidar", "vz-400", "--line", "0,0,1:1,0,1",
                            "-o", str(tmp_path / "f")])  # fmt: skip
    assert r.exit_code != 0 and "vz-400" in r.output


def _for_instance_reader(path):
    """The FOR-instance convention as a benchmark's loader reads it (TreeLearn and
    ForestFormer3D read the LAS ``classification`` and the extra dimension ``treeID``):
    0 unclassified, 1 low vegetation, 2 terrain, 3 out-points, 4 stem, 5 live branches,
    6 woody branches; treeID 0 no tree, 1..N one tree each."""
    import laspy

    las = laspy.read(str(path))
    assert las.header.version.major == 1 and las.header.version.minor == 4
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    return xyz, np.asarray(las.classification), np.asarray(las.treeID)


def test_a_drone_flight_writes_the_benchmarks_labels(forest_folder, runner, tmp_path):
    """A line scanner (its 330 degree line, as on a car or a low drone) flown 3 m above the
    ground beside a beech and a pine with ``--labels for-instance``: stem,
    live and woody branch points carry their tree's treeID (its trees.csv id + 1), every stem
    point lies within its tree's trunk of that tree's leaning axis (trees.csv's base and
    breast-height point), terrain and low vegetation carry none."""
    import csv

    text = beech_and_pine(1) + '[ground]\nkind = "plane"\nmargin = 5.0\n'
    forest, _ = forestcache.text_forest(forest_folder, "beech-pine-ground", text)
    plan = tmp_path / "drone.toml"
    plan.write_text("[lidar]\npulse_rate = 100000.0\nbeam_rings = 0\nnoise = false\n")
    out = tmp_path / "drone"
    args = ["fly", str(forest), "--lidar", "vux-1uav", "--config", str(plan), "--line",
            "0,4,3:20,4,3", "--speed", "10", "--labels", "for-instance", "--sonar",
            "none"]  # fmt: skip
    r = runner.invoke(app, [*args, "-o", str(out), "--json"])
    assert r.exit_code == 0, r.output
    xyz, cls, tree_id = _for_instance_reader(tmp_path / "drone.las")
    assert set(np.unique(cls)) <= {0, 1, 2, 4, 5, 6} and {2, 4, 5, 6} <= set(np.unique(cls))
    on_tree = np.isin(cls, [4, 5, 6])
    assert np.all(tree_id[on_tree] > 0) and np.all(tree_id[~on_tree] == 0)
    with open(forest.parent / "beech-pine-ground_assets" / "trees.csv") as f:
        trees = {int(row["id"]): row for row in csv.DictReader(f)}
    assert set(np.unique(tree_id[on_tree]) - 1) <= set(trees)
    stem = np.flatnonzero(cls == 4)
    assert stem.size > 100
    for i in stem:
        t = trees[int(tree_id[i]) - 1]
        base = np.array([float(t[a]) for a in "xyz"])
        axis = np.array([float(t[f"{a}_bh"]) for a in "xyz"]) - base
        axis /= np.linalg.norm(axis)
        off = xyz[i] - base
        d = float(np.linalg.norm(off - (off @ axis) * axis))
        # the trunk's widest at the foot: the stump diameter 1.3-1.45 DBH (Laasasenaho 1975,
        # 2 + 1.25 DBH cm), out of round by a few percent
        assert d <= float(t["dbh"]) / 2 * 1.7 + 0.02, (i, t["id"], d)


def test_the_label_sets_are_one_list_and_bad_ones_are_refused(runner, tmp_path):
    from usdforest.cli.sensors import LAS_LABELS
    from usdforest.sensors.lidar.las import LABELS, for_instance_classes

    assert LAS_LABELS == LABELS
    r = runner.invoke(app, ["fly", "x.usda", "--labels", "semantic3d", "--line", "0,0,1:1,0,1",
                            "-o", str(tmp_path / "f")])  # fmt: skip
    assert (
        r.exit_code != 0 and "--labels: 'semantic3d' is not one of asprs, for-instance" in r.output
    )
    assert not list(tmp_path.iterdir())
    # every class of ours, on a tree and on none (a shrub's leaves are low vegetation)
    cls = np.array([CLASS_ID[c] for c in ("unknown", "trunk", "branch", "leaf", "ground",
                                          "dead_wood", "ground_vegetation")] * 2)  # fmt: skip
    tree = np.repeat([3, -1], 7)
    assert for_instance_classes(cls, tree).tolist() == [0, 4, 6, 5, 2, 1, 1, 0, 1, 1, 1, 2, 1, 1]

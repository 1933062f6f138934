"""Flights: Doppler on a moving sonar's echo against 2 v / c, a moving lidar's per-ray poses
against a wall, and a flight through a built forest read back with laspy."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from usdforest.cli import app
from usdforest.errors import UsdForestError
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.sensors.lidar.scanners import SpinningLidar
from usdforest.sensors.platforms.flight import Trajectory, fly_lidar, read_path
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.scene.scenetypes import Leaves
from usdforest.sensors.sonar.model import SonarConfig, chirp, echo_from_leaves
from usdforest.usd.forest import write_forest


def _disk(x: float) -> Leaves:
    return Leaves(
        np.array([[x, 0.0, 0.0]]),
        np.array([[-1.0, 0.0, 0.0]]),
        np.array([math.pi * 0.03**2]),
        np.array([0]),
    )


def _peak_frequency(x: np.ndarray, fs: float) -> float:
    """The frequency of the spectrum's peak (zero-padded FFT, parabolic interpolation)."""
    n = 1 << 21
    a = np.abs(np.fft.rfft(x, n))
    k = int(np.argmax(a))
    y0, y1, y2 = np.log(a[k - 1 : k + 2])
    return (k + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)) * fs / n


@pytest.mark.parametrize("v", [8.0, -6.0])
def test_a_moving_sonar_hears_the_doppler_shift_2v_over_c(v):
    """A long narrow-band call (69-71 kHz, 10 ms) and one disk 3 m ahead: approaching
    (v > 0) or receding, the echo's spectral peak moves by 2 v / c f, within 1 % of that."""
    cfg = SonarConfig(leaf_model="disk", f_min=69e3, f_max=71e3, call_duration=0.01)
    c = cfg.speed_of_sound
    rest = echo_from_leaves(_disk(3.0), Pose(0, 0, 0), cfg)
    moving = echo_from_leaves(_disk(3.0), Pose(0, 0, 0), cfg, velocity=np.array([v, 0, 0]))
    f0 = _peak_frequency(rest.echo, cfg.sample_rate)
    f1 = _peak_frequency(moving.echo, cfg.sample_rate)
    assert f0 == pytest.approx(70e3, rel=2e-3)
    assert f1 - f0 == pytest.approx(2 * v / c * f0, rel=0.01)
    # the transfer function keeps the disk's spectrum (only its delay moves; the band
    # interpolation of the delay histograms is good to about 1e-4)
    np.testing.assert_allclose(np.abs(moving.transfer), np.abs(rest.transfer), rtol=1e-3)
    assert chirp(cfg).size == round(cfg.call_duration * cfg.sample_rate)


def _envelope_peak(x: np.ndarray, fs: float) -> float:
    """The time of the analytic signal's envelope peak (parabolic interpolation)."""
    from scipy.signal import hilbert

    env = np.abs(hilbert(x))
    k = int(np.argmax(env))
    y0, y1, y2 = env[k - 1 : k + 2]
    return (k + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)) / fs


@pytest.mark.parametrize("v", [6.0, 8.0, -6.0, -8.0])
def test_a_moving_sonar_times_its_echo_where_the_platform_hears_it(v):
    """One disk 14 m ahead, the sonar flying towards it (v > 0) or away at 6 and 8 m/s: the
    wave meets the disk at r / c and then the platform, which has moved on, so the echo
    arrives at 2 r / (c + v), not 2 r / c (the issue's +24 / -33 cm of range). The echo's
    envelope peak (the call's own offset, measured at rest, compressed by the Doppler factor
    s = 1 + 2 v / c) lands there within 1 cm of range; the impulse response peaks there."""
    cfg = SonarConfig(leaf_model="disk", max_range=20.0)
    c, fs, r = cfg.speed_of_sound, cfg.sample_rate, 14.0
    rest = echo_from_leaves(_disk(r), Pose(0, 0, 0), cfg)
    moving = echo_from_leaves(_disk(r), Pose(0, 0, 0), cfg, velocity=np.array([v, 0, 0]))
    exact = 2 * r / (c + v)
    offset = _envelope_peak(rest.echo, fs) - 2 * r / c  # the call's envelope peak
    s = 1 + 2 * v / c
    heard = _envelope_peak(moving.echo, fs)
    assert abs(heard - (exact + offset / s)) * c / 2 < 0.01
    assert abs(heard - (2 * r / c + offset / s)) * c / 2 > 0.2  # what a platform at rest hears
    impulse = moving.t[np.argmax(np.abs(moving.impulse))]
    assert abs(impulse - exact) * c / 2 < 0.005


def _wall(tmp_path, d):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(tmp_path / "wall.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    wall = UsdGeom.Plane.Define(stage, "/Wall")
    wall.CreateAxisAttr("X")
    wall.CreateWidthAttr(200.0)
    wall.CreateLengthAttr(200.0)
    UsdGeom.XformCommonAPI(wall).SetTranslate((d, 0, 0))
    stage.SetDefaultPrim(wall.GetPrim())
    stage.Save()
    return tmp_path / "wall.usda"


def test_a_moving_lidar_fires_each_ray_from_where_the_platform_is(tmp_path):
    """Towards a wall 30 m ahead at 20 m/s: a ray fired at time t straight ahead meets the
    wall at 30 - 20 t; its GPS time is its sweep's start plus its azimuth's share."""
    scene = extract_scene(_wall(tmp_path, 30.0))
    traj = Trajectory.line((0, 0, 0), (10, 0, 0), 20.0)
    lidar = SpinningLidar(channels=1, vfov_min=0, vfov_max=0, azimuth_step=1.0, max_range=100)
    r = fly_lidar(scene, lidar, traj, rate=10.0)
    assert r.sweeps == 5 and r.n_rays == 5 * 360
    ahead = np.abs(r.points[:, 1]) < 1e-6
    sensor_x = 20.0 * r.gps_time[ahead]
    np.testing.assert_allclose(r.range[ahead], 30.0 - sensor_x, atol=1e-4)
    np.testing.assert_allclose(r.points[:, 0], 30.0, atol=1e-4)
    frac = (r.gps_time * 10.0) % 1.0  # share of the sweep = azimuth / 360
    az = np.degrees(np.arctan2(r.points[:, 1], r.points[:, 0] - 20.0 * r.gps_time)) % 360
    np.testing.assert_allclose(frac * 360, az, atol=1e-3)


def test_a_flight_through_a_built_forest_writes_las_and_sonar(tmp_path, runner):
    import laspy

    stand = tmp_path / "two.usda"
    pipe = default_recipe_path().parent / "paper-two-tree-stand.toml"
    write_forest(read_recipe(pipe), stand, thumbnail=False)
    out = tmp_path / "run"
    args = ["fly", str(stand), "--line", "1,2,1.5:9,2,1.5", "--speed", "8", "-o", str(out)]
    r = runner.invoke(app, [*args, "--sonar", "paper", "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    las = laspy.read(str(tmp_path / "run.las"))
    assert las.header.version.major == 1 and las.header.version.minor == 4
    assert len(las.points) == summary["lidar"]["returns"] > 1000
    assert las.gps_time.min() >= 0 and las.gps_time.max() <= 1.0 + 1e-9
    tree = np.asarray(las.tree_id)
    assert set(np.unique(tree[tree >= 0])) == {0, 1}  # both trees of the stand are hit
    cls = np.asarray(las.usdforest_class)
    assert {1, 3} <= set(np.unique(cls))  # trunk and leaf returns
    # vegetation by its height above the ground (the stand's ground is z = 0): low under 2 m,
    # medium under 5 m, high above (LAStools' lasheight: -classify_between 0.5 2 3, 2 5 4);
    # ground 2; the height is kept in its own dimension
    asprs, z = np.asarray(las.classification), np.asarray(las.z)
    assert np.all(np.abs(z[cls == 4]) < 0.01) and np.all(asprs[cls == 4] == 2)
    veg = np.isin(cls, [1, 2, 3])
    np.testing.assert_allclose(np.asarray(las.height)[veg], z[veg], atol=1e-3)
    expected = np.where(z[veg] < 2, 3, np.where(z[veg] < 5, 4, 5))
    clear = np.min(np.abs(z[veg][:, None] - [2.0, 5.0]), axis=1) > 1e-3  # z is kept to 0.1 mm
    assert np.array_equal(asprs[veg][clear], expected[clear]) and {3, 4} <= set(asprs[veg])
    # the header as the field writes it
    assert las.header.system_identifier == "Velodyne VLP-16"
    assert las.header.generating_software.startswith("usdforest ")
    assert las.header.file_source_id == 1
    assert las.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.WEEK_TIME
    # the VLP-16's dual mode: one or two returns per pulse (a pulse is its GPS time and
    # laser), numbered by range; some pulses through foliage give two
    pulse = np.unique(np.column_stack([las.gps_time, las.ring]), axis=0, return_inverse=True)[1]
    per = np.bincount(pulse.ravel())
    number, count = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    assert set(np.unique(per)) == {1, 2} and np.all(count == per[pulse.ravel()])
    assert np.all(np.sort(number[per[pulse.ravel()] == 2]) > 0)
    for k in (1, 2):  # each two-return pulse holds return 1 and return 2
        assert np.sum(number[count == 2] == k) == np.sum(per == 2)
    assert np.sum(per == 2) >= 3
    # flight line 1, no CRS (the stage has none)
    assert np.all(las.point_source_id == 1) and not las.header.global_encoding.wkt
    assert np.mean(np.asarray(las.intensity) > 0) > 0.9  # the lidar equation (a wall test below)
    # every point's ring, azimuth and scan angle are the laser and direction it was fired
    # at, seen from where the trajectory file (an SBET record's fields) puts the platform at
    # the point's GPS time
    traj = np.genfromtxt(tmp_path / "run_trajectory.csv", delimiter=",", names=True)
    assert traj.dtype.names[:4] == ("time", "x", "y", "z") and len(traj.dtype.names) == 17
    assert traj["time"][0] == 0 and traj["time"][-1] == pytest.approx(1.0)
    np.testing.assert_allclose(traj["x"], 1 + 8 * traj["time"], atol=1e-6)
    np.testing.assert_allclose(traj["x_velocity"], 8.0, atol=1e-6)
    np.testing.assert_allclose(traj["heading"], 90.0, atol=1e-6)  # +x is east: 90 from north
    for k in ("roll", "pitch", "x_acceleration", "z_angular_rate"):
        np.testing.assert_allclose(traj[k], 0.0, atol=1e-6)
    gps = np.asarray(las.gps_time)
    at = np.column_stack([np.interp(gps, traj["time"], traj[k]) for k in "xyz"])
    d = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]) - at
    azimuth = np.degrees(np.arctan2(d[:, 1], d[:, 0]))  # heading +x: azimuth from forward
    assert np.all(np.abs((azimuth - np.asarray(las.azimuth) + 180) % 360 - 180) < 0.01)
    # ASPRS: the angle from straight down across the track, positive counter-clockwise seen
    # from behind facing along it: towards the right, which is -y when heading +x
    down = np.degrees(np.arctan2(-d[:, 1], -d[:, 2]))
    scan = np.asarray(las.scan_angle) * 0.006
    assert np.all(np.abs((down - scan + 180) % 360 - 180) < 0.01)
    elevation = np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
    ring = np.asarray(las.ring)
    assert set(np.unique(ring)) <= set(range(16)) and len(np.unique(ring)) > 8
    np.testing.assert_allclose(elevation, np.linspace(-15, 15, 16)[ring], atol=0.01)
    pulses = np.load(tmp_path / "run_sonar.npz")
    assert pulses["echoes"].shape[0] == summary["sonar"]["pulses"] == 21  # 1 s at 20/s
    np.testing.assert_allclose(pulses["velocity"][:, 0], 8.0)
    parts = {k for k in pulses.files if k.startswith("echoes_")}
    assert {"echoes_leaf", "echoes_trunk", "echoes_branch"} <= parts
    total = sum(pulses[k].astype(float) for k in parts)
    np.testing.assert_allclose(total, pulses["echoes"], atol=1e-6 * np.abs(pulses["echoes"]).max())
    labels = pulses["labels"]
    assert set(np.unique(labels["pulse"])) <= set(range(21))
    assert set(np.unique(labels["tree"][labels["tree"] >= 0])) == {0, 1}
    assert (tmp_path / "run_sonar.wav").stat().st_size > 1000
    assert (tmp_path / "run_sonar.png").stat().st_size > 1000
    # again without --force: refused, nothing changed
    r = runner.invoke(app, args)
    assert r.exit_code != 0 and "exists" in r.output


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("t,x,y\n0,0,0\n1,1,1\n", "needs columns t,x,y,z"),
        ("t,x,y,z\n0,0,0,0\n0,1,1,1\n", "strictly increasing"),
        ("t,x,y,z\n0,0,0,0\n", "at least two poses"),
        ("t,x,y,z\n0,0,0,0\n1,a,0,0\n", "could not convert"),
    ],
)
def test_bad_paths_are_refused(tmp_path, text, fragment):
    p = tmp_path / "p.csv"
    p.write_text(text)
    with pytest.raises(UsdForestError, match=fragment):
        read_path(p)


def test_a_short_flight_through_the_default_forest_writes_every_output(tmp_path, runner, shipped):
    """The embedded default forest, 4 m at 4 m/s and 2 m up with all three sensors: a LAS
    that laspy reads with one point per return, sonar pulses whose class echoes add up, a
    WAV, an echogram, camera frames and a contact sheet."""
    import laspy

    forest, _ = shipped("default")
    cfg = tmp_path / "sensors.toml"
    cfg.write_text("[sonar]\npulse_rate = 4.0\nbands = 16\n[camera]\nwidth = 64\nheight = 48\n")
    out = tmp_path / "run"
    r = runner.invoke(
        app,
        ["fly", str(forest), "--line", "26,68,2:30,68,2", "--speed", "4", "-o", str(out),
         "--sonar", "paper",
         "--camera", "pinhole-640", "--camera-rate", "2", "--config", str(cfg), "--json"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    names = sorted(p.name for p in tmp_path.glob("run*"))
    assert names == [
        "run.las",
        "run_camera.npz",
        "run_camera.png",
        "run_sonar.npz",
        "run_sonar.png",
        "run_sonar.wav",
        "run_trajectory.csv",
    ]
    las = laspy.read(str(tmp_path / "run.las"))
    assert len(las.points) == summary["lidar"]["returns"] > 10_000
    assert len(np.unique(np.asarray(las.tree_id)[np.asarray(las.tree_id) >= 0])) > 5
    sonar = np.load(tmp_path / "run_sonar.npz")
    assert sonar["echoes"].shape[0] == summary["sonar"]["pulses"] == 5
    parts = [k for k in sonar.files if k.startswith("echoes_")]
    assert {
        "echoes_leaf",
        "echoes_ground_vegetation",
        "echoes_trunk",
        "echoes_branch",
        "echoes_dead_wood",
        "echoes_ground",
    } == set(parts)
    np.testing.assert_allclose(
        sum(sonar[k].astype(float) for k in parts),
        sonar["echoes"],
        atol=1e-6 * np.abs(sonar["echoes"]).max(),
    )
    frames = np.load(tmp_path / "run_camera.npz")
    assert frames["depth"].shape == (3, 48, 64) == (summary["camera"]["frames"], 48, 64)


def test_a_flight_reports_progress_and_an_interrupted_one_leaves_nothing(
    tmp_path, runner, monkeypatch
):
    """Progress lines name each sensor's work with its count (the sonar only when asked for:
    it is off by default); Ctrl-C during the sonar, after the lidar has finished, leaves no
    LAS, no sonar files and no staging folder."""
    import usdforest.sensors.platforms.flight as flight

    stand = tmp_path / "two.usda"
    pipe = default_recipe_path().parent / "paper-two-tree-stand.toml"
    write_forest(read_recipe(pipe), stand, thumbnail=False)
    args = ["fly", str(stand), "--line", "1,2,1.5:9,2,1.5", "--speed", "8"]
    r = runner.invoke(app, [*args, "-o", str(tmp_path / "a")])
    assert r.exit_code == 0, r.output
    assert "lidar sweeps: 10/10" in r.stderr and "sonar" not in r.stderr
    # the work before the first sweep and after the last shows too
    for stage in ("tree prototypes: 2/2", "ray-casting scene:", "writing outputs: 1/1"):
        assert stage in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.glob("a*")) == ["a.las", "a_trajectory.csv"]
    r = runner.invoke(app, [*args, "-o", str(tmp_path / "b"), "--sonar", "paper", "-q"])
    assert r.exit_code == 0 and r.stderr == ""
    assert len(list(tmp_path.glob("b_sonar.*"))) == 3

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(flight, "fly_sonar", interrupted)
    r = runner.invoke(app, [*args, "-o", str(tmp_path / "c"), "--sonar", "paper"])
    assert r.exit_code != 0 and "Traceback" not in r.stderr
    assert "lidar sweeps: 10/10" in r.stderr  # the lidar had finished
    assert not list(tmp_path.glob("c*")) and not list(tmp_path.glob(".c*"))


def test_a_near_leaf_among_far_ones_keeps_its_delay_when_moving():
    """One Doppler group (``doppler_bins = 1``) holding a disk 0.3 m ahead and ten 9 m
    ahead, the sonar closing at 8 m/s: every echo inside the window (none placed before
    t = 0), the near disk's impulse peak at 2 r / (c + v) within 1 mm of range."""
    cfg = SonarConfig(leaf_model="disk", doppler_bins=1)
    c, v = cfg.speed_of_sound, 8.0
    xs = np.array([0.3] + [9.0] * 10)
    ys = np.r_[0.0, np.linspace(-0.5, 0.5, 10)]
    leaves = Leaves(
        np.column_stack([xs, ys, np.zeros(11)]),
        np.tile([-1.0, 0.0, 0.0], (11, 1)),
        np.full(11, math.pi * 0.03**2),
        np.zeros(11, np.int64),
    )
    e = echo_from_leaves(leaves, Pose(0, 0, 0), cfg, velocity=np.array([v, 0, 0]))
    assert np.all(np.isfinite(e.echo)) and np.abs(e.echo).max() > 0
    near = e.t < 0.5 * (2 * 0.3 / c + 2 * 9.0 / c)
    t = e.t[near][np.argmax(np.abs(e.impulse[near]))]
    assert abs(t - 2 * 0.3 / (c + v)) * c / 2 < 1e-3


def test_lidar_intensity_follows_the_lidar_equation_on_a_wall(tmp_path):
    """A plane 10 m ahead, unlabelled (reflectance 0.5), scanned by a VLP-16: each return's
    intensity is 65,535 x 0.5 x cos(incidence) / r^2, with cos = 10 / r for a wall facing the
    sensor (written here from the geometry, not from the hit normals), within 1 count; the
    exact cloud (``noise = False``)."""
    from dataclasses import replace

    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.lidar.scanners import scan

    scene = extract_scene(_wall(tmp_path, 10.0))
    r = scan(scene, replace(PRESETS["vlp-16"], noise=False), Pose(0, 0, 0))
    assert len(r) > 5000
    dist = np.linalg.norm(r.points, axis=1)
    expected = 65535 * 0.5 * (10.0 / dist) / dist**2
    assert np.abs(r.intensity.astype(float) - expected).max() <= 1.0
    assert r.intensity.max() == 328  # head-on: 65,535 x 0.5 / 100, and less obliquely


def test_a_start_time_gives_adjusted_standard_gps_time(tmp_path, runner):
    """LAS 1.4: "standard GPS Time (satellite GPS Time) minus 1 x 10^9" with the global
    encoding's bit 0 set: seconds since 1980-01-06 00:00:00 UTC plus the 18 leap seconds GPS
    has gained by 2017 (GPS time at 2017-01-01 00:00:00 UTC is 1,167,264,018 s)."""
    from datetime import UTC, datetime

    import laspy

    from usdforest.sensors.lidar.gpstime import gps_seconds, parse_utc
    from usdforest.sensors.lidar.las import write_las
    from usdforest.sensors.platforms.flight import write_trajectory

    assert gps_seconds(parse_utc("2017-01-01T00:00:00Z")) == 1_167_264_018
    assert gps_seconds(parse_utc("2016-12-31T23:59:59Z")) == 1_167_264_016  # before the leap
    scene = extract_scene(_wall(tmp_path, 30.0))
    traj = Trajectory.line((0, 0, 0), (10, 0, 0), 20.0)
    lidar = SpinningLidar(channels=1, vfov_min=0, vfov_max=0, azimuth_step=1.0, max_range=100)
    r = fly_lidar(scene, lidar, traj, rate=10.0)
    start = "2026-06-21T12:00:00+02:00"  # 10:00 UTC
    write_las(r, tmp_path / "f.las", start_time=start)
    write_trajectory(traj, tmp_path / "f.csv", start_time=start)
    las = laspy.read(str(tmp_path / "f.las"))
    epoch = datetime(2026, 6, 21, 10, tzinfo=UTC) - datetime(1980, 1, 6, tzinfo=UTC)
    t0 = epoch.total_seconds() + 18 - 1e9
    assert las.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    np.testing.assert_allclose(np.asarray(las.gps_time), t0 + r.gps_time, atol=1e-6)
    csv = np.genfromtxt(tmp_path / "f.csv", delimiter=",", names=True)
    assert csv["time"][0] == pytest.approx(t0, abs=1e-6)
    assert las.header.system_identifier == "OTHER"  # a lidar without a model name
    for bad, words in (("yesterday", "not an ISO 8601 time"), ("2026-06-21T10:00", "no time zone"),
                       ("1970-01-01T00:00:00Z", "before the GPS epoch")):  # fmt: skip
        r = runner.invoke(app, ["fly", str(tmp_path / "wall.usda"), "--line", "0,0,1:1,0,1",
                                "-o", str(tmp_path / "x"), "--start-time", bad])  # fmt: skip
        assert r.exit_code == 2 and words in r.stderr and "Traceback" not in r.output, r.output
        assert not list(tmp_path.glob("x*"))

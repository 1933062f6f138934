"""Wind: the trees' sway as time samples in a layer over the static forest, measured on the
composed stage against the cantilever and drag formulas written here, and sensors that scan
the forest at a time."""

from __future__ import annotations

import functools
import math
import subprocess
import sys
import tomllib
from pathlib import Path

import measure
import numpy as np
import pytest
import trimesh
from pxr import Sdf, Usd, UsdGeom
from scipy.spatial import ConvexHull
from stands import build_text, slice_middles

from usdforest import api
from usdforest.errors import RecipeError, UsdForestError
from usdforest.recipe import parse_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.stats import stage_info
from usdforest.usd.validate import validate

# two allometric Scots pines 20 m apart along y = 20; the wind blows from the west (+x)
TWO_PINES = """
seed = 5
[region]
bounds = [0.0, 0.0, 40.0, 40.0]
[[sites]]
x = 10.0
y = 20.0
species = "pine"
dbh = 0.30
height = 22.0
[[sites]]
x = 30.0
y = 20.0
species = "pine"
dbh = 0.30
height = 22.0
[species.pine]
preset = "scots-pine"
"""
RHO_AIR = 1.204  # kg/m³
E, RHO_WOOD = 8.0e9, 900.0  # the defaults: green wood


def _recipe(text: str, base: Path):
    return parse_recipe(tomllib.loads(text), base, "wind.toml")


def _build(root: Path, name: str, wind: str | None) -> Path:
    return build_text(root, name, TWO_PINES + (f"[wind]\n{wind}\n" if wind is not None else ""))


@pytest.fixture(scope="module")
def forests(tmp_path_factory):
    root = tmp_path_factory.mktemp("wind")
    return {
        "still": _build(root, "still", None),
        "steady8": _build(root, "steady8", "speed = 8.0\ngustiness = 0.0\nduration = 2\nfps = 5"),
        "steady4": _build(root, "steady4", "speed = 4.0\ngustiness = 0.0\nduration = 2\nfps = 5"),
        "gusty": _build(root, "gusty", "speed = 8.0\ngustiness = 0.05\nduration = 400\nfps = 4"),
        "calm": _build(root, "calm", "speed = 0.0\nduration = 2\nfps = 5"),
    }


def _instancer(stage: Usd.Stage) -> UsdGeom.PointInstancer:
    return UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))


# _tops, _measured_pine and _scan read a built stage and give the same answer each time:
# each is worked out once per stage (and its arrays made read-only) for every test asking
@functools.cache
def _tops(path: Path, height: float) -> np.ndarray:
    """``(time codes, trees, 3)``: each stem top's displacement from its base, from the
    composed instance transforms at every time code."""
    stage = Usd.Stage.Open(str(path))
    pi = _instancer(stage)
    out = []
    for t in range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1):
        m = np.asarray(pi.ComputeInstanceTransformsAtTime(t, t), dtype=float)
        top = np.array([0.0, 0.0, height, 1.0]) @ m
        out.append(top[:, :3] - m[:, 3, :3])
    out = np.array(out)
    out.setflags(write=False)
    return out


@functools.cache
def _measured_pine(path: Path) -> dict:
    """The pines measured here on their prototype, times their instance scale: height
    (bounds), DBH (a girth tape at 1.3 m round the trunk mesh, trimesh's section), crown
    silhouette (the leaves' 5th height percentile to
    the top, twice their 95th radial percentile wide, an ellipse) and crown centre (the
    leaves' mean height)."""
    stage = Usd.Stage.Open(str(path))
    proto = stage.GetPrimAtPath(_instancer(stage).GetPrototypesRel().GetTargets()[0])
    cache = UsdGeom.XformCache()
    inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(proto), dtype=float))
    leaves, trunk = [], None
    for p in Usd.PrimRange(proto, Usd.TraverseInstanceProxies()):
        purpose = p.GetAttribute("purpose")
        if purpose and purpose.Get() in ("proxy", "guide"):
            continue
        to = np.asarray(cache.GetLocalToWorldTransform(p), dtype=float) @ inv
        if p.IsA(UsdGeom.PointInstancer) and "/Leaves" in str(p.GetPath()):
            m = np.asarray(UsdGeom.PointInstancer(p).ComputeInstanceTransformsAtTime(0, 0))
            leaves.append(m[:, 3, :3] @ to[:3, :3] + to[3, :3])
        elif p.IsA(UsdGeom.Mesh) and "/Trunk" in str(p.GetPath()) and trunk is None:
            mesh = UsdGeom.Mesh(p)
            v = np.asarray(mesh.GetPointsAttr().Get(), dtype=float) @ to[:3, :3] + to[3, :3]
            f = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
            trunk = trimesh.Trimesh(v, f, process=False)
    section = trimesh.intersections.mesh_plane(trunk, [0, 0, 1], [0, 0, 1.3]).reshape(-1, 3)
    hull = ConvexHull(section[:, :2])
    ring = section[hull.vertices, :2]
    dbh = np.linalg.norm(ring - np.roll(ring, 1, axis=0), axis=1).sum() / math.pi
    bbox = UsdGeom.BBoxCache(0, ["default", "render"], True).ComputeUntransformedBound(proto)
    height = bbox.ComputeAlignedRange().GetMax()[2]
    crown = np.concatenate(leaves)
    base = np.percentile(crown[:, 2], 5)
    width = 2 * np.percentile(np.hypot(crown[:, 0], crown[:, 1]), 95)
    s = float(_instancer(stage).GetScalesAttr().Get()[0][2])  # both trees' (the same size)
    return {
        "height": float(height) * s,
        "dbh": float(dbh) * s,
        "area": math.pi / 4 * width * (height - base) * s * s,
        "centre": float(crown[:, 2].mean()) * s,
    }


def _cantilever_frequency(dbh: float, height: float) -> float:
    # first mode of a uniform clamped-free Euler-Bernoulli beam of circular section:
    # w1 = (1.8751)² sqrt(E I / (mu L⁴)), I = pi d⁴ / 64, mu = rho pi d² / 4
    inertia, mu = math.pi * dbh**4 / 64, RHO_WOOD * math.pi * dbh**2 / 4
    return 1.875104**2 * math.sqrt(E * inertia / (mu * height**4)) / (2 * math.pi)


def _static_deflection(tree: dict, speed: float) -> float:
    """Top deflection of the cantilever under the crown's drag at its centre, the wind there
    below the canopy top by the exponential profile (a = 2.5; the tallest tree is the top)."""
    u = speed * math.exp(2.5 * (min(tree["centre"] / tree["height"], 1.0) - 1.0))
    force = 0.5 * RHO_AIR * 0.35 * tree["area"] * u * u
    zc, h = tree["centre"], tree["height"]
    return force * zc**2 * (3 * h - zc) / (6 * E * math.pi * tree["dbh"] ** 4 / 64)


def test_the_wind_layer_composes_over_the_static_forest_and_validates(forests):
    still, windy = forests["still"], forests["gusty"]
    assets, wind_assets = still.parent / "still_assets", windy.parent / "gusty_assets"
    # the stand's layers are the still forest's, byte for byte; its trees are too in still
    # air, and in a wind that sways their branches they hold the same geometry with each
    # limb in a group of its own (test_limbsway)
    calm_assets = forests["calm"].parent / "calm_assets"
    for name in ("instances.usdc", "colliders.usdc"):
        assert (assets / name).read_bytes() == (wind_assets / name).read_bytes()
    trees = sorted((assets / "trees").iterdir())
    names = sorted(p.name for p in (wind_assets / "trees").iterdir())
    assert trees and [t.name for t in trees] == names
    for tree in trees:
        assert tree.read_bytes() == (calm_assets / "trees" / tree.name).read_bytes()
        grouped = wind_assets / "trees" / tree.name
        assert tree.read_bytes() != grouped.read_bytes()
        a, b = stage_info(tree, full=True), stage_info(grouped, full=True)
        assert (a["triangles"], a["leaves"]) == (b["triangles"], b["leaves"])
        np.testing.assert_allclose(
            measure.composed_bounds(Usd.Stage.Open(str(tree))),
            measure.composed_bounds(Usd.Stage.Open(str(grouped))),
            atol=1e-5,
        )
    layer = Sdf.Layer.FindOrOpen(str(windy))
    assert layer.subLayerPaths[0] == "./gusty_assets/wind.usdc"
    assert (layer.timeCodesPerSecond, layer.startTimeCode, layer.endTimeCode) == (4, 0, 1600)
    # muted, the still forest; unmuted at its default time, too
    stage, still_stage = Usd.Stage.Open(str(windy)), Usd.Stage.Open(str(still))
    static = np.asarray(
        _instancer(still_stage).ComputeInstanceTransformsAtTime(
            Usd.TimeCode.Default(), Usd.TimeCode.Default()
        )
    )
    default = _instancer(stage).ComputeInstanceTransformsAtTime(
        Usd.TimeCode.Default(), Usd.TimeCode.Default()
    )
    assert np.array_equal(np.asarray(default), static)
    stage.MuteLayer(str(wind_assets / "wind.usdc"))
    muted = _instancer(stage).ComputeInstanceTransformsAtTime(5, 5)
    assert np.array_equal(np.asarray(muted), static)
    assert validate(windy) == []
    # the swaying trees stay inside the instancer's extent at every time code
    stage = Usd.Stage.Open(str(windy))
    lo, hi = np.asarray(_instancer(stage).GetExtentAttr().Get(), dtype=float)
    tops = _tops(windy, _measured_pine(windy)["height"])
    base = np.asarray(_instancer(stage).GetPositionsAttr().Get(), dtype=float)
    swayed = tops[..., :2] + base[:, :2]
    assert np.all(swayed >= lo[:2]) and np.all(swayed <= hi[:2])


def test_a_steady_wind_bends_each_tree_as_the_cantilever_under_its_crowns_drag(forests):
    tree = _measured_pine(forests["steady8"])
    expected = _static_deflection(tree, 8.0)
    for name, speed in (("steady8", 8.0), ("steady4", 4.0)):
        tops = _tops(forests[name], tree["height"])
        along = tops[..., 0]  # the wind blows towards +x
        np.testing.assert_allclose(along, expected * (speed / 8.0) ** 2, rtol=0.02)
        np.testing.assert_allclose(tops[..., 1], 0.0, atol=1e-6)
    # 8 m/s bends a 22 m, 30 cm pine by centimetres, not metres (a plausibility bound)
    assert 0.02 < expected < 0.3
    # the deflection is the drag's: four times at twice the speed, exactly
    ratio = (
        _tops(forests["steady8"], tree["height"])[..., 0]
        / _tops(forests["steady4"], tree["height"])[..., 0]
    )
    np.testing.assert_allclose(ratio, 4.0, rtol=1e-5)


def test_gusts_sway_a_tree_at_its_cantilever_frequency_by_the_predicted_amount(forests):
    path = forests["gusty"]
    tree = _measured_pine(path)
    f0 = _cantilever_frequency(tree["dbh"], tree["height"])
    stage = Usd.Stage.Open(str(path))
    stored = _instancer(stage).GetPrim().GetAttribute("usdforest:swayFrequency").Get()
    np.testing.assert_allclose(stored, f0, rtol=0.01)
    assert 0.15 < f0 < 0.4  # Scots pines of this size sway at 0.2-0.3 Hz
    x = _tops(path, tree["height"])[:-1, 0, 0]  # one period of the loop, along the wind
    fps, n = 4.0, len(x)
    f = np.fft.rfftfreq(n, 1 / fps)
    power = np.abs(np.fft.rfft(x - x.mean())) ** 2
    # the model's spectrum: von Kármán gusts (L = 20 m) through the drag's linear term and a
    # damped oscillator (zeta = 0.1)
    scale = 20.0 / 8.0
    gusts = 4 * scale / (1 + 70.8 * (f * scale) ** 2) ** (5 / 6)
    w, w0 = 2 * math.pi * f, 2 * math.pi * f0
    gain = w0**4 / ((w0**2 - w**2) ** 2 + (2 * 0.1 * w0 * w) ** 2)
    model = gain * gusts
    # the resonance's centre (power-weighted mean frequency within 30 % of f0) is the
    # model's, whose peak is f0's (the gusts' falling spectrum pulls both down a little)
    near = (f > 0.7 * f0) & (f < 1.3 * f0)
    centre = np.sum(f[near] * power[near]) / np.sum(power[near])
    assert centre == pytest.approx(np.sum(f[near] * model[near]) / np.sum(model[near]), rel=0.01)
    assert f[near][np.argmax(model[near])] == pytest.approx(f0, rel=0.03)
    # the sway's standard deviation: 2 g times the mean deflection (the drag's linear term)
    # through the oscillator, over the bins the gusts fill (not the mean, not Nyquist's)
    fill = slice(1, n // 2)
    through = math.sqrt(np.sum(model[fill]) / np.sum(gusts[fill]))
    sd = 2 * 0.05 * _static_deflection(tree, 8.0) * through
    assert x.std() == pytest.approx(sd, rel=0.1)


def test_gusts_cross_the_stand_with_the_wind(forests):
    """Taylor's frozen turbulence: the downwind pine sways as the upwind one did 20 m / 8 m/s
    = 2.5 s (10 time codes) earlier."""
    tops = _tops(forests["gusty"], _measured_pine(forests["gusty"])["height"])[:-1]
    upwind, downwind = tops[:, 0, :2], tops[:, 1, :2]
    np.testing.assert_allclose(downwind, np.roll(upwind, 10, axis=0), atol=2e-4)
    assert not np.allclose(downwind, upwind, atol=2e-3)


@functools.cache
def _scan(path: Path, time: float | None):
    """The noiseless lidar's scan from (20, 20, 12) at ``time``: its sorted points and its
    warnings."""
    done = api.scan(path, "lidar", (20.0, 20.0, 12.0), settings={"noise": False}, time=time)
    points = np.sort(np.round(np.asarray(done.result.points, dtype=float), 6), axis=0)
    points.setflags(write=False)
    return points, done.warnings


def _leaf_points(path: Path, time: float | None) -> np.ndarray:
    return _scan(path, time)[0]


def test_a_lidar_sees_the_trees_move_in_wind_and_stand_still_in_calm_air(forests):
    windy = [_leaf_points(forests["gusty"], t) for t in (0.0, 3.0)]
    assert len(windy[0]) > 1000
    assert windy[0].shape != windy[1].shape or not np.array_equal(*windy)
    calm = [_leaf_points(forests["calm"], t) for t in (0.0, 0.3)]
    assert np.array_equal(*calm)
    # still air sways nothing: the calm forest at any time is the still forest
    assert np.array_equal(calm[0], _leaf_points(forests["still"], None))


def test_a_scan_at_a_time_outside_the_loop_sees_its_time_in_the_loop(forests):
    """The wind layer loops (its last time code is its first): a scan 400 s (its duration)
    later or earlier sees the forest as at 3 s, as a flight's pulses do, not the forest
    that USD holds at its first or last time code."""
    at = _leaf_points(forests["gusty"], 3.0)
    for t in (403.0, -397.0, 1203.0):
        np.testing.assert_array_equal(_leaf_points(forests["gusty"], t), at)
    assert not np.array_equal(_leaf_points(forests["gusty"], 400.0 - 1e-9), at)
    # and says so, as a time given to a forest that does not move (the scans' own warnings)
    assert _scan(forests["gusty"], 403.0)[1] == (
        "time: 403 s is outside the stage's loop of 400 s from 0 s: scanned at 3 s",
    )
    assert _scan(forests["gusty"], 3.0)[1] == ()
    assert _scan(forests["still"], 3.0)[1] == (
        "time: the stage has no animation (no time codes): scanned as it stands",
    )


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("speed = -1", r"wind\.speed: -1 is outside 0 to 60"),
        ("gustiness = 2", r"wind\.gustiness: 2 is outside 0 to 1"),
        ("fps = 0", r"wind\.fps: 0 must be above 0 and at most 240$"),
        ("duration = 0", r"wind\.duration: 0 must be above 0 and at most 3600$"),
        ("gusts = 1", r"wind: unknown key 'gusts'"),
        ("speed = 'fast'", r"wind\.speed"),
    ],
)
def test_the_recipe_checks_its_wind_table(tmp_path, table, message):
    with pytest.raises(RecipeError, match=message):
        _recipe(TWO_PINES + f"[wind]\n{table}\n", tmp_path)


def test_a_tiled_recipe_sways_built_as_one_layer_and_is_refused_in_tiles(tmp_path, forests):
    """A tiled recipe's wind is written when it is built ``untiled``: the same wind layer, to
    the byte, as the recipe without its tiles; built in tiles it is refused before anything
    is written, in one line that says how (CLI and API alike)."""
    windy = TWO_PINES + "[wind]\nspeed = 8\nduration = 2\nfps = 10\n"
    tiled = _recipe(windy + "[tiles]\nsize = 20\n", tmp_path)
    api.build_forest(tiled, tmp_path / "a" / "f.usda", thumbnail=False, untiled=True)
    write_forest(_recipe(windy, tmp_path), tmp_path / "b" / "f.usda", thumbnail=False)
    a, b = (tmp_path / x / "f_assets" / "wind.usdc" for x in "ab")
    assert a.read_bytes() == b.read_bytes()
    stage = Usd.Stage.Open(str(tmp_path / "a" / "f.usda"))
    trees = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    assert len(trees.GetOrientationsfAttr().GetTimeSamples()) == 21
    assert validate(tmp_path / "a" / "f.usda") == []
    with pytest.raises(UsdForestError, match=r"wind: a tiled forest sways only as one layer"):
        api.build_forest(tiled, tmp_path / "c" / "f.usda", thumbnail=False)
    (tmp_path / "r.toml").write_text(windy + "[tiles]\nsize = 20\n")
    cmd = [sys.executable, "-m", "usdforest", "build", "d.usda", "-p", "r.toml", "-q"]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert run.returncode == 2, run.stderr
    assert run.stderr.strip().splitlines() == [
        "error: r.toml: wind: a tiled forest sways only as one layer; build it with --untiled "
        "(untiled=True in the API), or remove [tiles] or [wind]"
    ]
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a", "b", "r.toml"]


def test_a_wind_layer_too_large_for_its_limbs_is_refused_before_anything_is_written(
    tmp_path, monkeypatch
):
    """The limit on the layer's samples counts the limbs' turns as well as the trees' tilts
    (a pine's 22 swaying limbs took 16 bytes a limb a time code, 15x its tree's 24): two
    pines whose tilts fit the limit and whose limbs do not are refused once their trees
    have grown, naming both and the size, and nothing is left."""
    import re

    from usdforest.usd import wind

    frames = 60 * 30 + 1
    monkeypatch.setattr(wind, "MAX_SAMPLE_BYTES", 2 * 24 * frames * 4)  # 4x the tilts
    recipe = _recipe(TWO_PINES + "[wind]\nduration = 60\nfps = 30\n", tmp_path)
    with pytest.raises(UsdForestError) as caught:
        write_forest(recipe, tmp_path / "out" / "f.usda", thumbnail=False)
    message = str(caught.value)
    got = re.fullmatch(
        r"wind: 2 trees and up to ([\d,]+) swaying limbs x 1,801 time codes would take "
        r"([\d.]+) MiB of samples \(at most 0\.3 MiB\); lower wind\.duration or wind\.fps",
        message,
    )
    assert got, message
    limbs = int(got[1].replace(",", ""))
    assert limbs > 20  # every first-order branch of the pine asset
    want = frames * (2 * 24 + limbs * 16) / 2**20
    assert float(got[2]) == pytest.approx(want, abs=0.05)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    # without branch sway no limb is counted: the tilts fit
    calm = _recipe(TWO_PINES + "[wind]\nduration = 60\nfps = 30\nbranch_sway = false\n",
                   tmp_path)  # fmt: skip
    write_forest(calm, tmp_path / "calm" / "f.usda", thumbnail=False)
    assert (tmp_path / "calm" / "f_assets" / "wind.usdc").is_file()


def test_build_and_info_say_how_long_the_forest_sways(tmp_path, forests):
    """``build --json`` reports the wind it wrote (seconds, frames a second, time codes,
    the layer's bytes) and ``info --json`` any stage's animation, as its root layer gives
    it; a still forest has none."""
    import json

    (tmp_path / "r.toml").write_text(TWO_PINES + "[wind]\nspeed = 7\nduration = 2\nfps = 5\n")
    cmd = [sys.executable, "-m", "usdforest", "build", "f.usda", "-p", "r.toml", "--json", "-q",
           "--no-thumbnail"]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=True)
    layer = tmp_path / "f_assets" / "wind.usdc"
    assert json.loads(run.stdout)["wind"] == {
        "seconds": 2.0,
        "fps": 5.0,
        "time_codes": 11,
        "speed": 7.0,
        "layer_bytes": layer.stat().st_size,
    }

    def info(stage: Path):
        cmd = [sys.executable, "-m", "usdforest", "info", str(stage), "--json", "-q"]
        run = subprocess.run(cmd, capture_output=True, text=True, check=True)
        return json.loads(run.stdout)["animation"]

    root = Sdf.Layer.FindOrOpen(str(tmp_path / "f.usda"))
    assert (root.startTimeCode, root.endTimeCode, root.timeCodesPerSecond) == (0, 10, 5)
    want = {"seconds": 2.0, "time_codes": 11, "time_codes_per_second": 5.0, "loops": True}
    assert info(tmp_path / "f.usda") == want
    assert info(forests["still"]) is None


def test_a_scan_refuses_a_time_that_is_no_number(tmp_path, forests):
    with pytest.raises(UsdForestError, match=r"time: expected a finite number"):
        api.scan(forests["calm"], "lidar", (20.0, 20.0, 12.0), time=float("nan"))
    out = tmp_path / "s.npz"
    cmd = [sys.executable, "-m", "usdforest", "scan", str(forests["calm"]), "--sensor",
           "lidar", "--pose", "20,20,12", "--time", "inf", "-o", str(out)]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True)
    assert run.returncode != 0 and not out.exists()
    assert run.stderr.strip().count("\n") == 0 and "--time" in run.stderr


def _hover(seconds: float, start: float = 0.0):
    """A platform hovering at (20, 20, 12), facing +x, from ``start`` to ``seconds``."""
    from usdforest.sensors.platforms.flight import Trajectory

    return Trajectory(
        np.array([start, seconds]), np.array([[20.0, 20.0, 12.0]] * 2), yaw=np.zeros(2),
        pitch=np.zeros(2), roll=np.zeros(2),
    )  # fmt: skip


def test_a_flight_sees_each_sweep_where_the_trees_sway_then(forests):
    """A hovering VLP-16 flown through the gusty forest: the sweep rolls, each slice of its
    azimuths a scan of the stage at the slice's middle (the trees moved between slices, by
    the wind layer's samples, and the flight reads them); in calm air every sweep is the
    still forest's."""
    import dataclasses

    from scipy.spatial import cKDTree

    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.scene.motion import animated

    assert animated(forests["gusty"]) and not animated(forests["still"])
    sensor = dataclasses.replace(PRESETS["vlp-16"], noise=False)
    rate, start, end = 10.0, 0.2, 0.45
    flown = api.fly(forests["gusty"], path=_hover(end, start), lidar=sensor, lidar_rate=rate)
    flown = flown.lidar
    sweep = np.floor((flown.gps_time - start) * rate + 1e-9).astype(int)
    assert sorted(set(sweep)) == [0, 1, 2]
    # each return's slice: the part of its sweep between the stage's time codes (4 a second)
    # about it; the first sweep (0.2 to 0.3 s) is cut at 0.25 s
    middle = slice_middles(flown.gps_time, rate, 4.0, start, end)
    assert len(np.unique(middle[sweep == 0])) == 2
    off_middle = []
    for k in (0, 2):
        times, count = np.unique(middle[sweep == k], return_counts=True)
        # the scan at the sweep's middle, one for both of its slices
        centre = start + (k + 0.5) / rate
        middle_scan = api.scan(
            forests["gusty"], "lidar", (20.0, 20.0, 12.0), settings=sensor, time=centre
        )
        middle_tree = cKDTree(middle_scan.result.points)
        for at in times[np.argsort(count)[-2:]]:
            mine = flown.points[middle == at]
            assert len(mine) > 100
            scanned = api.scan(
                forests["gusty"], "lidar", (20.0, 20.0, 12.0), settings=sensor, time=at
            )
            gap, _ = cKDTree(scanned.result.points).query(mine)
            assert gap.max() < 1e-5  # the slice's returns are the scan's at the slice's time
            off_middle.append(middle_tree.query(mine)[0].max())
    # the sweep's middle is not the slice's time: the trees moved in between
    assert max(off_middle) > 1e-4
    calm = api.fly(forests["calm"], path=_hover(0.25), lidar=sensor, lidar_rate=rate).lidar
    still = api.fly(forests["still"], path=_hover(0.25), lidar=sensor, lidar_rate=rate).lidar
    np.testing.assert_array_equal(calm.points, still.points)


def test_a_hover_of_a_tenth_of_a_second_is_one_sweep_wherever_it_starts(forests):
    """0.1 s from 2.5 s is 0.10000000000000009 s in floats: still one 10 Hz sweep, as from
    0.5 s (it made a second of pulses all fired at the end, every return twice); a hover
    truly longer than one sweep makes a second."""
    import dataclasses

    from usdforest.sensors.lidar.presets import PRESETS

    sensor = dataclasses.replace(PRESETS["vlp-16"], noise=False)
    one_sweep = sensor.directions().shape[0]
    for start, end, sweeps in ((0.5, 0.6, 1), (2.5, 2.6, 1), (2.5, 2.61, 2)):
        flown = api.fly(forests["calm"], path=_hover(end, start), lidar=sensor, lidar_rate=10.0)
        assert (flown.lidar.sweeps, flown.lidar.n_rays) == (sweeps, sweeps * one_sweep)


def test_a_flights_camera_frames_see_the_trees_at_their_own_times(forests, monkeypatch):
    """Each frame of a flight is the camera's scan at its time; the flight composes the
    stage once for its scene, its motion and its colours (each a full-detail open)."""
    import dataclasses

    import usdforest.usd.layers
    from usdforest.sensors.optics import camera
    from usdforest.sensors.platforms import survey
    from usdforest.sensors.scene import extraction as scene
    from usdforest.sensors.scene import motion

    opened = []
    real = usdforest.usd.layers.open_stage

    def counted(*args, **kwargs):
        opened.append(args[0])
        return real(*args, **kwargs)

    for module in (survey, scene, motion, usdforest.usd.layers):
        monkeypatch.setattr(module, "open_stage", counted)
    cam = dataclasses.replace(camera.PRESETS["pinhole-640"], width=96, height=72)
    frames = api.fly(
        forests["gusty"], path=_hover(0.25), lidar=None, camera=cam, camera_rate=10.0
    ).camera
    assert [Path(p) for p in opened] == [forests["gusty"]]
    monkeypatch.undo()
    assert len(frames.t) == 3
    depths = []
    for k, t in enumerate(frames.t):
        shot = api.scan(forests["gusty"], "camera", (20.0, 20.0, 12.0), settings=cam, time=t)
        np.testing.assert_allclose(frames.depth[k], shot.result.depth, atol=1e-4)
        depths.append(frames.depth[k])
    assert not np.allclose(depths[0], depths[2], atol=1e-3)


def test_leaves_move_with_their_swaying_trees_at_the_velocity_the_scene_gives(forests):
    """SceneMotion's leaf velocities at the middle of a time code's interval are the finite
    differences of the leaves' own positions, extracted anew at two times inside that interval
    (where USD interpolates each tree's tilt): within 1 % of the fastest."""
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.motion import SceneMotion

    stage, centre, radius = forests["gusty"], np.array([20.0, 20.0, 10.0]), 30.0
    t, dt = 10.125, 0.05  # the gusty forest has 4 time codes a second: 10.0 to 10.25 here
    still = extract_scene(stage, centre=centre, radius=radius)
    motion = SceneMotion(stage, still)
    now, before, after = (
        extract_scene(stage, centre=centre, radius=radius, time=s).leaves
        for s in (t, t - dt, t + dt)
    )
    # the still scene's leaves carried to t are those extracted at t
    carried = motion.leaves(t, still.leaves)
    np.testing.assert_allclose(carried.centre, now.centre, atol=1e-5)
    np.testing.assert_allclose(carried.normal, now.normal, atol=1e-5)
    assert np.abs(carried.centre - still.leaves.centre).max() > 1e-3
    expected = (after.centre - before.centre) / (2 * dt)
    fastest = float(np.abs(expected).max())
    assert fastest > 1e-3  # the crowns do move
    got = motion.velocities(t, now.centre, now.tree, now.carrier)
    np.testing.assert_allclose(got, expected, atol=0.01 * fastest)


def test_a_leaf_moving_towards_the_sonar_sounds_as_a_sonar_moving_towards_it():
    """Only the closing speed sets the Doppler: a leaf moving at 1 m/s towards a still sonar
    and a sonar moving at 1 m/s towards a still leaf give the same echo. Their delays differ
    at second order in v/c (2 r (c - v) / c² against 2 r / (c + v)), so the still leaf is
    placed that much nearer, by r v² / c² (0.03 mm at 3 m)."""
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.scenetypes import Leaves
    from usdforest.sensors.sonar.model import PRESETS, Targets, echo_from_targets

    cfg, pose = PRESETS["paper"], Pose(0.0, 0.0, 0.0)
    c = cfg.speed_of_sound

    def leaf(x: float) -> Leaves:
        return Leaves(
            np.array([[x, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]]), np.array([0.003]),
            np.array([0]),
        )  # fmt: skip

    moving_leaf = echo_from_targets(
        Targets(leaf(3.0), leaf_velocity=np.array([[-1.0, 0.0, 0.0]])), pose, cfg
    ).echo
    nearer = leaf(3.0 * (1 - 1 / c**2))
    moving_sonar = echo_from_targets(Targets(nearer), pose, cfg, np.array([1.0, 0.0, 0.0])).echo
    still = echo_from_targets(Targets(leaf(3.0)), pose, cfg).echo
    peak = np.abs(still).max()
    assert np.abs(moving_leaf - moving_sonar).max() < 1e-4 * peak
    assert np.abs(moving_leaf - still).max() > 0.1 * peak  # the Doppler is heard


def test_a_hovering_sonar_hears_the_swaying_crowns(forests):
    """The leaves' positions and velocities at each pulse's time reach the sonar's echoes in
    wind; in calm air its echoes are the still forest's, bit for bit."""
    echoes = {
        k: api.fly(forests[k], path=_hover(0.2), lidar=None, sonar="paper").sonar.echoes
        for k in ("gusty", "calm", "still")
    }
    assert len(echoes["still"]) == 5
    np.testing.assert_array_equal(echoes["calm"], echoes["still"])
    peak = np.abs(echoes["still"]).max()
    assert np.abs(echoes["gusty"] - echoes["still"]).max() > 1e-3 * peak


def test_the_wood_sways_with_its_tree_and_the_sonar_hears_it_there(forests):
    """The sonar's wood in wind: the pieces fitted on the still scene and carried to t are
    those fitted on the scene extracted at t, they move at the velocity their tree's motion
    gives them, and a pulse at t (leaves, wood and what hides them, all moved) is the pulse
    of the scene extracted at t when the reflectors' velocities are left out."""
    import functools

    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.motion import SceneMotion, leaves_at, wood_at
    from usdforest.sensors.sonar.model import SonarConfig, SonarScene
    from usdforest.sensors.sonar.wood import scene_cylinders

    stage, centre, radius = forests["gusty"], np.array([20.0, 20.0, 10.0]), 30.0
    t = 10.125  # between the time codes 40 and 41 (4 a second)
    still = extract_scene(stage, centre=centre, radius=radius)
    now = extract_scene(stage, centre=centre, radius=radius, time=t)
    motion = SceneMotion(stage, still)
    wood = scene_cylinders(still, 0.05)
    carried, fitted = motion.cylinders(t, wood), scene_cylinders(now, 0.05)
    assert len(carried) == len(fitted) and np.array_equal(carried.tree, fitted.tree)
    np.testing.assert_allclose(carried.centre, fitted.centre, atol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(carried.axis * fitted.axis, axis=1)), 1, atol=1e-5)
    assert np.abs(carried.centre - wood.centre).max() > 1e-3
    # the velocity of the wood: its tree's transform differenced over the time codes about t
    a, b = (motion.cylinders(s, wood).centre for s in (10.0, 10.25))
    chord = (b - a) / 0.25
    speed = motion.velocities(t, carried.centre, carried.tree, carried.carrier)
    np.testing.assert_allclose(speed, chord, atol=0.01 * np.abs(chord).max())
    # a pulse at t with everything moved, velocities left out, against the scene at t
    cfg = SonarConfig(occlusion=True, max_range=8.0)
    pose = Pose(14.0, 20.0, 6.0, 0.0, 10.0)

    def still_leaves(leaves):
        moved, _ = leaves_at(motion, t, leaves)
        return moved, None

    def still_wood(pieces):
        moved, _ = wood_at(motion, t, pieces)
        return moved, None

    prepared = SonarScene(still, cfg)
    heard = prepared.echo(
        pose, cfg, moved=still_leaves, wood_moved=still_wood,
        caster=prepared.caster.moved(motion.at(t)), reach=motion.reach(t),
    )  # fmt: skip
    want = SonarScene(now, cfg).echo(pose, cfg)
    assert heard.reflectors == want.reflectors
    assert heard.reflectors["trunk"] + heard.reflectors["branch"] > 10
    peak = np.abs(want.echo).max()
    np.testing.assert_allclose(heard.echo, want.echo, atol=1e-3 * peak)
    # and with their velocities, the wood's echo carries its Doppler: it differs
    moving = prepared.echo(
        pose, cfg, moved=functools.partial(leaves_at, motion, t),
        wood_moved=functools.partial(wood_at, motion, t),
        caster=prepared.caster.moved(motion.at(t)), reach=motion.reach(t),
    )  # fmt: skip
    assert np.abs(moving.parts["branch"] - heard.parts["branch"]).max() > 0

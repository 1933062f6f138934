"""Leaf flutter: a windy forest's leaves twisting and flapping about their petioles, stored as
a few shared rotations, read on the composed stage and by the sensors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom
from stands import beech_and_pine, build_text, slice_middles

from usdforest.errors import RecipeError
from usdforest.usd.validate import validate

# a beech beside a pine (whose shoots do not flutter); the wind at 10 m/s
STAND = beech_and_pine(3)
SPEED, DURATION, FPS, CLASSES, ANGLE, FREQUENCY = 10.0, 2.0, 24.0, 6, 20.0, 3.0
WIND = (
    f"[wind]\nspeed = {SPEED}\nduration = {DURATION}\nfps = {FPS}\nflutter_classes = {CLASSES}\n"
    f"flutter_angle = {ANGLE}\nflutter_frequency = {FREQUENCY}\n"
    # the leaves' own turns alone (the limbs' sway: test_limbsway)
    "branch_sway = false\n"
)
BEECH = "/Forest/Trees/Prototypes/Beech_0"
PINE = "/Forest/Trees/Prototypes/Pine_0"


@pytest.fixture(scope="module")
def stands(tmp_path_factory):
    root = tmp_path_factory.mktemp("flutter")
    return {
        "still": build_text(root, "still", STAND),
        "windy": build_text(root, "windy", STAND + WIND),
    }


@pytest.fixture(scope="module")
def rest_scene(stands):
    """The windy stand's sensor scene at its default time, uncached (scenes are frozen)."""
    from usdforest.sensors.scene.extraction import extract_scene

    return extract_scene(stands["windy"], cache=False)


def _leaf_instancers(stage: Usd.Stage, tree: str) -> list[UsdGeom.PointInstancer]:
    """The tree's leaf instancers: its own and each limb's."""
    return [
        UsdGeom.PointInstancer(p)
        for p in Usd.PrimRange(stage.GetPrimAtPath(tree))
        if p.IsA(UsdGeom.PointInstancer) and p.GetName() == "Leaves"
    ]


def _leaf_rows(stage: Usd.Stage, tree: str, time, limbs: bool = True) -> np.ndarray:
    """Each leaf's composed transform in its tree's space, its prototype's own transform
    (the flutter) included, as USD computes it, instancer by instancer (without ``limbs``:
    in its instancer's space, its limb's sway left out)."""
    cache = UsdGeom.XformCache(time)
    inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(stage.GetPrimAtPath(tree))))
    out = []
    for pi in _leaf_instancers(stage, tree):
        to_tree = np.asarray(cache.GetLocalToWorldTransform(pi.GetPrim()), dtype=float) @ inv
        if not limbs:
            to_tree = np.eye(4)
        rows = np.asarray(pi.ComputeInstanceTransformsAtTime(time, time), dtype=float)
        out.append(rows.reshape(-1, 4, 4) @ to_tree)
    return np.concatenate(out)


def _twist_and_flap(rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angles of R = Ry(flap) Rx(twist) (column vectors) from row-vector 3x3 ``rel``."""
    r = np.swapaxes(rel, -1, -2)
    return np.arctan2(-r[..., 1, 2], r[..., 1, 1]), np.arctan2(-r[..., 2, 0], r[..., 0, 0])


def test_leaves_flutter_about_their_petioles_as_pure_tones(stands):
    """Every beech leaf turns in its own frame about its petiole (its origin stays), by a
    twist about its midrib and half as much flap, each a sine at whole cycles of the loop
    with the amplitude flutter_angle (the wind is past 3.4 m/s, Beaufort 3, where the model
    stops growing it); the leaves fall into the classes."""
    stage = Usd.Stage.Open(str(stands["windy"]))
    rest = _leaf_rows(stage, BEECH, Usd.TimeCode.Default(), limbs=False)
    frames = int(DURATION * FPS)
    # every frame's rows in one call per instancer (USD's batch of the same computation: the
    # leaves carry no velocities, so the base time changes nothing; bit for bit
    # _leaf_rows(stage, BEECH, f, limbs=False), 4x quicker)
    codes = [Usd.TimeCode(float(f)) for f in range(frames + 1)]
    rows = np.concatenate(
        [
            np.array(pi.ComputeInstanceTransformsAtTimes(codes, codes[0]), dtype=float)
            for pi in _leaf_instancers(stage, BEECH)
        ],
        axis=1,
    )
    # the petiole stays where it was; the leaf turns about it, a rotation in its own frame
    np.testing.assert_allclose(
        rows[:, :, 3, :3], np.broadcast_to(rest[:, 3, :3], rows[:, :, 3, :3].shape), atol=1e-5
    )
    rel = rows[..., :3, :3] @ np.linalg.inv(rest[:, :3, :3])[None]
    np.testing.assert_allclose(
        rel @ np.swapaxes(rel, -1, -2), np.broadcast_to(np.eye(3), rel.shape), atol=2e-5
    )
    twist, flap = _twist_and_flap(rel)
    np.testing.assert_allclose(twist[0], twist[-1], atol=1e-6)  # the loop closes
    # one tone per leaf: the classes' distinct series
    series = np.unique(np.round(twist[:-1].T, 4), axis=0)
    assert len(series) == CLASSES
    amplitude = math.radians(ANGLE) * min(SPEED / 3.4, 1.0)
    for k, angle in enumerate((twist, flap)):
        spectrum = np.abs(np.fft.rfft(angle[:-1], axis=0)) * 2 / frames  # (bins, leaves)
        peak = spectrum.argmax(axis=0)
        assert spectrum.max(axis=0) == pytest.approx(amplitude / (1 + k), rel=1e-3)
        # everything at one frequency: the sine's
        share = spectrum.max(axis=0) ** 2 / (spectrum**2).sum(axis=0)
        assert share.min() > 0.999
        hz = peak / DURATION
        assert hz.min() >= 0.5 * FREQUENCY - 0.5 / DURATION
        assert hz.max() <= 1.5 * FREQUENCY + 0.5 / DURATION
    counts = np.bincount(
        np.unique(np.round(twist[:-1].T, 4), axis=0, return_inverse=True)[1].ravel()
    )
    assert counts.min() > 0.6 * len(rest) / CLASSES


def test_flutter_is_a_few_shared_rotations_and_leaves_the_still_forest_as_it_was(stands):
    stage = Usd.Stage.Open(str(stands["windy"]))
    layer = Sdf.Layer.FindOrOpen(str(stands["windy"].parent / "windy_assets" / "wind.usdc"))
    samples = {}

    def count(path: Sdf.Path) -> None:
        spec = layer.GetObjectAtPath(path)
        if isinstance(spec, Sdf.AttributeSpec) and layer.GetNumTimeSamplesForPath(path):
            samples[str(path)] = layer.GetNumTimeSamplesForPath(path)

    layer.Traverse(Sdf.Path.absoluteRootPath, count)
    flutter = {p: n for p, n in samples.items() if "Flutter" in p}
    # one rotation per class and time code; no leaf has samples of its own
    assert len(flutter) == CLASSES
    assert set(flutter.values()) == {int(DURATION * FPS) + 1}
    limbs = {p for p in samples if p.endswith(".xformOp:rotateXYZ:sway")}  # test_limbsway
    assert set(samples) - set(flutter) - limbs == {
        "/Forest/Trees.orientations",
        "/Forest/Trees.orientationsf",
    }
    # the pine's shoots do not flutter: its instancers are untouched
    pines = _leaf_instancers(stage, PINE)  # one: branch_sway is off, no limb groups
    assert len(pines) == 1 and len(pines[0].GetPositionsAttr().Get()) > 1000
    assert not any(layer.GetPrimAtPath(p.GetPath()) for p in pines)
    # muted, or at the default time, the leaves are the still forest's
    still = Usd.Stage.Open(str(stands["still"]))
    for time in (Usd.TimeCode.Default(),):
        got, want = _leaf_rows(stage, BEECH, time), _leaf_rows(still, BEECH, time)
        key = np.lexsort(np.round(got[:, 3, :3], 6).T)
        ref = np.lexsort(np.round(want[:, 3, :3], 6).T)
        np.testing.assert_allclose(got[key], want[ref], atol=1e-6)
    assert validate(stands["windy"]) == []


def test_a_scene_at_a_time_holds_its_leaves_turned_and_motion_turns_them_there(stands):
    """The sensors' scene at t holds each leaf where USD's composed transforms put it then
    (the leaf's own turn applied once), and SceneMotion moves a scene extracted at another
    time to t exactly, with velocities the central differences of scenes at t +- 1 ms."""
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.motion import SceneMotion

    path = stands["windy"]
    stage = Usd.Stage.Open(str(path))
    t = 0.7
    code = t * FPS
    scene = extract_scene(path, time=t, cache=False)
    beech = scene.leaves.take(np.flatnonzero(scene.leaves.turning))
    assert len(beech) == len(_leaf_rows(stage, BEECH, code))
    # independently: the leaf shape's box centre through USD's transforms, then the tree's
    mesh = next(
        p
        for p in Usd.PrimRange(stage.GetPrimAtPath(BEECH + "/Leaves/Prototypes/Leaf"))
        if p.IsA(UsdGeom.Mesh)
    )
    pts = np.asarray(UsdGeom.Mesh(mesh).GetPointsAttr().Get(), dtype=float)
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    rows = _leaf_rows(stage, BEECH, code)
    trees = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    tree = np.asarray(trees.ComputeInstanceTransformsAtTime(code, code), dtype=float)[0]
    want = np.append(centre, 1.0) @ rows @ tree
    got = beech.centre
    key = np.lexsort(np.round(got, 5).T)
    ref = np.lexsort(np.round(want[:, :3], 5).T)
    np.testing.assert_allclose(got[key], want[ref, :3], atol=1e-6)
    # moved from another time's scene
    early = extract_scene(path, time=0.1, cache=False)
    motion = SceneMotion(path, early)
    moved = motion.leaves(t, early.leaves)
    np.testing.assert_allclose(moved.centre, scene.leaves.centre, atol=1e-6)
    np.testing.assert_allclose(moved.normal, scene.leaves.normal, atol=1e-6)
    speed = motion.leaf_velocities(t, early.leaves)
    # the stage interpolates between its time codes: the velocity is the chord between the
    # two about t (here 16 and 17), as extracted scenes give it
    ends = [extract_scene(path, time=c / FPS, cache=False).leaves.centre for c in (16, 17)]
    np.testing.assert_allclose(speed, (ends[1] - ends[0]) * FPS, atol=1e-6)
    assert np.linalg.norm(speed[early.leaves.turning], axis=1).max() > 0.1
    # against the motion at t itself (+- 1 ms): the chord of a turn of up to 0.2 rad a
    # time code is off its tangent by a few per cent
    h = 1e-3
    after, before = (extract_scene(path, time=t + s, cache=False).leaves.centre for s in (h, -h))
    fd = (after - before) / (2 * h)
    err = np.linalg.norm(speed - fd, axis=1).max()
    assert err < 0.04 * np.linalg.norm(fd, axis=1).max()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("flutter_classes = 2.5", r"wind\.flutter_classes: 2\.5 is not a whole number"),
        ("flutter_angle = 50", r"wind\.flutter_angle: 50 is outside 0 to 45"),
        ("fps = 10", r"wind\.flutter_frequency: the leaves of beech flutter up to 4\.5 Hz"),
    ],
)
def test_the_recipe_checks_the_flutter(tmp_path, extra, message):
    from tomllib import loads

    from usdforest.recipe import parse_recipe

    table = {**loads(WIND)["wind"], **loads(extra)}
    text = (
        STAND
        + "[wind]\n"
        + "".join(
            f"{k} = {str(v).lower() if isinstance(v, bool) else v}\n" for k, v in table.items()
        )
    )
    with pytest.raises(RecipeError, match=message):
        parse_recipe(loads(text), tmp_path, "f.toml")


def test_conifers_alone_or_leafless_broadleaves_need_no_frames_for_flutter(tmp_path):
    from tomllib import loads

    from usdforest.recipe import parse_recipe

    pines = STAND.replace('species = "beech"', 'species = "pine"').replace(
        '[species.beech]\npreset = "european-beech"\n', ""
    )
    assert parse_recipe(loads(pines + "[wind]\nfps = 5\n"), tmp_path, "p.toml").wind.fps == 5
    winter = parse_recipe(loads(STAND + "[wind]\nfps = 5\n"), tmp_path, "w.toml", season="winter")
    assert winter.wind.fps == 5
    # a broadleaf the recipe defines but plants nowhere does not flutter either
    unplanted = STAND.replace('species = "beech"', 'species = "pine"')
    assert "[species.beech]" in unplanted
    assert parse_recipe(loads(unplanted + "[wind]\nfps = 5\n"), tmp_path, "u.toml").wind.fps == 5


def test_each_leaf_shapes_box_holds_it_at_every_turn_between_the_time_codes(stands, rest_scene):
    """The casters' box of a fluttering leaf shape (kept for the whole flight) holds the shape
    as USD turns it at any time, also between two time codes (where the stage slerps)."""
    from usdforest.sensors.scene.motion import SceneMotion

    path = stands["windy"]
    scene = rest_scene
    assert scene.shape_turns is not None and scene.shape_sweep is not None
    motion = SceneMotion(path, scene)
    times = np.random.default_rng(5).uniform(0, DURATION, 400)
    grown = 0.0
    for k, shape in enumerate(scene.shapes):
        pts = np.asarray(shape.triangles, dtype=float).reshape(-1, 3)
        back = np.linalg.inv(scene.shape_turns[k])
        at = np.array([motion.turns(t)[k] for t in times]) @ back
        moved = np.einsum("pj,njk->npk", pts, at[:, :3, :3]) + at[:, None, 3, :3]
        lo, hi = scene.shape_sweep[k]
        assert (moved >= lo - 1e-9).all() and (moved <= hi + 1e-9).all()
        grown = max(grown, float(np.max(hi - lo - (pts.max(axis=0) - pts.min(axis=0)))))
    assert grown > 0.05  # the beech's leaves turn: their boxes grew (the pine's did not)


def test_the_shapes_turns_and_sweeps_are_kept_with_the_stages_prototypes(
    stands, tmp_path, monkeypatch
):
    """The leaf shapes' turns and swept boxes (a second for the windy default forest) are kept
    in the scene cache with the prototypes: a second extraction reads them, equal to those
    made without the cache, at the default time and at another."""
    from usdforest.sensors.scene import walk as scene_module
    from usdforest.sensors.scene.extraction import extract_scene

    monkeypatch.setenv("USDFOREST_CACHE", str(tmp_path / "cache"))
    path = stands["windy"]
    real = scene_module.shape_turns
    made = []

    def counted(*args):
        made.append(args)
        return real(*args)

    monkeypatch.setattr(scene_module, "shape_turns", counted)
    for time in (None, 0.3):
        made.clear()
        first = extract_scene(path, time=time)
        assert len(made) == 1
        again = extract_scene(path, time=time)
        assert len(made) == 1  # read back, not made again
        bare = extract_scene(path, time=time, cache=False)
        assert len(made) == 2
        for scene in (first, again):
            np.testing.assert_array_equal(scene.shape_turns, bare.shape_turns)
            np.testing.assert_array_equal(scene.shape_sweep, bare.shape_sweep)
    # the two times' turns differ: each time has its own entry
    assert not np.array_equal(extract_scene(path).shape_turns, bare.shape_turns)


def test_a_flights_lidar_sees_each_leaf_turned_as_it_is_at_its_slice(stands, rest_scene):
    """A hovering VLP-16 between the beech and the pine: each slice of its sweeps returns what
    a scan of the stage at the slice's middle returns, the beech's leaves turned by their
    flutter then (the caster is built once; each leaf's callback turns the ray by its
    shape's turn; Warp's scene is built turned); had the leaves stayed at rest on their
    trees, as flights saw them before, many of the beech's returns would be millimetres to
    centimetres off."""
    import dataclasses

    from scipy.spatial import cKDTree

    from usdforest import api
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.platforms.flight import Trajectory
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.motion import SceneMotion

    path, at = stands["windy"], (10.0, 10.0, 9.0)
    sensor = dataclasses.replace(PRESETS["vlp-16"], noise=False)
    hover = Trajectory(
        np.array([0.0, 0.2]), np.array([at] * 2), yaw=np.zeros(2), pitch=np.zeros(2),
        roll=np.zeros(2),
    )  # fmt: skip
    flown = api.fly(path, path=hover, lidar=sensor, lidar_rate=10.0).lidar
    sweep = np.floor(flown.gps_time * 10.0 + 1e-9).astype(int)
    # each return's slice: the part of its sweep between the stage's time codes about it
    middle = slice_middles(flown.gps_time, 10.0, FPS, 0.0, 0.2)
    assert len(np.unique(middle)) >= 6  # 24 frames/s cut each 10 Hz sweep at least twice
    checked = 0
    for k in (0, 1):
        times, count = np.unique(middle[sweep == k], return_counts=True)
        # each sweep's two largest slices, over 3000 returns each: with the leaves left at
        # rest in the flight, 33 % and 73 % of the first sweep's, 76 % and 7 % of the
        # second's were off by more than 0.1 mm (0.2 % allowed)
        for t in times[np.argsort(count)[-2:]]:
            mine = flown.points[middle == t]
            scanned = api.scan(path, "lidar", at, settings=sensor, time=t).result.points
            gap = cKDTree(scanned).query(mine)[0]
            # a ray grazing a leaf's edge may fall either side of it: the two casts turn the
            # leaf by one float32 product or two
            assert np.mean(gap > 1e-4) < 2e-3
            checked += len(mine)
    assert checked > 3000
    # the leaves' turn is what a caster moved to t adds: without it (the leaves at rest on
    # their swaying trees) the beech's leaf returns are off
    scene = rest_scene
    motion = SceneMotion(path, scene)
    base = SceneCaster(scene)
    rng = np.random.default_rng(2)
    d = rng.normal(size=(20000, 3))
    d[:, 0] = -np.abs(d[:, 0])  # towards the beech, 4 m west
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile(np.array(at), (len(d), 1))
    now = motion.at(0.13)
    turned = base.moved(now).first_hit(o, d)
    rest = base.moved(dataclasses.replace(now, shape_turns=scene.shape_turns)).first_hit(o, d)
    want = SceneCaster(extract_scene(path, time=0.13, cache=False)).first_hit(o, d)
    # Warp (here on the CPU, as on CUDA) builds its scene for each time, the leaves turned
    warped = SceneCaster(scene, "warp-cpu").moved(now).first_hit(o, d)
    for got in (turned, warped):
        assert np.mean(got.hit != want.hit) < 2e-3
        both = got.hit & want.hit
        assert np.mean(np.abs(got.t[both] - want.t[both]) > 1e-4) < 2e-3
    leafy = want.hit & rest.hit & (want.cls == rest.cls)
    assert np.mean(np.abs(rest.t[leafy] - want.t[leafy]) > 1e-3) > 0.05

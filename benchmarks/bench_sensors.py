"""Lidar rays per second on a ~1M-triangle tree; sonar echo time for ~100k leaves."""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from usdforest.grow.species import get_species
from usdforest.sensors.cast.raycast import SceneCaster
from usdforest.sensors.lidar.scanners import SpinningLidar, scan
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.sonar.model import SonarConfig, echo_from_leaves
from usdforest.usd.tree import write_tree

WORK = Path(tempfile.mkdtemp(prefix="usdforest-bench-"))
_CACHE: dict = {}


def _lidar_setup():
    if "lidar" not in _CACHE:
        write_tree(get_species("pine"), WORK / "pine.usdc", seed=1)
        t0 = time.perf_counter()
        scene = extract_scene(WORK / "pine.usdc")
        t1 = time.perf_counter()
        caster = SceneCaster(scene)
        t2 = time.perf_counter()
        _CACHE["lidar"] = (scene, caster, t1 - t0, t2 - t1)
    return _CACHE["lidar"]


def lidar_1m_rays() -> tuple[int, str, str]:
    scene, caster, t_scene, t_bvh = _lidar_setup()
    sensor = SpinningLidar(
        channels=64, vfov_min=-30, vfov_max=30, azimuth_step=360 / 15625, max_range=50
    )
    r = scan(scene, sensor, Pose(-4.0, 0.0, 4.0), caster=caster)
    return (
        r.n_rays,
        "rays",
        (
            f"{len(scene):,} triangles ({t_scene:.1f} s to extract, "
            f"{t_bvh:.1f} s caster build), {len(r):,} returns"
        ),
    )


def sonar_100k_leaves() -> tuple[int, str, str]:
    if "sonar" not in _CACHE:
        sp = get_species("broadleaf")
        sp = replace(sp, geometry=replace(sp.geometry, leaves_per_site=285.0))
        write_tree(sp, WORK / "broadleaf.usdc", seed=1)
        _CACHE["sonar"] = extract_scene(WORK / "broadleaf.usdc")
    scene = _CACHE["sonar"]
    e = echo_from_leaves(scene.leaves, Pose(-6.0, 0.0, 5.5), SonarConfig(max_range=15))
    return e.leaves_used, "leaves", "32 bands, 20-100 kHz, 400 kHz output, 15 m window"


def lidar_forest_scan() -> tuple[int, str, str]:
    """End to end in the default forest: extract (culled), build, cast a VLP-16 at 30 m."""
    from usdforest.sensors.lidar.presets import PRESETS

    sensor = replace(PRESETS["vlp-16"], max_range=30.0)
    pose = Pose(30.0, 70.0, 1.5)
    scene = extract_scene(_default_forest(), centre=pose.position, radius=sensor.max_range)
    r = scan(scene, sensor, pose)
    return (
        r.n_rays,
        "rays",
        (
            f"{len(scene.instances)} trees, {len(scene):,} triangles in range "
            f"({len(scene.protos)} prototypes), {len(r):,} returns"
        ),
    )


def _default_forest() -> Path:
    """The default forest, built once per process."""
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.usd.forest import write_forest

    if "forest" not in _CACHE:
        write_forest(read_recipe(default_recipe_path()), WORK / "forest.usda", thumbnail=False)
        _CACHE["forest"] = WORK / "forest.usda"
    return _CACHE["forest"]


def camera_shadows() -> tuple[int, str, str]:
    """What the sun's shadows cost the camera (issue 40, item 3): a 640 x 480 frame at head
    height in the default forest with a shadow ray per sunlit pixel against none, on one warm
    caster, alternating, best of three (target: within 2x: at most one more ray a pixel)."""
    from usdforest.sensors.optics.camera import PRESETS, path_colours, render

    pose = Pose(50.0, 50.0, 1.6, yaw=20.0, pitch=5.0)
    cam = PRESETS["pinhole-640"]
    scene = extract_scene(_default_forest(), centre=pose.position, radius=cam.max_range)
    colours = path_colours(_default_forest(), scene.paths)
    caster = SceneCaster(scene)
    render(scene, cam, pose, colours, caster)  # builds the caster's trees
    best = {}
    for _ in range(3):
        for name, c in (("shadows", replace(cam, shadows=True)), ("none", cam)):
            t0 = time.perf_counter()
            render(scene, c, pose, colours, caster)
            best[name] = min(best.get(name, np.inf), time.perf_counter() - t0)
    return (
        cam.width * cam.height,
        "pixels",
        f"{best['shadows']:.2f} s vs {best['none']:.2f} s without: "
        f"{best['shadows'] / best['none']:.2f}x (target 2x)",
    )


def _vlp16_variants(variants: dict, target: float) -> tuple[int, str, str]:
    """A VLP-16 at head height in the default forest as each of ``variants`` (name -> its
    changes to the preset), on one warm caster, alternating, best of three each in this run;
    the first against the second, with its ``target`` ratio."""
    from usdforest.sensors.lidar.presets import PRESETS

    pose = Pose(50.0, 50.0, 2.0)
    scene = extract_scene(_default_forest(), centre=pose.position, radius=100.0)
    caster = SceneCaster(scene)
    best, returns = {}, {}
    for _ in range(3):
        for name, changes in variants.items():
            sensor = replace(PRESETS["vlp-16"], **changes)
            t0 = time.perf_counter()
            r = scan(scene, sensor, pose, caster=caster)
            best[name] = min(best.get(name, np.inf), time.perf_counter() - t0)
            returns[name] = len(r)
    a, b = list(variants)[:2]
    return (
        r.n_rays,
        "pulses",
        f"{best[a]:.2f} s vs {best[b]:.2f} s {b}: {best[a] / best[b]:.2f}x (target "
        f"{target:g}x); {returns[a]:,} returns vs {returns[b]:,}",
    )


def lidar_leaf_transmittance() -> tuple[int, str, str]:
    """What following light through leaves costs: leaves at 0.42 transmittance against
    opaque leaves (target: within 2x)."""
    from usdforest.sensors.lidar.presets import PRESETS

    through = {"leaf_transmittance": PRESETS["vlp-16"].leaf_transmittance}
    return _vlp16_variants({"through": through, "opaque": {"leaf_transmittance": 0.0}}, 2.0)


def lidar_waveform() -> tuple[int, str, str]:
    """What echoes from the return waveform cost (issue 40): the preset's 4 ns pulse against
    no pulse shape (echoes at the energy-weighted range of their hits; target: within
    1.3x)."""
    return _vlp16_variants({"waveform": {}, "no waveform": {"pulse_width": 0.0}}, 1.3)


def sonar_wood() -> tuple[int, str, str]:
    """What hearing wood at the sonar's own range costs (issue 40, item 2): a ``paper``
    pulse's wood echoes in the default forest (specular points, ends and joints of the
    chains in range, through the near-field Kirchhoff model) against the floor of any wood
    model, the same points' two-way beam, absorption and spreading alone (target: within
    5x)."""
    import timeit

    from usdforest.sensors.sonar.model import (
        PRESETS,
        SonarScene,
        _Grid,
        _propagation,
        _sight,
        wood_amplitudes,
        wood_points,
    )

    cfg, pose = PRESETS["paper"], Pose(50.0, 50.0, 2.0)
    scene = extract_scene(_default_forest(), centre=pose.position, radius=cfg.max_range + 5)
    wood = SonarScene(scene, cfg).targets(pose, cfg).wood
    f = _Grid.of(cfg).centres

    def heard() -> None:
        wood_amplitudes(wood_points(wood, pose.position), pose, cfg, f)

    points = wood_points(wood, pose.position)
    r, _, theta_b = _sight(points.position, pose)
    heard()  # numba compiles or loads its kernel on the first call
    ours = min(timeit.repeat(heard, number=1, repeat=3))
    base = min(timeit.repeat(lambda: _propagation(r, theta_b, f, cfg), number=1, repeat=3))
    return (
        len(points.radius),
        "wood points",
        f"{ours * 1e3:.0f} ms for {len(wood):,} pieces' echoes vs {base * 1e3:.0f} ms their beam "
        f"and spreading alone: {ours / base:.1f}x",
    )


def full_detail_open() -> tuple[int, str, str]:
    """What selecting full detail costs the sensors: the default forest (which selects lod =
    medium for clients) opened as scan, fly, stats and preview open it (switched to full in
    its session layer), against the same forest built at full, in one run."""
    import timeit

    from usdforest.recipe import default_recipe_path, parse_recipe, read_recipe
    from usdforest.usd.forest import write_forest
    from usdforest.usd.layers import open_stage

    if "lods" not in _CACHE:
        base = read_recipe(default_recipe_path())
        full = dict(base.data, forest=dict(base.data["forest"], lod="full"))
        write_forest(base, WORK / "lod-medium.usda", thumbnail=False)
        write_forest(parse_recipe(full, base.base, base.source), WORK / "lod-full.usda",
                     thumbnail=False)  # fmt: skip
        _CACHE["lods"] = (WORK / "lod-medium.usda", WORK / "lod-full.usda")
    medium, built_full = _CACHE["lods"]

    def opened(path) -> None:
        open_stage(path, sound=True, full=True)

    ours = min(timeit.repeat(lambda: opened(medium), number=1, repeat=3))
    before = min(timeit.repeat(lambda: opened(built_full), number=1, repeat=3))
    return (
        1,
        "stage",
        f"{ours * 1e3:.0f} ms the medium forest switched to full vs {before * 1e3:.0f} ms the "
        f"forest built at full: {ours / before:.2f}x",
    )


def _forest_floor(kind: str) -> tuple[int, str, str]:
    """Rays cast into the quick mixed stand's instances (15 m around a pose) against Embree
    on the same trees' triangles copied into one scene: the floor, and the ratio to it (the
    default forest's triangles fit in no flat copy)."""
    import timeit

    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.sensors.cast.raycast import RayCaster
    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.lidar.scanners import DepthCamera
    from usdforest.usd.forest import write_forest

    if "quick" not in _CACHE:
        recipe = read_recipe(default_recipe_path().parent / "quick-mixed.toml")
        write_forest(recipe, WORK / "quick.usda", thumbnail=False)
        _CACHE["quick"] = WORK / "quick.usda"
    pose, reach = Pose(30.0, 70.0, 1.5), 15.0
    if "floor" not in _CACHE:
        inst = extract_scene(_CACHE["quick"], centre=pose.position, radius=reach)
        flat = extract_scene(_CACHE["quick"], centre=pose.position, radius=reach, instancing=False)
        _CACHE["floor"] = (inst, SceneCaster(inst), flat, RayCaster(flat.triangles))
    inst, caster, flat, floor = _CACHE["floor"]
    sensor = (
        replace(PRESETS["vlp-16"], max_range=reach)
        if kind == "lidar"
        else DepthCamera(640, 480, 90.0, reach)
    )
    dirs = sensor.directions() @ pose.rotation().T
    o = np.ascontiguousarray(np.broadcast_to(pose.position, dirs.shape))
    caster.first_hit(o, dirs, reach)  # Embree builds its trees on the first cast
    floor.first_hit(o, dirs, reach)
    ours = min(timeit.repeat(lambda: caster.first_hit(o, dirs, reach), number=1, repeat=3))
    base = min(timeit.repeat(lambda: floor.first_hit(o, dirs, reach), number=1, repeat=3))
    return (
        len(dirs),
        "rays",
        f"{ours * 1e3:.0f} ms instanced vs {base * 1e3:.0f} ms Embree on the "
        f"{len(flat.triangles):,} triangles copied: {ours / base:.1f}x the floor "
        f"({len(inst.instances)} trees)",
    )


def lidar_forest_floor() -> tuple[int, str, str]:
    return _forest_floor("lidar")


def camera_forest_floor() -> tuple[int, str, str]:
    return _forest_floor("camera")


def las_1m_returns() -> tuple[int, str, str]:
    """write_las of 1M returns (asprs labels), and what its treeID dimension (issue 62)
    costs: the same fields written by laspy directly with and without it, each the best of
    three in this run; the record sizes from the headers; and what a survey's ``ply = true``
    adds: write_ply of the same returns (FOR-instanceV2's PLY), its time and file size
    against write_las's."""
    import laspy

    from usdforest.sensors.lidar.las import FlightReturns, benchmark_tree_ids, write_las
    from usdforest.sensors.lidar.ply import write_ply

    n = 1_000_000
    rng = np.random.default_rng(1)
    r = FlightReturns(
        points=rng.uniform(0, 100, (n, 3)), gps_time=np.sort(rng.uniform(0, 10, n)),
        range=rng.uniform(1, 50, n), cls=rng.integers(0, 7, n).astype(np.uint8),
        tree=rng.integers(-1, 500, n).astype(np.int32), path=np.zeros(n, np.int32), paths=(),
        n_rays=n, sweeps=100, ring=rng.integers(0, 16, n).astype(np.uint16),
        azimuth=rng.uniform(-180, 180, n), intensity=rng.integers(0, 65535, n).astype(np.uint16),
        return_number=np.ones(n, np.uint8), number_of_returns=np.ones(n, np.uint8),
        scan_angle=rng.uniform(-90, 90, n), height=rng.uniform(0, 30, n),
    )  # fmt: skip
    dims = [("ring", np.uint16, r.ring), ("azimuth", np.float32, r.azimuth),
            ("height", np.float32, r.height), ("tree_id", np.int32, r.tree),
            ("usdforest_class", np.uint8, r.cls)]  # fmt: skip
    tree_dim = [("treeID", np.int32, benchmark_tree_ids(r.tree))]

    def plain(path: Path, extra: list) -> int:
        header = laspy.LasHeader(point_format=6, version="1.4")
        header.scales = np.array([1e-4, 1e-4, 1e-4])
        header.offsets = np.floor(r.points.min(axis=0))
        header.add_extra_dims([laspy.ExtraBytesParams(name=k, type=t) for k, t, _ in extra])
        las = laspy.LasData(header)
        las.x, las.y, las.z = r.points.T
        las.gps_time, las.intensity, las.classification = r.gps_time, r.intensity, r.cls
        las.return_number, las.number_of_returns = r.return_number, r.number_of_returns
        las.scan_angle = np.round(r.scan_angle / 0.006).astype(np.int16)
        for k, _, v in extra:
            las[k] = v
        las.write(str(path))
        return header.point_format.size

    best = {"write_las": 1e9, "write_ply": 1e9, "with": 1e9, "without": 1e9}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(3):
            for key, run in (
                ("write_las", lambda: write_las(r, Path(tmp) / "a.las")),
                ("write_ply", lambda: write_ply(r, Path(tmp) / "a.ply")),
                ("with", lambda: plain(Path(tmp) / "b.las", dims + tree_dim)),
                ("without", lambda: plain(Path(tmp) / "c.las", dims)),
            ):
                t0 = time.perf_counter()
                run()
                best[key] = min(best[key], time.perf_counter() - t0)
        size_with = plain(Path(tmp) / "b.las", dims + tree_dim)
        size_without = plain(Path(tmp) / "c.las", dims)
        las_bytes, ply_bytes = ((Path(tmp) / f).stat().st_size for f in ("a.las", "a.ply"))
    note = (
        f"write_las {1000 * best['write_las']:.0f} ms; treeID's cost, the same fields with and "
        f"without it: {1000 * best['with']:.0f} vs {1000 * best['without']:.0f} ms "
        f"({best['with'] / best['without']:.2f}x), {size_with} vs {size_without} bytes a "
        f"point ({size_with / size_without:.2f}x); ply = true adds write_ply, "
        f"{1000 * best['write_ply']:.0f} ms ({best['write_ply'] / best['write_las']:.2f}x "
        f"write_las) and {ply_bytes / n:.0f} bytes a point ({ply_bytes / las_bytes:.2f}x the LAS)"
    )
    return n, "returns", note


BENCHMARKS = {
    "lidar: 1M rays, pine tree": lidar_1m_rays,
    "sonar: echo of ~100k leaves": sonar_100k_leaves,
    "lidar: default forest, VLP-16 at 30 m, end to end": lidar_forest_scan,
    "lidar: light through leaves vs opaque leaves, VLP-16 in the default forest": (
        lidar_leaf_transmittance
    ),
    "lidar: echoes from the waveform vs without, VLP-16 in the default forest": lidar_waveform,
    "sonar: wood echoes of a pulse vs their beam and spreading, default forest": sonar_wood,
    "camera: sun shadows vs none, 640 x 480 in the default forest": camera_shadows,
    "sensors: default forest opened at full detail": full_detail_open,
    "lidar: quick-mixed 15 m, VLP-16 vs Embree on copied triangles": lidar_forest_floor,
    "camera: quick-mixed 15 m, 640 x 480 vs Embree on copied triangles": camera_forest_floor,
    "las: 1M returns written, with treeID vs without": las_1m_returns,
}

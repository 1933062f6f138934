"""Ray casters side by side, in two parts.

1. The quick mixed stand (the embedded default until the closed canopy): the rays of a VLP-16
   and of a 640 x 480 camera cast from one pose, 15 m of forest around it, where a flat copy
   of every triangle still fits. Each library runs in its own subprocess on the same scene
   file: flat Embree (embreex, every triangle copied: the floor), usdforest's CPU caster
   (Embree 4, trees and leaves kept as instances), Warp's kernels on the CPU (the caster
   before it), and, when an interpreter that has them is named in
   ``USDFOREST_RAYTRACE_PYTHON``, Mitsuba 3 (one instance level, so each tree's leaves are
   copied into its prototype) and Open3D (flat). Agreement is counted against flat Embree
   on the same rays: the fraction of rays whose hit-or-miss is the same and, of the rays
   both hit, whose distance agrees within 1e-4 m.
2. The default closed canopy (6.8 G triangles at ``full``: no flat copy fits), 100 m of it
   around (50, 50, 2): the CPU caster against Warp's kernels on the CPU, and on CUDA where a
   GPU is present (``--device cuda``), each in its own subprocess:
   build time, memory the build adds, rays/s of a VLP-16 (4 sweeps) and a 640 x 480 frame,
   and agreement of the two (hit or miss, distance within 1e-4 m, same tree).

Usage: ``python benchmarks/bench_raytrace.py [--part 1|2]`` (``make bench`` runs both).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

POSE = (30.0, 70.0, 1.5)
REACH = 15.0


def _best(fn, repeat: int = 3) -> float:
    fn()  # first cast: builds, compiles, warms caches
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def prepare(work: Path) -> Path:
    """Build the quick mixed stand, extract 15 m of it and save what every library needs."""
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.lidar.scanners import DepthCamera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.usd.forest import write_forest

    forest = work / "forest.usda"
    recipe = read_recipe(default_recipe_path().parent / "quick-mixed.toml")
    write_forest(recipe, forest, thumbnail=False)
    pose = Pose(*POSE)
    scene = extract_scene(forest, centre=pose.position, radius=REACH, reflectors=False)
    flat = extract_scene(
        forest, centre=pose.position, radius=REACH, instancing=False, reflectors=False
    )
    protos = {}
    for k, p in enumerate(scene.protos):  # one-level instancing: leaves copied per prototype
        li = p.leaf_instances
        leaf = [
            (scene.shapes[s].triangles.reshape(-1, 3) @ m[:3, :3] + m[3, :3]).reshape(-1, 3, 3)
            for s, m in zip(li.shape, li.matrix, strict=True)
        ]
        protos[f"proto{k}"] = np.concatenate([p.triangles, *leaf]).astype(np.float32)
    rays = {
        "lidar": replace(PRESETS["vlp-16"], max_range=REACH).directions() @ pose.rotation().T,
        "camera": DepthCamera(640, 480, 90.0, REACH).directions() @ pose.rotation().T,
    }
    out = work / "scene.npz"
    np.savez(
        out,
        forest=str(forest),
        flat=flat.triangles,
        world=scene.triangles,
        matrix=scene.instances.matrix,
        proto=scene.instances.proto,
        n_proto=len(scene.protos),
        origin=pose.position,
        **{f"rays_{k}": v for k, v in rays.items()},
        **protos,
    )
    return out


def _embree(z) -> dict:
    from usdforest.sensors.cast.raycast import RayCaster

    t = time.perf_counter()
    caster = RayCaster(z["flat"])
    caster.first_hit(np.zeros((1, 3)), np.array([[0.0, 0, 1]]))
    build = time.perf_counter() - t

    def cast(o, d):
        return caster.first_hit(o, d, REACH)[0]

    return {"build": build, "cast": cast, "triangles": len(z["flat"])}


def _instanced(device: str):
    def setup(z) -> dict:
        from usdforest.sensors.cast.raycast import SceneCaster
        from usdforest.sensors.scene.extraction import extract_scene

        scene = extract_scene(str(z["forest"]), centre=z["origin"], radius=REACH, reflectors=False)
        t = time.perf_counter()
        caster = SceneCaster(scene, device)
        caster.first_hit(np.zeros((1, 3)), np.array([[0.0, 0, 1]]))  # compiled, loaded
        build = time.perf_counter() - t

        def cast(o, d):
            return caster.first_hit(o, d, REACH).t

        return {"build": build, "cast": cast, "triangles": len(scene)}

    return setup


def _mitsuba(z) -> dict:
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")

    def mesh(name, tri):
        pts = np.asarray(tri, np.float32).reshape(-1, 3)
        m = mi.Mesh(name, vertex_count=len(pts), face_count=len(pts) // 3)
        p = mi.traverse(m)
        p["vertex_positions"] = mi.Float(pts.ravel())
        p["faces"] = mi.UInt32(np.arange(len(pts), dtype=np.uint32))
        p.update()
        return m

    t = time.perf_counter()
    d = {"type": "scene", "world": mesh("world", z["world"])}
    for k in range(int(z["n_proto"])):
        d[f"g{k}"] = {"type": "shapegroup", "m": mesh(f"p{k}", z[f"proto{k}"])}
    for i, (m, k) in enumerate(zip(z["matrix"], z["proto"], strict=True)):
        d[f"i{i}"] = {
            "type": "instance",
            "shapegroup": {"type": "ref", "id": f"g{int(k)}"},
            "to_world": mi.ScalarTransform4f(m.T.tolist()),
        }
    scene = mi.load_dict(d)
    build = time.perf_counter() - t

    def cast(o, dd):
        ray = mi.Ray3f(
            mi.Point3f(*(np.ascontiguousarray(o[:, j], np.float32) for j in range(3))),
            mi.Vector3f(*(np.ascontiguousarray(dd[:, j], np.float32) for j in range(3))),
        )
        ray.maxt = REACH
        si = scene.ray_intersect_preliminary(ray)
        dr.eval(si.t)
        return np.array(si.t, dtype=float)

    n = len(z["world"]) + sum(len(z[f"proto{k}"]) for k in z["proto"])
    return {"build": build, "cast": cast, "triangles": n}


def _open3d(z) -> dict:
    import open3d as o3d

    t = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    pts = np.asarray(z["flat"], np.float32).reshape(-1, 3)
    scene.add_triangles(pts, np.arange(len(pts), dtype=np.uint32).reshape(-1, 3))
    build = time.perf_counter() - t

    def cast(o, d):
        rays = np.concatenate([o, d], axis=1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)
        return np.where(t <= REACH, t, np.inf)

    return {"build": build, "cast": cast, "triangles": len(pts)}


LIBRARIES = {
    "embree": _embree,
    "usdforest cpu (Embree 4, two levels)": _instanced("cpu"),
    "warp-cpu (Warp kernels)": _instanced("warp-cpu"),
    "mitsuba": _mitsuba,
    "open3d": _open3d,
}
OWN = ("embree", "usdforest cpu (Embree 4, two levels)", "warp-cpu (Warp kernels)")


def measure(lib: str, scene_file: str) -> dict:
    """One library's build time, cast times and distances on the saved rays."""
    z = np.load(scene_file)
    setup = LIBRARIES[lib](z)
    out = {"build_s": setup["build"], "triangles": setup["triangles"]}
    for kind in ("lidar", "camera"):
        d = np.asarray(z[f"rays_{kind}"], dtype=float)
        o = np.ascontiguousarray(np.broadcast_to(z["origin"], d.shape))
        out[f"{kind}_s"] = _best(lambda o=o, d=d: setup["cast"](o, d))
        t = setup["cast"](o, d)
        np.save(Path(scene_file).with_name(f"{_file(lib)}_{kind}.npy"), t)
        out[f"{kind}_rays"] = len(d)
    return out


def _file(lib: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in lib)


def _rss() -> int:
    """This process's resident memory now (bytes)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


DEFAULT_POSE = (50.0, 50.0, 2.0)
DEFAULT_REACH = 100.0


def measure_default(device: str, forest: str, out: str) -> dict:
    """Part 2: one caster on the default forest (in its own process)."""
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.lidar.scanners import DepthCamera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene

    pose = Pose(*DEFAULT_POSE)
    scene = extract_scene(forest, centre=pose.position, radius=DEFAULT_REACH, reflectors=False)
    before = _rss()
    t = time.perf_counter()
    caster = SceneCaster(scene, device)
    caster.first_hit(np.zeros((1, 3)), np.array([[0.0, 0, 1]]))
    build = time.perf_counter() - t
    added = _rss() - before
    row = {"build_s": build, "memory_bytes": added, "triangles": len(scene)}
    rays = {
        "lidar": np.tile(PRESETS["vlp-16"].directions(), (4, 1)),
        "camera": DepthCamera(640, 480, 90.0).directions(),
    }
    saved = {}
    for kind, d in rays.items():
        d = d @ pose.rotation().T
        o = np.broadcast_to(pose.position, d.shape)
        row[f"{kind}_s"] = _best(lambda o=o, d=d: caster.first_hit(o, d, DEFAULT_REACH))
        row[f"{kind}_rays"] = len(d)
        h = caster.first_hit(o, d, DEFAULT_REACH)
        saved[f"{kind}_t"], saved[f"{kind}_tree"] = h.t, h.tree
    np.savez(out, **saved)
    return row


def part2() -> None:
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.usd.forest import write_forest

    work = Path(tempfile.mkdtemp(prefix="usdforest-raytrace-default-"))
    forest = work / "forest.usda"
    write_forest(read_recipe(default_recipe_path()), forest, thumbnail=False)
    from usdforest.sensors.cast.warpcast import cuda_devices

    rows = {}
    for device in ("cpu", "warp-cpu", *cuda_devices()[:1]):
        r = subprocess.run(
            [sys.executable, __file__, "--default", device, str(forest), str(work / device)],
            capture_output=True, text=True,
        )  # fmt: skip
        rows[device] = json.loads(r.stdout.splitlines()[-1]) if r.returncode == 0 else None
        if r.returncode:
            print(r.stderr[-2000:], file=sys.stderr)
    print("| caster | build | memory added | VLP-16 | 640 x 480 | vs Warp kernels | agreement |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    base = rows["warp-cpu"]
    for device, r in rows.items():
        if r is None:
            continue
        agree = []
        for kind in ("lidar", "camera"):
            a, b = np.load(work / f"{device}.npz"), np.load(work / "warp-cpu.npz")
            ta, tb = a[f"{kind}_t"], b[f"{kind}_t"]
            both = np.isfinite(ta) & np.isfinite(tb)
            close = both & (np.abs(np.where(both, ta, 0) - np.where(both, tb, 0)) < 1e-4)
            agree.append(
                f"{kind}: hit {np.mean(np.isfinite(ta) == np.isfinite(tb)):.5f}, distance "
                f"{close.sum() / max(both.sum(), 1):.5f}, tree "
                f"{np.mean(a[f'{kind}_tree'][close] == b[f'{kind}_tree'][close]):.5f}"
            )
        name = {"cpu": "Embree 4, two levels (used)", "warp-cpu": "Warp kernels, CPU"}.get(
            device, f"Warp kernels, {device} (--device cuda)"
        )
        print(
            f"| {name} | {r['build_s']:.1f} s | {r['memory_bytes'] / 2**30:.2f} GiB | "
            f"{r['lidar_rays'] / r['lidar_s'] / 1e6:.2f} M rays/s | "
            f"{r['camera_rays'] / r['camera_s'] / 1e6:.2f} M rays/s | "
            f"{base['lidar_s'] / r['lidar_s']:.1f}x, {base['camera_s'] / r['camera_s']:.1f}x | "
            f"{'; '.join(agree)} |",
            flush=True,
        )


def main() -> None:
    part = sys.argv[2] if len(sys.argv) == 3 and sys.argv[1] == "--part" else "all"
    if part in ("1", "all"):
        part1()
    if part in ("2", "all"):
        part2()


def part1() -> None:
    work = Path(tempfile.mkdtemp(prefix="usdforest-raytrace-"))
    scene = prepare(work)
    other = os.environ.get("USDFOREST_RAYTRACE_PYTHON", sys.executable)
    rows = {}
    for lib in LIBRARIES:
        python = sys.executable if lib in OWN else other
        r = subprocess.run(
            [python, __file__, "--one", lib, str(scene)], capture_output=True, text=True
        )
        rows[lib] = json.loads(r.stdout) if r.returncode == 0 else None
    print("| library | triangles | build | VLP-16 | 640 x 480 | vs flat Embree | agreement |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    base = rows["embree"]
    for lib, r in rows.items():
        if r is None:
            print(f"| {lib} | not installed for `USDFOREST_RAYTRACE_PYTHON` | | | | | |")
            continue
        agree = []
        for kind in ("lidar", "camera"):
            a = np.load(work / f"{_file(lib)}_{kind}.npy")
            b = np.load(work / f"{_file('embree')}_{kind}.npy")
            both = np.isfinite(a) & np.isfinite(b)
            same = np.mean(np.isfinite(a) == np.isfinite(b))
            close = np.mean(np.abs(a[both] - b[both]) < 1e-4) if both.any() else 1.0
            agree.append(f"{kind}: hit {same:.5f}, distance {close:.5f}")
        print(
            f"| {lib} | {r['triangles']:,} | {r['build_s']:.2f} s | "
            f"{r['lidar_s'] * 1e3:.0f} ms | {r['camera_s'] * 1e3:.0f} ms | "
            f"{r['lidar_s'] / base['lidar_s']:.2f}x, {r['camera_s'] / base['camera_s']:.2f}x | "
            f"{'; '.join(agree)} |",
            flush=True,
        )


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--one":
        print(json.dumps(measure(sys.argv[2], sys.argv[3])))
    elif len(sys.argv) == 5 and sys.argv[1] == "--default":
        print(json.dumps(measure_default(sys.argv[2], sys.argv[3], sys.argv[4])))
    else:
        main()

"""Ray-tracing libraries side by side on the quick mixed stand (issue 23; the embedded default
until the closed canopy, whose triangles no flat copy holds): the rays of a VLP-16 and of a
640 x 480 camera cast from one pose, 15 m of forest around it.

Usage: ``python benchmarks/bench_raytrace.py`` (``make bench``). Each library runs in its
own subprocess on the same scene file: flat Embree (embreex, every triangle copied), Warp
(usdforest's caster: trees, then leaves, then triangles), and, when an interpreter that has
them is named in ``USDFOREST_RAYTRACE_PYTHON``, Mitsuba 3 (Embree instancing; one level
only, so each tree's leaves are copied into its prototype) and Open3D (flat). Agreement is
counted against flat Embree on the same rays: the fraction of rays whose hit-or-miss is the
same and, of the rays both hit, whose distance agrees within 1e-4 m.
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
    from usdforest.sensors.lidar import PRESETS, DepthCamera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene import extract_scene
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
    from usdforest.sensors.raycast import RayCaster

    t = time.perf_counter()
    caster = RayCaster(z["flat"])
    caster.first_hit(np.zeros((1, 3)), np.array([[0.0, 0, 1]]))
    build = time.perf_counter() - t

    def cast(o, d):
        return caster.first_hit(o, d, REACH)[0]

    return {"build": build, "cast": cast, "triangles": len(z["flat"])}


def _warp(z) -> dict:
    from usdforest.sensors.raycast import SceneCaster
    from usdforest.sensors.scene import extract_scene

    scene = extract_scene(str(z["forest"]), centre=z["origin"], radius=REACH, reflectors=False)
    t = time.perf_counter()
    caster = SceneCaster(scene)
    build = time.perf_counter() - t

    def cast(o, d):
        return caster.first_hit(o, d, REACH).t

    return {"build": build, "cast": cast, "triangles": len(scene)}


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


LIBRARIES = {"embree": _embree, "warp": _warp, "mitsuba": _mitsuba, "open3d": _open3d}


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
        np.save(Path(scene_file).with_name(f"{lib}_{kind}.npy"), t)
        out[f"{kind}_rays"] = len(d)
    return out


def main() -> None:
    work = Path(tempfile.mkdtemp(prefix="usdforest-raytrace-"))
    scene = prepare(work)
    other = os.environ.get("USDFOREST_RAYTRACE_PYTHON", sys.executable)
    rows = {}
    for lib in LIBRARIES:
        python = sys.executable if lib in ("embree", "warp") else other
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
            a = np.load(work / f"{lib}_{kind}.npy")
            b = np.load(work / f"embree_{kind}.npy")
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
    else:
        main()

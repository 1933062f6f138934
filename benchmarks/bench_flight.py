"""A 100 m flight through the default forest: a VLP-16 at 10 Hz, the paper's sonar at 20
pulses/s (leaves, wood and ground) and a 640 x 480 camera at 1 frame/s, at 5 m/s and 2 m up.

Usage: ``python benchmarks/bench_flight.py [--only lidar,sonar,camera] [--device cuda]``
(``make bench`` runs it all on the CPU after the main table). The lidar is flown twice: as
the preset is (a 3 mrad beam of 7 sub-rays, dual returns) and as thin rays with one return
each (what it was before multiple returns), and the ratio of the two printed.
Prints a Markdown table: wall time of each part and its real-time factor (seconds of flight
simulated per second of wall time: at least 1 keeps up with the sensor), rays/s, echoes
(pulses)/s and reflectors/s, frames/s, and the whole flight's wall time and peak memory. One
run (the flight takes minutes); the parts are timed in process, as ``usdforest fly`` runs
them.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

LINE = ((0.0, 50.0, 2.0), (100.0, 50.0, 2.0))
SPEED = 5.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="lidar,sonar,camera", help="parts to fly")
    parser.add_argument("--device", default="cpu", help="the caster's device: cpu or cuda[:N]")
    args = parser.parse_args()
    only = set(args.only.split(","))
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.lidar.presets import PRESETS as LIDARS
    from usdforest.sensors.optics import camera
    from usdforest.sensors.platforms.flight import Trajectory, fly_lidar
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.sonar.model import PRESETS as SONARS
    from usdforest.usd.forest import write_forest

    work = Path(tempfile.mkdtemp(prefix="usdforest-flight-"))
    stage = work / "forest.usda"
    write_forest(read_recipe(default_recipe_path()), stage, thumbnail=False)
    traj = Trajectory.line(*LINE, SPEED)
    lidar, sonar, cam = LIDARS["vlp-16"], SONARS["paper"], camera.PRESETS["pinhole-640"]
    rows = []
    start = time.perf_counter()
    t = time.perf_counter()
    lo, hi = traj.position.min(axis=0), traj.position.max(axis=0)
    reach = max(lidar.max_range, sonar.max_range, cam.max_range)
    scene = extract_scene(
        stage, centre=(lo + hi) / 2, radius=float(np.linalg.norm(hi - lo) / 2 + reach)
    )
    caster = SceneCaster(scene, args.device)
    rows.append(
        ("scene: extract and build the caster", time.perf_counter() - t,
         f"{len(scene.instances)} trees, {len(scene):,} triangles, {len(scene.leaves):,} leaves")
    )  # fmt: skip
    if "lidar" in only:
        thin = dataclasses.replace(lidar, divergence=0.0)
        spent = {}
        for name, sensor in (("VLP-16, 10 Hz, thin rays, one return", thin),
                             ("VLP-16, 10 Hz, 3 mrad beam, 7 sub-rays, dual", lidar)):  # fmt: skip
            t = time.perf_counter()
            r = fly_lidar(scene, sensor, traj, 10.0, caster=caster)
            dt = spent[sensor] = time.perf_counter() - t
            two = int(np.count_nonzero(r.return_number == 2))
            rows.append(
                (f"lidar: {name}", dt,
                 f"{r.sweeps} sweeps, {r.n_rays:,} pulses, {r.n_rays / dt / 1e3:,.0f} k pulses/s, "
                 f"{len(r):,} returns, {two:,} pulses with two")
            )  # fmt: skip
        rows.append(("lidar: multiple returns / one return", spent[lidar] / spent[thin], None))
    if "sonar" in only:
        sonar_rows(scene, sonar, traj, caster, rows)
    if "camera" in only:
        camera_rows(stage, scene, cam, traj, caster, rows)
    report(rows, traj, start)


def sonar_rows(scene, sonar, traj, caster, rows) -> None:
    from usdforest.sensors.platforms.flight import fly_sonar
    from usdforest.sensors.sonar import bandsum
    from usdforest.sensors.sonar.model import SonarScene

    t = time.perf_counter()
    prepared = SonarScene(scene, sonar, caster=caster)
    prep = time.perf_counter() - t
    # the band-sum kernels' share of the flight, timed as they are called
    spent = dict.fromkeys(("group_fit_deposit", "beam_deposit", "deposit"), 0.0)

    def timed(name, kernel):
        def run(*args):
            start = time.perf_counter()
            try:
                return kernel(*args)
            finally:
                spent[name] += time.perf_counter() - start

        return run

    kernels = {name: getattr(bandsum, name) for name in spent}
    for name, kernel in kernels.items():
        setattr(bandsum, name, timed(name, kernel))
    try:
        t = time.perf_counter()
        f = fly_sonar(scene, sonar, traj, caster=caster)
        dt = time.perf_counter() - t
    finally:
        for name, kernel in kernels.items():
            setattr(bandsum, name, kernel)
    heard = sum(
        int(n)
        for index in prepared._index
        for n in index.query_ball_point(f.position, sonar.max_range, return_length=True)
    )
    rows.append(
        ("sonar: paper preset, 20 pulses/s", dt,
         f"{len(f.t)} pulses, {len(f.t) / dt:.2f} echoes/s; {heard / dt / 1e3:,.0f} k leaves and "
         f"cylinders/s (+ ground facets); {len(prepared.wood):,} wood cylinders fitted in "
         f"{prep:.1f} s")
    )  # fmt: skip
    per = {name: spent[name] / len(f.t) for name in spent}
    rows.append(
        ("sonar: per pulse, band-sum kernels", sum(per.values()), "-",
         f"leaves (group fit) {per['group_fit_deposit']:.3f} s, ground facets "
         f"{per['beam_deposit']:.3f} s, wood {per['deposit']:.3f} s; the rest of a pulse "
         f"{dt / len(f.t) - sum(per.values()):.3f} s")
    )  # fmt: skip


def camera_rows(stage, scene, cam, traj, caster, rows) -> None:
    from usdforest.sensors.optics import camera

    t = time.perf_counter()
    colours = camera.path_colours(stage, scene.paths)
    frames = camera.fly_camera(scene, cam, traj, 1.0, colours, caster)
    dt = time.perf_counter() - t
    rays = frames.depth.size
    rows.append(
        ("camera: 640 x 480, 1 frame/s", dt,
         f"{len(frames)} frames, {len(frames) / dt:.2f} frames/s, {rays / dt / 1e3:,.0f} k rays/s")
    )  # fmt: skip


def report(rows, traj, start) -> None:
    total = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"100 m at {SPEED:g} m/s ({traj.duration:g} s of flight), 2 m up, default forest\n")
    print("| part | wall time | real time | figures |")
    print("| --- | --- | --- | --- |")
    for name, seconds, *rest in rows:
        note = rest[-1]
        if note is None:  # a ratio row
            print(f"| {name} | {seconds:.2f}x | | |")
            continue
        factor = (
            rest[0] if len(rest) == 2 else "-" if name.startswith("scene") else
            f"{traj.duration / seconds:.2f}x"
        )  # fmt: skip
        shown = f"{seconds:,.1f}" if seconds >= 10 else f"{seconds:.2f}"
        print(f"| {name} | {shown} s | {factor} | {note} |")
    print(
        f"| whole flight | {total:,.1f} s | {traj.duration / total:.2f}x | "
        f"peak memory {peak:,.0f} MiB |"
    )
    sys.stdout.flush()


if __name__ == "__main__":
    main()

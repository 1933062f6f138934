"""Surveys of the default forest: one terrestrial station of the VZ-400 preset at 0.1 deg
(+60/-40 deg x 360 deg: 3.6 M pulses of 7 sub-rays), and a drone survey of the 1 ha plot at
about 300 pulses/m² (the VUX-1UAV preset at 375 kHz, 60 m above the ground, 6 m/s, 50 %
side overlap, a 40 deg swath) with thin beams.

Usage: ``python benchmarks/bench_surveys.py`` (``make bench`` runs it after the main
table). One run; the survey's parts timed in process from its progress: the scene (its
prototypes read from the scene cache, which a first extraction fills), then the station or
the lines. Targets (issue 62): a station in at most 60 s after the scene is cached, the
drone survey at least as fast as the real flight (its flight time over its wall time >= 1);
on two Dask workers, the client's memory flat: the same peak for a quarter hectare and for
the hectare (four times the points), each measured in a process of its own.
Prints a Markdown table.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path


def _timed(stage, plan, lidar):
    from usdforest.sensors.platforms.campaign import run_survey

    t0 = time.perf_counter()
    first: dict[str, float] = {}

    def tick(stage_name, done, total):
        first.setdefault(stage_name, time.perf_counter() - t0)

    survey = run_survey(stage, plan, lidar, progress=tick)
    wall = time.perf_counter() - t0
    part = "station 1" if plan.kind == "tls" else "flight lines"
    return survey, wall, first.get(part, 0.0)


CLIENT = """
import json, sys, time
import usdforest
stage, out, x1 = sys.argv[1], sys.argv[2], float(sys.argv[3])
plan = {"survey": {"kind": "flight", "lidar": "vux-1uav", "region": [0.0, 0.0, x1, 100.0],
                   "height": 60.0, "speed": 6.0, "side_overlap": 0.5, "scan_angle": 40.0},
        "lidar": {"pulse_rate": 375e3, "beam_rings": 0}}
t = time.perf_counter()
usdforest.survey(stage, plan, out=out, workers=2)
# VmHWM: this process's own peak (ru_maxrss keeps the parent's across fork and exec)
hwm = next(ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:"))
print(json.dumps({"wall": time.perf_counter() - t, "peak": int(hwm.split()[1]) / 1024}))
"""


def _on_workers(stage: Path, tmp: Path, x1: float) -> dict:
    """The survey of the region 0..x1 x 0..100 on two local Dask workers, in a process of
    its own: its wall time and the client's own peak memory (MiB; the workers not
    counted)."""
    out = subprocess.run(
        [sys.executable, "-c", CLIENT, str(stage), str(tmp / f"w{x1:g}"), str(x1)],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    report = json.loads(out.stdout.strip().splitlines()[-1])
    points = 0
    import laspy

    for f in (tmp / f"w{x1:g}" / "lines").glob("*.las"):
        with laspy.open(str(f)) as las:
            points += las.header.point_count
    return {**report, "points": points}


def main() -> None:
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.platforms.plans import SurveyPlan, pulse_density
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.usd.forest import write_forest

    with tempfile.TemporaryDirectory() as tmp:
        stage = Path(tmp) / "default.usda"
        write_forest(read_recipe(default_recipe_path()), stage, thumbnail=False)
        t = time.perf_counter()
        extract_scene(stage, reflectors=False)  # fills the scene cache
        cold = time.perf_counter() - t
        print(
            "| survey | pulses | points | scene and caster | survey's own | wall | target "
            "| peak memory |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
        tls = PRESETS["vz-400"]
        plan = SurveyPlan(kind="tls", stations=((50.0, 50.0),), height=1.5)
        s, wall, scene = _timed(stage, plan, tls)
        own = wall - scene
        print(
            f"| TLS station, VZ-400 at 0.1 deg | {tls.station_pulses():,} | "
            f"{sum(len(p) for p in s.parts):,} | {scene:.1f} s (cached; {cold:.1f} s uncached) "
            f"| {own:.1f} s | {wall:.1f} s | station <= 60 s: {own:.1f} s | "
            f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:,.0f} MiB |",
            flush=True,
        )
        vux = replace(PRESETS["vux-1uav"], pulse_rate=375e3, beam_rings=0)
        plan = SurveyPlan(kind="flight", region=(0.0, 0.0, 100.0, 100.0), height=60.0,
                          speed=6.0, side_overlap=0.5, scan_angle=40.0)  # fmt: skip
        s, wall, scene = _timed(stage, plan, vux)
        flown = sum(float(p.gps_time.max() - p.gps_time.min()) for p in s.parts)
        print(
            f"| drone 1 ha, VUX-1UAV 375 kHz thin beams, {pulse_density(plan, vux):.0f} "
            f"pulses/m² planned, {s.measured_density:.0f} measured | "
            f"{sum(p.n_rays for p in s.parts):,} | {sum(len(p) for p in s.parts):,} | "
            f"{scene:.1f} s | {wall - scene:.1f} s | {wall:.1f} s | flight {flown:.1f} s: "
            f"{flown / wall:.2f}x real time ({flown / (wall - scene):.2f}x without the scene) | "
            f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:,.0f} MiB |",
            flush=True,
        )
        quarter, whole = (_on_workers(stage, Path(tmp), x1) for x1 in (25.0, 100.0))
        for name, r in (("0.25 ha", quarter), ("1 ha", whole)):
            print(
                f"| drone {name} as above, lines on 2 Dask workers | | {r['points']:,} | "
                f"(each task its own) | | {r['wall']:.1f} s | client memory flat: "
                f"{r['peak']:,.0f} MiB | {r['peak']:,.0f} MiB (client) |",
                flush=True,
            )


if __name__ == "__main__":
    sys.exit(main())

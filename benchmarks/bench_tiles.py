"""Tiled landscapes (issue 15): build 1, 10 and 100 km² at 0.05 trees/m² in 500 m payload
tiles with 1 and 2 Dask workers; open the root with payloads unloaded; load one tile.

Usage: ``python benchmarks/bench_tiles.py [km2 ...]`` (``make bench`` runs 1 and 10; the
100 km² row takes a few minutes). Prints a Markdown table. Peak memory is each process's
peak resident set: the client's, and the largest worker's.
"""

from __future__ import annotations

import json
import math
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pxr import Usd

from usdforest.recipe import parse_recipe
from usdforest.usd.forest import write_forest


def _recipe(km2: float):
    side = math.sqrt(km2) * 1000.0
    data = {
        "seed": 15,
        "region": {"bounds": [0.0, 0.0, side, side]},
        "intensity": {
            "kind": "expression",
            "expr": f"0.05 + 0.03 * sin(x / {side / 3:.1f}) * cos(y / {side / 4:.1f})",
        },
        "mix": {"pine": 0.55, "broadleaf": 0.45},
        "species": {"pine": {}, "broadleaf": {}},
        "forest": {"variants": 2, "colliders": "none", "max_trees": 10**8},
        "tiles": {"size": 500.0},
    }
    return parse_recipe(data, Path("."), f"landscape-{km2:g}km2")


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(km2: float, workers: int) -> dict:
    out = Path(tempfile.mkdtemp(prefix="usdforest-tiles-")) / "land.usda"
    recipe = _recipe(km2)
    worker_peak = 0.0
    try:
        if workers > 1:
            from distributed import Client, LocalCluster

            with (
                LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=None) as c,
                Client(c) as client,
            ):
                t = time.perf_counter()
                b = write_forest(recipe, out, thumbnail=False, scheduler=c.scheduler_address)
                wall = time.perf_counter() - t
                peaks = client.run(lambda: _peak_mib())
                worker_peak = max(peaks.values())
        else:
            t = time.perf_counter()
            b = write_forest(recipe, out, thumbnail=False)
            wall = time.perf_counter() - t
        t = time.perf_counter()
        stage = Usd.Stage.Open(str(out), Usd.Stage.LoadNone)
        open_s = time.perf_counter() - t
        tiles = stage.GetPrimAtPath("/Forest/Tiles").GetAllChildren()
        t = time.perf_counter()
        stage.Load(tiles[len(tiles) // 2].GetPath())
        load_s = time.perf_counter() - t
        size = sum(p.stat().st_size for p in out.parent.rglob("*") if p.is_file())
        return {
            "trees": b.n_trees,
            "tiles": b.n_tiles,
            "wall": wall,
            "open": open_s,
            "load": load_s,
            "client_peak": _peak_mib(),
            "worker_peak": worker_peak,
            "bytes": size,
        }
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)


def main(areas: list[float]) -> None:
    print(
        "| area | workers | trees | tiles | build | per worker peak | client peak "
        "| root open, unloaded | one tile load | on disk |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for km2 in areas:
        for workers in (1, 2):
            # each run in its own process, so peaks are that run's
            r = subprocess.run(
                [sys.executable, __file__, "--one", str(km2), str(workers)],
                capture_output=True,
                text=True,
                check=True,
            )
            d = json.loads(r.stdout.strip().splitlines()[-1])
            wp = f"{d['worker_peak']:,.0f} MiB" if workers > 1 else "(in process)"
            print(
                f"| {km2:g} km² | {workers} | {d['trees']:,} | {d['tiles']} | {d['wall']:.1f} s "
                f"| {wp} | {d['client_peak']:,.0f} MiB | {d['open'] * 1e3:.0f} ms "
                f"| {d['load'] * 1e3:.0f} ms | {d['bytes'] / 2**20:,.0f} MiB |",
                flush=True,
            )


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--one":
        print(json.dumps(run(float(sys.argv[2]), int(sys.argv[3]))))
    else:
        main([float(a) for a in sys.argv[1:]] or [1.0, 10.0])

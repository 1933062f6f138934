"""Tiled landscapes (issues 15 and 25): build 1, 10, 100 and 1,000 km² at 0.05 trees/m² in
500 m payload tiles on a Dask cluster of 1 and 2 worker processes; open the root with
payloads unloaded; load one tile.

Usage: ``python benchmarks/bench_tiles.py [km2 ...]`` (``make bench`` runs 1 and 10; 100 km²
takes a minute, 1,000 km² about ten). Prints a Markdown table. Each run is its own process
(the client) beside a scheduler and worker processes started as a user starts them
(``dask scheduler``, ``dask worker``) before the clock; peak memory is each process's peak
resident set: the client's (measured when the build returns, before the stage is opened)
and every worker's.
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


def _recipe(km2: float):
    from usdforest.recipe import parse_recipe

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
        "forest": {"variants": 2, "colliders": "none", "max_trees": 10**9},
        "tiles": {"size": 500.0},
    }
    return parse_recipe(data, Path("."), f"landscape-{km2:g}km2")


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(km2: float, workers: int) -> dict:
    from pxr import Usd

    from usdforest.cluster import process_cluster
    from usdforest.usd.forest import write_forest

    folder = Path(tempfile.mkdtemp(prefix="usdforest-tiles-"))
    out = folder / "land.usda"
    recipe = _recipe(km2)
    try:
        with process_cluster(workers, folder) as client:
            address = client.scheduler.address
            t = time.perf_counter()
            b = write_forest(recipe, out, thumbnail=False, scheduler=address)
            wall = time.perf_counter() - t
            client_peak = _peak_mib()
            worker_peaks = sorted(client.run(_peak_mib).values())
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
            "client_peak": client_peak,
            "worker_peaks": worker_peaks,
            "root_bytes": out.stat().st_size,
            "bytes": size,
        }
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def main(areas: list[float]) -> None:
    print(
        "| area | workers | trees | tiles | build | trees/s | client peak | worker peaks "
        "| root open, unloaded | one tile load | root layer | on disk |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
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
            wp = " / ".join(f"{p:,.0f}" for p in d["worker_peaks"]) + " MiB"
            print(
                f"| {km2:g} km² | {workers} | {d['trees']:,} | {d['tiles']:,} | {d['wall']:.1f} s "
                f"| {d['trees'] / d['wall'] / 1e3:,.0f} k | {d['client_peak']:,.0f} MiB | {wp} "
                f"| {d['open'] * 1e3:.0f} ms | {d['load'] * 1e3:.0f} ms "
                f"| {d['root_bytes'] / 2**20:,.1f} MiB | {d['bytes'] / 2**20:,.0f} MiB |",
                flush=True,
            )


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--one":
        print(json.dumps(run(float(sys.argv[2]), int(sys.argv[3]))))
    else:
        main([float(a) for a in sys.argv[1:]] or [1.0, 10.0])

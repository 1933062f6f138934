"""Run the benchmarks and print a Markdown table (copied into the README by hand).

Usage: ``python benchmarks/run.py [substring ...]`` (``make bench``). Each benchmark runs in a
fresh subprocess: the time is the best of three runs, the memory the process's peak resident
set size (numpy, USD and everything else) minus its size before the first run.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def registry() -> dict[str, Callable[[], tuple]]:
    from bench_forest import BENCHMARKS as FOREST
    from bench_lsystem import BENCHMARKS as LSYSTEM
    from bench_profile import BENCHMARKS as PROFILE
    from bench_sensors import BENCHMARKS as SENSORS
    from bench_tree import BENCHMARKS as TREE

    return {**LSYSTEM, **TREE, **PROFILE, **FOREST, **SENSORS}


def run_one(name: str) -> dict:
    fn = registry()[name]
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    best = float("inf")
    result: tuple = ()
    for _ in range(3):
        t = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    units, label, *note = result
    return {
        "seconds": best,
        "units": units,
        "label": label,
        "peak_mib": (peak - base) / 1024,
        "note": note[0] if note else "",
    }


def main(filters: list[str]) -> None:
    print("| benchmark | size | time | throughput | peak memory | notes |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name in registry():
        if filters and not any(f in name for f in filters):
            continue
        r = subprocess.run(
            [sys.executable, __file__, "--one", name], capture_output=True, text=True, check=True
        )
        d = json.loads(r.stdout)
        print(
            f"| {name} | {d['units']:,} {d['label']} | {d['seconds'] * 1000:,.0f} ms | "
            f"{d['units'] / d['seconds'] / 1e6:,.2f} M {d['label']}/s | "
            f"{d['peak_mib']:,.0f} MiB | {d['note']} |",
            flush=True,
        )


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--one":
        print(json.dumps(run_one(sys.argv[2])))
    else:
        main(sys.argv[1:])

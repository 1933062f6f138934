"""Run the benchmarks and print a Markdown table (copied into the README by hand).

Usage: ``python benchmarks/run.py [name ...]`` (``make bench``). Each benchmark reports the best
of a few repeats and the peak traced memory of one run.
"""

from __future__ import annotations

import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_lsystem import BENCHMARKS as LSYSTEM

ALL: dict[str, Callable[[], tuple[int, str]]] = {**LSYSTEM}


def measure(fn: Callable[[], tuple[int, str]], repeats: int = 3) -> tuple[float, int, str, float]:
    best = float("inf")
    units, label = 0, ""
    for _ in range(repeats):
        t = time.perf_counter()
        units, label = fn()
        best = min(best, time.perf_counter() - t)
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return best, units, label, peak / 2**20


def main(names: list[str]) -> None:
    print("| benchmark | size | time | throughput | peak memory |")
    print("| --- | --- | --- | --- | --- |")
    for name, fn in ALL.items():
        if names and name not in names:
            continue
        secs, units, label, peak = measure(fn)
        print(
            f"| {name} | {units:,} {label} | {secs * 1000:,.0f} ms | "
            f"{units / secs / 1e6:,.2f} M {label}/s | {peak:,.0f} MiB |",
            flush=True,
        )


if __name__ == "__main__":
    main(sys.argv[1:])

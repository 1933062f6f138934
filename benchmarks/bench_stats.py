"""``usdforest stats`` on the default forest with and without the canopy measured by rays
(issue 43: the ray-based figures within 3x the inventory's time): whole processes, as a user
runs them, one run each; the first ray run gathers the prototypes into the scene cache (cold),
the second reads them (warm; the figures the first kept are removed before it), and the third
reads the figures the second kept (what a second ``stats`` of a forest costs).

Usage: ``python benchmarks/bench_stats.py`` (``make bench`` runs it). Prints a Markdown table
of wall time, peak memory and the ratio to ``stats --no-rays``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WRAP = (
    "import resource, runpy, sys\n"
    "sys.argv = ['usdforest', *sys.argv[1:]]\n"
    "try:\n"
    "    runpy.run_module('usdforest', run_name='__main__')\n"
    "finally:\n"
    "    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n"
)


def run(args: list[str], env: dict) -> tuple[float, float, dict]:
    """Wall seconds, peak memory (MiB) and JSON output of ``usdforest ARGS`` in a child."""
    start = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", WRAP, *args], capture_output=True, text=True,
                         env=env)  # fmt: skip
    seconds = time.perf_counter() - start
    if out.returncode:
        raise SystemExit(out.stderr)
    peak = int(out.stderr.strip().splitlines()[-1]) / 1024
    return seconds, peak, json.loads(out.stdout)


def main() -> None:
    work = Path(tempfile.mkdtemp(prefix="usdforest-bench-stats-"))
    env = {**os.environ, "USDFOREST_CACHE": str(work / "cache")}
    stage = work / "forest.usda"
    subprocess.run([sys.executable, "-m", "usdforest", "build", "-q", "--no-thumbnail",
                    str(stage)], check=True, env=env)  # fmt: skip
    base, base_peak, _ = run(["stats", str(stage), "--json", "-q", "--no-rays"], env)
    rows = [("stats --no-rays (inventory, crown footprint)", base, base_peak, None)]
    for label in ("stats (rays, cold scene cache)", "stats (rays, warm scene cache)"):
        for kept in (work / "cache").glob("stats-*.json"):  # measure, not read back
            kept.unlink()
        rows.append((label, *run(["stats", str(stage), "--json", "-q"], env)))
    again = run(["stats", str(stage), "--json", "-q"], env)
    rows.append(("stats (rays, the figures kept)", *again))
    print("Default forest, one run each (whole processes):\n")
    print("| run | wall time | vs --no-rays | peak memory | canopy cover | gap fraction "
          "0/30/45/60 | clumping 0 |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for label, seconds, peak, f in rows:
        head = f"| {label} | {seconds:.1f} s | {seconds / base:.2f}x | {peak:,.0f} MiB |"
        if f is None:
            print(head + " | | |")
            continue
        gaps = "/".join(f"{f['gap_fraction'][k]:.3f}" for k in ("0", "30", "45", "60"))
        print(f"{head} {f['canopy_cover']:.3f} | {gaps} | {f['clumping_index']['0']:.2f} |")


if __name__ == "__main__":
    main()

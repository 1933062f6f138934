"""An inventory of 2,000 rows (12 % saplings; the plot of ``tests/test_inventory_sizes.py``)
built with the inventory's default of 64 size classes a species against the sampled stands'
24 (what inventories had before): wall time, peak memory, tree assets, and the rows whose DBH
in ``trees.csv`` is more than 5 % off.

Usage: ``python benchmarks/bench_inventory.py`` (``make bench`` runs it). One run each.
"""

from __future__ import annotations

import csv
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from bench_stats import WRAP
from test_inventory_sizes import RECIPE, stem_map


def main() -> None:
    work = Path(tempfile.mkdtemp(prefix="usdforest-bench-inventory-"))
    rows = stem_map(work / "stems.csv")
    print("| classes a species | wall time | peak memory | tree assets | rows > 5 % off in DBH |")
    print("| --- | --- | --- | --- | --- |")
    base = None
    runs = (("24 (a sampled stand's default)", "[forest]\nvariants = 24\n"), ("64 (default)", ""))
    for label, extra in runs:
        (work / "r.toml").write_text(RECIPE + extra)
        out = work / f"f{len(extra)}.usda"
        start = time.perf_counter()
        args = ["build", "-q", "--no-thumbnail", "-p", str(work / "r.toml"), str(out)]
        run = subprocess.run([sys.executable, "-c", WRAP, *args], capture_output=True, text=True)
        seconds = time.perf_counter() - start
        if run.returncode:
            raise SystemExit(run.stderr)
        peak = int(run.stderr.strip().splitlines()[-1]) / 1024
        assets = len(list((work / f"{out.stem}_assets" / "trees").glob("*.usdc")))
        trees = {int(t["id"]): float(t["dbh"]) for t in csv.DictReader(
            open(work / f"{out.stem}_assets" / "trees.csv"))}  # fmt: skip
        off = sum(1 for k, d in enumerate(rows["dbh"]) if d > 0 and abs(trees[k] / d - 1) > 0.05)
        base = base or (seconds, peak)
        print(f"| {label} | {seconds:.1f} s ({seconds / base[0]:.2f}x) | {peak:,.0f} MiB "
              f"({peak / base[1]:.2f}x) | {assets} | {off} |")  # fmt: skip


if __name__ == "__main__":
    main()

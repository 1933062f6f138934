"""Whole ``usdforest`` processes as a user runs them, best of five, against the targets of
issue 14: ``--help`` under 0.3 s, a small ``tree`` under 0.8 s, and a sonar scan of a
100k-leaf tree end to end under 3 s, and ``sample`` of a million sites under 1.5 s.

Usage: ``python benchmarks/bench_startup.py`` (``make bench`` runs it). Prints a Markdown
table. Byte-code caching is on, as after any install (the first run writes the caches).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

EXE = Path(sys.executable).with_name("usdforest")
PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
CASES = (
    ("usdforest --help", ["--help"], 0.3),
    (
        "usdforest tree (paper-rule-1)",
        ["tree", "{tmp}/t.usda", "--species", "paper-rule-1", "--force"],
        0.8,
    ),
    (
        "usdforest scan --sensor sonar (100,047-leaf broadleaf)",
        ["scan", "{tmp}/big.usdc", "--sensor", "sonar", "--pose", "-6,0,5.5", "-o", "{tmp}/e.npz",
         "--force"],
        3.0,
    ),
    (
        "usdforest sample (stress-1m: 1,000,889 sites)",
        ["sample", "{tmp}/s.csv", "-p", str(PIPELINES / "stress-1m.toml"), "--force"],
        1.5,
    ),
)  # fmt: skip


def _big_tree(path: Path) -> None:
    from dataclasses import replace

    from usdforest.grow.species import get_species
    from usdforest.usd.tree import write_tree

    sp = get_species("broadleaf")
    write_tree(replace(sp, geometry=replace(sp.geometry, leaves_per_site=285.0)), path, seed=1)


def main() -> None:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    print("| command | best of 5 | target | ratio |")
    print("| --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        _big_tree(Path(tmp) / "big.usdc")
        for name, args, target in CASES:
            argv = [str(EXE), *(a.format(tmp=tmp) for a in args)]
            subprocess.run(argv, env=env, capture_output=True, check=True)  # warm the caches
            best = float("inf")
            for _ in range(5):
                t = time.perf_counter()
                subprocess.run(argv, env=env, capture_output=True, check=True)
                best = min(best, time.perf_counter() - t)
            print(f"| {name} | {best:.2f} s | {target:g} s | {best / target:.2f} |", flush=True)


if __name__ == "__main__":
    main()

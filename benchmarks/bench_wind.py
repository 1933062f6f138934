"""What a minute of wind costs a user: ``usdforest build`` of the default recipe as it is and
with ``[wind]`` (60 s at 30 frames/s, the other keys their defaults), as whole processes,
alternating, best of two each, in one run; and the size of the wind layer. Target (issue 41):
the windy build within 2x of the still one.

Usage: ``python benchmarks/bench_wind.py`` (``make bench`` runs it). Prints a Markdown table;
memory is each process's own peak resident set.
"""

from __future__ import annotations

import sys
import tempfile
import tomllib
from pathlib import Path

import tomli_w
from bench_floor import DEFAULT, _run

TARGET = 2.0
WIND = {"duration": 60.0, "fps": 30.0}


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        recipes = {}
        for k, name in enumerate(("still", "one minute of wind")):
            data = tomllib.loads(DEFAULT.read_text())
            if k:
                data["wind"] = dict(WIND)
            recipes[name] = work / f"v{k}.toml"
            recipes[name].write_text(tomli_w.dumps(data))
        best: dict[str, tuple[float, float]] = {}
        for _ in range(2):
            for k, (name, recipe) in enumerate(recipes.items()):
                s, mib = _run(["build", str(work / f"v{k}.usda"), "-p", str(recipe), "--force"])
                old = best.get(name, (float("inf"), 0.0))
                best[name] = (min(old[0], s), max(old[1], mib))
        layer = (work / "v1_assets" / "wind.usdc").stat().st_size
        trees = (work / "v1_assets" / "trees.csv").read_text().count("\n") - 1
    (ts, ms), (tw, mw) = best["still"], best["one minute of wind"]
    print("| build | still | one minute of wind (30 frames/s) | ratio: time | memory | target |")
    print("| --- | --- | --- | --- | --- | --- |")
    print(
        f"| default forest | {ts:.1f} s, {ms:,.0f} MiB | {tw:.1f} s, {mw:,.0f} MiB | "
        f"{tw / ts:.2f}x | {mw / ms:.2f}x | {TARGET}x |"
    )
    print(
        f"\nwind.usdc: {layer / 2**20:.1f} MiB for {trees} trees x 1,801 time codes "
        f"({layer / trees / 1801:.1f} B a tree a time code)"
    )


if __name__ == "__main__":
    sys.exit(main())

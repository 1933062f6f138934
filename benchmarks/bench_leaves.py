"""What the broadleaves' own leaves cost a user: ``usdforest build``, ``preview`` and a lidar
``scan`` of the default recipe as it is (beech and birch with their species' leaf templates and
leaf inclination distributions) and with every broadleaf on the one generic leaf its preset had
before (``leaf_broadleaf`` at its old size, the leaf angle from the twig), as whole processes,
alternating, best of two each, in one run; and the triangles each composes to at full detail
(``usdforest info --full``). Target (issue 39): within 1.3x of the generic leaf's time and
memory.

Usage: ``python benchmarks/bench_leaves.py`` (``make bench`` runs it). Prints a Markdown table.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import tomli_w
from bench_floor import EXE, best_of_two

DEFAULT = Path(__file__).resolve().parents[1] / "pipelines" / "default.toml"
TARGET = 1.3
GENERIC = {  # preset -> its leaf before it had its own (template, length in metres)
    "european-beech": 0.1,
    "sessile-oak": 0.12,
    "silver-birch": 0.06,
}


def _recipes(work: Path) -> dict[str, Path]:
    own = tomllib.loads(DEFAULT.read_text())
    generic = tomllib.loads(DEFAULT.read_text())
    for name, size in GENERIC.items():
        if name in generic.get("species", {}):
            generic["species"][name]["geometry"] = {
                "leaf": "leaf_broadleaf",
                "leaf_size": size,
                "leaf_inclination": [],
                "shade_inclination": [],
            }
    out = {}
    for k, (name, data) in enumerate((("species' leaves", own), ("one generic leaf", generic))):
        out[name] = work / f"v{k}.toml"
        out[name].write_text(tomli_w.dumps(data))
    return out


def _triangles(stage: Path) -> int:
    text = subprocess.run(
        [str(EXE), "info", str(stage), "--full"], capture_output=True, text=True, check=True
    ).stdout
    return int(re.search(r"triangles\s+([\d,]+)", text).group(1).replace(",", ""))


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        recipes = _recipes(work)
        best = best_of_two(recipes, work)
        triangles = {n: _triangles(work / f"v{k}.usda") for k, n in enumerate(recipes)}
    names = list(recipes)
    print("| step | " + " | ".join(names) + " | ratio: time | memory | target |")
    print("| --- " * (len(names) + 4) + "|")
    for step in ("build", "preview", "scan"):
        cells = [f"{best[(step, n)][0]:.1f} s, {best[(step, n)][1]:,.0f} MiB" for n in names]
        (to, mo), (tg, mg) = best[(step, names[0])], best[(step, names[1])]
        ratios = f" | {to / tg:.2f}x | {mo / mg:.2f}x | {TARGET}x |"
        print(f"| {step} | " + " | ".join(cells) + ratios)
    cells = [f"{triangles[n] / 1e9:.2f} G" for n in names]
    print("| triangles at full detail | " + " | ".join(cells)
          + f" | {triangles[names[0]] / triangles[names[1]]:.2f}x | | |")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())

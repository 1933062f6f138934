"""What the default forest's layers under the crowns cost a user: ``usdforest build``,
``preview`` and a lidar ``scan`` of the default recipe as it is (dead wood, ground
vegetation, shrubs and young trees), without its understorey (``[shrubs]`` and
``[regeneration]``), without its ground vegetation too, and without any of them (the bare
stand), as whole processes, alternating, best of two each, in one run. Target (issue 39):
within 1.3x of the bare stand's time and memory.

Usage: ``python benchmarks/bench_floor.py`` (``make bench`` runs it). Prints a Markdown
table; memory is each process's own peak resident set (``os.wait4``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import tomli_w

EXE = Path(sys.executable).with_name("usdforest")
DEFAULT = Path(__file__).resolve().parents[1] / "pipelines" / "default.toml"
TARGET = 1.3
POSE = "50,50,2"  # a VLP-16 at head height in the middle of the plot
LAYERS = {  # variant -> the tables taken out of the default recipe
    "default": (),
    "no understorey": ("shrubs", "regeneration"),
    "dead wood only": ("shrubs", "regeneration", "groundcover"),
    "bare stand": ("shrubs", "regeneration", "groundcover", "deadwood"),
}


def _run(args: list[str]) -> tuple[float, float]:
    """Seconds and peak MiB of one ``usdforest`` process."""
    t = time.perf_counter()
    proc = subprocess.Popen([str(EXE), *args, "-q"], stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"usdforest {' '.join(args)} failed ({proc.returncode})")
    return time.perf_counter() - t, usage.ru_maxrss / 1024


def best_of_two(recipes: dict[str, Path], work: Path) -> dict[tuple[str, str], tuple[float, float]]:
    """``(step, recipe name) -> (best seconds, peak MiB)`` of ``usdforest build``, ``preview``
    and a VLP-16 ``scan`` of each recipe, alternating, best of two; the forests stay in
    ``work`` as ``v0.usda``, ``v1.usda``... in the recipes' order."""
    best: dict[tuple[str, str], tuple[float, float]] = {}
    for _ in range(2):
        for k, (name, recipe) in enumerate(recipes.items()):
            stem = work / f"v{k}"
            steps = {
                "build": ["build", f"{stem}.usda", "-p", str(recipe), "--force"],
                "preview": ["preview", f"{stem}.usda", "-o", f"{stem}.png", "--force"],
                "scan": ["scan", f"{stem}.usda", "--sensor", "lidar", "--pose", POSE,
                         "-o", f"{stem}.npz", "--force"],
            }  # fmt: skip
            for step, args in steps.items():
                s, mib = _run(args)
                old = best.get((step, name), (float("inf"), 0.0))
                best[(step, name)] = (min(old[0], s), max(old[1], mib))
    return best


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        recipes = {}
        for k, (name, dropped) in enumerate(LAYERS.items()):
            data = tomllib.loads(DEFAULT.read_text())
            for table in dropped:
                data.pop(table)
            recipes[name] = work / f"v{k}.toml"
            recipes[name].write_text(tomli_w.dumps(data))
        best = best_of_two(recipes, work)
    names = list(LAYERS)
    print("| step | " + " | ".join(names) + " | default / bare: time | memory | target |")
    print("| --- " * (len(names) + 4) + "|")
    for step in ("build", "preview", "scan"):
        cells = [f"{best[(step, n)][0]:.1f} s, {best[(step, n)][1]:,.0f} MiB" for n in names]
        (tw, mw), (tb, mb) = best[(step, names[0])], best[(step, names[-1])]
        print(
            f"| {step} | " + " | ".join(cells) + f" | {tw / tb:.2f}x | {mw / mb:.2f}x | {TARGET}x |"
        )


if __name__ == "__main__":
    main()

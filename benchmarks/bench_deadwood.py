"""What the default forest's dead wood costs a user: ``usdforest build``, ``preview`` and a
lidar ``scan`` of the default recipe with its ``[deadwood]`` table and without it, as whole
processes, alternating, best of two each, in one run. Target (issue 39): within 1.3x of the
time and memory without.

Usage: ``python benchmarks/bench_deadwood.py`` (``make bench`` runs it). Prints a Markdown
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


def _run(args: list[str]) -> tuple[float, float]:
    """Seconds and peak MiB of one ``usdforest`` process."""
    t = time.perf_counter()
    proc = subprocess.Popen([str(EXE), *args, "-q"], stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"usdforest {' '.join(args)} failed ({proc.returncode})")
    return time.perf_counter() - t, usage.ru_maxrss / 1024


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        data = tomllib.loads(DEFAULT.read_text())
        data.pop("deadwood")
        bare = work / "bare.toml"
        bare.write_text(tomli_w.dumps(data))
        recipes = {"with dead wood": DEFAULT, "without": bare}
        best: dict[tuple[str, str], tuple[float, float]] = {}
        for _ in range(2):
            for name, recipe in recipes.items():
                stem = work / name.replace(" ", "_")
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
    print("| step | with dead wood | without | time ratio | memory ratio | target |")
    print("| --- | --- | --- | --- | --- | --- |")
    for step in ("build", "preview", "scan"):
        (tw, mw), (tb, mb) = best[(step, "with dead wood")], best[(step, "without")]
        print(
            f"| {step} | {tw:.1f} s, {mw:,.0f} MiB | {tb:.1f} s, {mb:,.0f} MiB | "
            f"{tw / tb:.2f}x | {mw / mb:.2f}x | {TARGET}x |"
        )


if __name__ == "__main__":
    main()

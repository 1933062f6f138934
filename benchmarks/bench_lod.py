"""Levels of detail: composed triangles per tree and per hectare, build times with colliders
and levels, and the stands opened and rendered in Blender (its peak memory).

Usage: ``python benchmarks/bench_lod.py`` (``make bench`` runs it after the main table).
Prints Markdown tables. Blender runs from ``.venv-blender`` (``make test`` makes it) or
``USDFOREST_BLENDER_PYTHON``; without it that row says so.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ROOT / "pipelines"
LEVELS = ("full", "medium", "proxy")

_OPEN = """
import json, sys
from usdforest.usd.stats import stage_info
info = stage_info(sys.argv[1])
print(json.dumps({"triangles": info["triangles"], "trees": info["trees"]}))
"""


def _recipe(name: str, **forest):
    from usdforest.recipe import parse_recipe, read_recipe

    base = read_recipe(PIPELINES / f"{name}.toml")
    data = dict(base.data, forest={**base.data.get("forest", {}), **forest})
    return parse_recipe(data, base.base, base.source)


def _build(name: str, folder: Path, **forest) -> tuple[Path, float, int]:
    from usdforest.usd.forest import write_forest

    out = folder / f"{name}-{'-'.join(f'{k}{v}' for k, v in forest.items())}.usda"
    t = time.perf_counter()
    b = write_forest(_recipe(name, **forest), out)
    return out, time.perf_counter() - t, b.n_trees


def _composed(out: Path) -> dict:
    r = subprocess.run(
        [sys.executable, "-c", _OPEN, str(out)], capture_output=True, text=True, check=True
    )
    return json.loads(r.stdout)


def _hectares(name: str) -> float:
    return _recipe(name).region.area / 1e4


def _blender_python() -> str | None:
    py = os.environ.get("USDFOREST_BLENDER_PYTHON") or str(ROOT / ".venv-blender/bin/python")
    return py if Path(py).exists() else None


def _blender(py: str | None, out: Path, png: Path | None = None) -> str:
    """Open ``out`` in Blender (and render it to ``png``): a table cell of its figures."""
    if py is None:
        return "bpy not installed"
    args = [py, str(ROOT / "tests" / "blender_probe.py"), str(out)]
    r = subprocess.run(
        args + ([str(png)] if png else []), capture_output=True, text=True, check=False
    )
    if r.returncode:
        return f"failed: {r.stderr.strip().splitlines()[-1][:80]}"
    d = json.loads(r.stdout.strip().splitlines()[-1])
    render = f", render {d['render_seconds']:.1f} s" if png else ""
    return (
        f"import {d['import_seconds']:.1f} s{render}, {d['scene_triangles']:,} triangles, "
        f"peak {d['peak_rss_mb'] / 1024:.2f} GB"
    )


# Blender is asked for what fits this 24 GB machine: every level of the quick 1 ha stand (the
# closed-canopy default is 8.9 G triangles at full), and the 1 km² stand at the proxy level
# (its full level is 36 G triangles)
BLENDER_RUNS = {
    ("quick-mixed", "full"),
    ("quick-mixed", "medium"),
    ("quick-mixed", "proxy"),
    ("stand-1km2", "proxy"),
}


def main() -> None:
    folder = Path(tempfile.mkdtemp(prefix="usdforest-lod-"))
    py = _blender_python()
    try:
        print(
            "| stand | level | trees | composed triangles | per tree | per hectare | "
            "build (colliders trunk) | build (colliders none) | Blender 5.0 (Cycles CPU, "
            "320x240, 4 spp) |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for name in ("quick-mixed", "stand-1km2"):
            ha = _hectares(name)
            for level in LEVELS:
                out, secs, n = _build(name, folder, lod=level)
                _, bare, _ = _build(name, folder, lod=level, colliders="none")
                c = _composed(out)
                png = folder / f"{name}-{level}.png"
                blender = _blender(py, out, png) if (name, level) in BLENDER_RUNS else "not run"
                if png.exists() and (name, level) == ("stand-1km2", "proxy"):
                    shutil.copyfile(png, ROOT / "docs" / "figures" / "blender-1km2-proxy.png")
                print(
                    f"| {name} ({ha:,.0f} ha) | {level} | {n:,} | {c['triangles']:,} | "
                    f"{c['triangles'] / n:,.0f} | {c['triangles'] / ha:,.0f} | "
                    f"{secs:.1f} s | {bare:.1f} s | {blender} |",
                    flush=True,
                )
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()

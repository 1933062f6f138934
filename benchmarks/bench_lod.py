"""Levels of detail: triangles and composed memory per tree and per hectare, build times with
colliders and levels, and the 1 km² stand at the proxy level opened and rendered in Blender.

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
import json, resource, sys
from usdforest.usd.stats import stage_info
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
info = stage_info(sys.argv[1])
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"triangles": info["triangles"], "trees": info["trees"],
                  "mib": (after - before) / 1024}))
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


def main() -> None:
    folder = Path(tempfile.mkdtemp(prefix="usdforest-lod-"))
    try:
        print("| stand | level | trees | composed triangles | per tree | per hectare | "
              "composed memory | build (colliders trunk) | build (colliders none) |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for name in ("default", "stand-1km2"):
            ha = _hectares(name)
            for level in LEVELS:
                out, secs, n = _build(name, folder, lod=level)
                _, bare, _ = _build(name, folder, lod=level, colliders="none")
                c = _composed(out)
                print(
                    f"| {name} ({ha:,.0f} ha) | {level} | {n:,} | {c['triangles']:,} | "
                    f"{c['triangles'] / n:,.0f} | {c['triangles'] / ha:,.0f} | "
                    f"{c['mib']:,.0f} MiB ({c['mib'] * 1024 / ha:,.0f} KiB/ha) | "
                    f"{secs:.1f} s | {bare:.1f} s |",
                    flush=True,
                )
        py = _blender_python()
        if py is None:
            print("\nBlender: bpy not installed (make test installs it in .venv-blender)")
            return
        out, _, n = _build("stand-1km2", folder, lod="proxy")
        png = folder / "blender-1km2-proxy.png"
        r = subprocess.run(
            [py, str(ROOT / "tests" / "blender_probe.py"), str(out), str(png)],
            capture_output=True,
            text=True,
            check=False,
        )
        if r.returncode:
            print(f"\nBlender failed: {r.stderr[-1000:]}")
            return
        d = json.loads(r.stdout.strip().splitlines()[-1])
        keep = ROOT / "docs" / "figures" / "blender-1km2-proxy.png"
        shutil.copyfile(png, keep)
        print(
            f"\nBlender {py}: stand-1km2 at proxy, {n:,} trees: import "
            f"{d['import_seconds']:.1f} s, {d['instances']:,} mesh instances, "
            f"{d['scene_triangles']:,} triangles, Cycles 320x240 4 spp "
            f"{d['render_seconds']:.1f} s, peak memory {d['peak_rss_mb']:,.0f} MB "
            f"(render: {keep.relative_to(ROOT)})"
        )
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()

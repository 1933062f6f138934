"""Thinning throughput and end-to-end forest builds (1 ha, 1 km², 1M trees)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from usdforest.pointprocess import Constant, ExpressionIntensity, Rectangle, thin
from usdforest.recipe import read_recipe
from usdforest.usd.forest import write_forest

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
KM2 = Rectangle(0, 0, 1000, 1000)
EXPR = ExpressionIntensity("0.5 + 0.5 * sin(x / 50) * cos(y / 70)")


def thin_constant() -> tuple[int, str]:
    return len(thin(KM2, Constant(1.0), np.random.default_rng(1))), "sites"


def thin_expression() -> tuple[int, str]:
    return len(thin(KM2, EXPR, np.random.default_rng(1))), "sites"


def _build(name: str) -> tuple[int, str, str]:
    out = Path(tempfile.mkdtemp(prefix="usdforest-bench-")) / "forest.usda"
    try:
        b = write_forest(read_recipe(PIPELINES / f"{name}.toml"), out)
        assets = out.parent / "forest_assets"
        inst = (assets / "instances.usdc").stat().st_size
        total = sum(p.stat().st_size for p in assets.rglob("*") if p.is_file())
        note = (
            f"instances.usdc {inst / 2**20:,.1f} MiB ({inst / b.n_trees:.1f} B/tree), "
            f"folder {total / 2**20:,.1f} MiB"
        )
        return b.n_trees, "trees", note
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)


_BUILT: dict[str, Path] = {}


def open_stress() -> tuple[int, str, str]:
    """Open the 1M-tree forest and read its positions (the build itself is not timed)."""
    import resource
    import time

    from pxr import Usd, UsdGeom

    if "stress" not in _BUILT:
        out = Path(tempfile.mkdtemp(prefix="usdforest-bench-")) / "forest.usda"
        write_forest(read_recipe(PIPELINES / "stress-1m.toml"), out)
        _BUILT["stress"] = out
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    stage = Usd.Stage.Open(str(_BUILT["stress"]))
    t1 = time.perf_counter()
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    n = len(pi.GetPositionsAttr().Get())
    t2 = time.perf_counter()
    rss = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
    return (
        n,
        "positions",
        (
            f"open {1000 * (t1 - t0):.0f} ms, read {1000 * (t2 - t1):.1f} ms, "
            f"+{rss:.0f} MiB resident"
        ),
    )


BENCHMARKS = {
    "thin: constant, 1 km², 1 tree/m²": thin_constant,
    "thin: expression, 1 km²": thin_expression,
    "build: stand-1ha": lambda: _build("stand-1ha"),
    "build: stand-1km2": lambda: _build("stand-1km2"),
    "build: stress-1m": lambda: _build("stress-1m"),
    "open: stress-1m forest, read positions": open_stress,
}

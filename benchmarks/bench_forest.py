"""Thinning throughput and end-to-end forest builds (1 ha, 1 km², 1M trees)."""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from usdforest.recipe import read_recipe
from usdforest.sites.pointprocess import (
    Bump,
    Constant,
    ExpressionIntensity,
    GaussianMixture,
    Rectangle,
    thin,
)
from usdforest.usd.forest import write_forest

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
KM2 = Rectangle(0, 0, 1000, 1000)
EXPR = ExpressionIntensity("0.5 + 0.5 * sin(x / 50) * cos(y / 70)")


def thin_constant() -> tuple[int, str]:
    return len(thin(KM2, Constant(1.0), np.random.default_rng(1))), "sites"


def thin_expression() -> tuple[int, str]:
    return len(thin(KM2, EXPR, np.random.default_rng(1))), "sites"


MIXTURE = GaussianMixture(
    0.6, (Bump(300, 300, 80, 0.8), Bump(700, 650, 120, 0.6), Bump(500, 800, 60, -0.4))
)


def _plain_thinning(rng: np.random.Generator) -> np.ndarray:
    """The floor: Lewis-Shedler thinning of MIXTURE on KM2 in plain numpy, nothing else."""
    lam_star = 0.6 + 0.8 + 0.6
    n = rng.poisson(lam_star * 1e6)
    x, y, u = rng.uniform(0, 1000, n), rng.uniform(0, 1000, n), rng.uniform(0, 1, n)
    lam = np.full(n, 0.6)
    for b in MIXTURE.bumps:
        lam += b.peak * np.exp(-((x - b.x) ** 2 + (y - b.y) ** 2) / (2 * b.sigma**2))
    keep = u * lam_star < np.maximum(lam, 0.0)
    return np.column_stack([x[keep], y[keep]])


def thin_mixture() -> tuple[int, str, str]:
    """thin() of a Gaussian mixture against the plain thinning of the same process, each
    the best of five in this run (target: within 1.15x)."""
    best = {}
    for name, fn in (
        ("thin", lambda rng: thin(KM2, MIXTURE, rng)),
        ("plain", _plain_thinning),
    ):
        times = []
        for i in range(5):
            rng = np.random.default_rng(i)
            t = time.perf_counter()
            n = len(fn(rng))
            times.append(time.perf_counter() - t)
        best[name] = min(times)
    ratio = best["thin"] / best["plain"]
    return (
        n,
        "sites",
        f"{best['thin'] * 1e3:.0f} ms vs {best['plain'] * 1e3:.0f} ms plain numpy: "
        f"{ratio:.2f}x the floor (target 1.15x)",
    )


def _build(name: str, side: float | None = None) -> tuple[int, str, str]:
    """Build a pipeline (``side``: its region made a square of that many metres)."""
    out = Path(tempfile.mkdtemp(prefix="usdforest-bench-")) / "forest.usda"
    recipe = read_recipe(PIPELINES / f"{name}.toml")
    if side is not None:
        recipe = replace(recipe, region=Rectangle(0, 0, side, side), max_trees=10**7)
    try:
        b = write_forest(recipe, out)
        assets = out.parent / "forest_assets"
        # the trees' instancers: one layer, or one a tile
        layers = (
            [assets / "instances.usdc"] if not b.n_tiles else [*(assets / "tiles").glob("*.usdc")]
        )
        inst = sum(p.stat().st_size for p in layers)
        total = sum(p.stat().st_size for p in assets.rglob("*") if p.is_file())
        name = "instances.usdc" if not b.n_tiles else f"{b.n_tiles} tile layers"
        note = (
            f"{name} {inst / 2**20:,.1f} MiB ({inst / b.n_trees:.1f} B/tree), "
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


def exact_functions() -> tuple[int, str, str]:
    """The build's CPU-independent elementary functions (:mod:`usdforest.grow.exact`, the C
    library's scalar ones) against numpy's SIMD loops, on the largest array a default build
    passes them (199,064 elements), each the best of five in this run."""
    from usdforest.grow import exact

    n = 199_064
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0.01, 10.0, n), rng.uniform(-3.0, 3.0, n)
    pairs = {
        "exp": (lambda: exact.exp(y), lambda: np.exp(y)),
        "log": (lambda: exact.log(x), lambda: np.log(x)),
        "power": (lambda: exact.power(x, y), lambda: np.power(x, y)),
        "arctan2": (lambda: exact.arctan2(y, x), lambda: np.arctan2(y, x)),
    }
    parts = []
    for name, (ours, theirs) in pairs.items():
        best = []
        for fn in (ours, theirs):
            times = []
            for _ in range(5):
                t0 = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t0)
            best.append(min(times))
        parts.append(
            f"{name} {1e9 * best[0] / n:.0f} ns vs numpy {1e9 * best[1] / n:.1f} ns an element"
        )
    return 4 * n, "elements", "; ".join(parts)


STEMS_CLIENT = """
import json, sys, time
from dataclasses import replace
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.usd.forest import write_forest
recipe = read_recipe(default_recipe_path())
recipe = replace(recipe, stems=sys.argv[2] == "stems")
t = time.perf_counter()
write_forest(recipe, sys.argv[1], thumbnail=False)
hwm = next(ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:"))
print(json.dumps({"wall": time.perf_counter() - t, "peak": int(hwm.split()[1]) / 1024}))
"""


def _trunk_triangles(assets: Path) -> tuple[int, int]:
    """Trunk templates and their triangles in a forest's templates folder."""
    from pxr import Usd, UsdGeom

    n = tri = 0
    for f in sorted((assets / "templates").glob("*.usdc")):
        if not (f.name.startswith("stem_") or f.name == "trunk_cone.usdc"):
            continue
        stage = Usd.Stage.Open(str(f))
        m = UsdGeom.Mesh(stage.GetPrimAtPath("/Template/Mesh"))
        n, tri = n + 1, tri + len(m.GetFaceVertexCountsAttr().Get())
    return n, tri


def stems_cost() -> tuple[int, str, str]:
    """The default forest built with its stems (each tree asset's own trunk: taper, flare,
    out-of-round sections, bark) and with the shared conical trunk (``[forest] stems =
    false``), each in a process of its own in this run: build time, peak memory (VmHWM),
    trunk triangles and the assets folder."""
    import json
    import subprocess
    import sys

    got = {}
    for kind in ("stems", "cone"):
        folder = Path(tempfile.mkdtemp(prefix="usdforest-bench-"))
        try:
            out = subprocess.run(
                [sys.executable, "-c", STEMS_CLIENT, str(folder / "forest.usda"), kind],
                capture_output=True, text=True, check=True,
            )  # fmt: skip
            report = json.loads(out.stdout.strip().splitlines()[-1])
            assets = folder / "forest_assets"
            size = sum(p.stat().st_size for p in assets.rglob("*") if p.is_file())
            got[kind] = {**report, "size": size, "trunks": _trunk_triangles(assets)}
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    a, b = got["stems"], got["cone"]
    return (
        a["trunks"][0],
        "stems",
        f"build {a['wall']:.1f} s vs {b['wall']:.1f} s with the cone "
        f"({a['wall'] / b['wall']:.2f}x), "
        f"peak {a['peak']:,.0f} vs {b['peak']:,.0f} MiB ({a['peak'] / b['peak']:.2f}x), "
        f"trunk triangles {a['trunks'][1]:,} in {a['trunks'][0]} stems vs {b['trunks'][1]:,} "
        f"in {b['trunks'][0]} template, assets {a['size'] / 2**20:.1f} vs "
        f"{b['size'] / 2**20:.1f} MiB ({a['size'] / b['size']:.2f}x)",
    )


BENCHMARKS = {
    "build: the default forest's stems vs the shared cone": stems_cost,
    "thin: constant, 1 km², 1 tree/m²": thin_constant,
    "thin: expression, 1 km²": thin_expression,
    "build: stand-1ha": lambda: _build("stand-1ha"),
    "build: stand-1km2": lambda: _build("stand-1km2"),
    "build: landscape-4km2 (UTM, 16 tiles)": lambda: _build("landscape-4km2"),
    "thin: Gaussian mixture vs plain numpy, 1 km²": thin_mixture,
    "build: stress-1m": lambda: _build("stress-1m"),
    "build: stress-1m on 5 km² (5M trees)": lambda: _build("stress-1m", side=2236.0),
    "open: stress-1m forest, read positions": open_stress,
    "exact: exp, log, power, arctan2 vs numpy's SIMD": exact_functions,
}

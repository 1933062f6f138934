"""The same bytes whatever BLAS kernel and SIMD loops the machine's numpy picks (issue 61,
item 8): a plot of the default recipe (its dead wood, colliders, layers under the crowns and
thumbnail), built in two processes that force two OpenBLAS kernels, the second also with
numpy's SIMD loops above its baseline turned off (``NPY_DISABLE_CPU_FEATURES``: an AVX-512
machine builds as an AVX2 one, an AVX2 one as a machine without), is the same file for
file. Under Haswell's kernel and this machine's own, a collider's position and the
thumbnail differed in their last bits (BLAS sums in the kernel's order and fuses
multiply-adds); with AVX-512's loops off, the colliders differed (numpy's ``exp``, ``log``,
``power`` and ``arctan2`` round otherwise there). usdforest's geometry goes through
:mod:`usdforest.grow.exact` instead. (A 20 m plot came out the same under both kernels
before that too: 30 m is the smallest that showed it.)"""

from __future__ import annotations

import math
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

from usdforest.recipe import default_recipe_path

KERNELS = ("Haswell", "Sandybridge")  # both run on any x86-64 CPU with AVX2

BUILD = """
import sys
from usdforest.recipe import read_recipe
from usdforest.usd.forest import write_forest
write_forest(read_recipe(sys.argv[1]), sys.argv[2])
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
print("simd:", *[f for f in __cpu_dispatch__ if __cpu_features__.get(f)])
"""
# the SIMD targets numpy dispatches to on this CPU, turned off in the second build
SIMD = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]


def _openblas() -> bool:
    config = np.show_config(mode="dicts")
    name = str(config.get("Build Dependencies", {}).get("blas", {}).get("name", ""))
    return "openblas" in name.lower()


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="x86-64 kernels")
@pytest.mark.skipif(not _openblas(), reason="numpy is not linked with OpenBLAS here")
def test_two_blas_kernels_build_the_same_bytes(tmp_path):
    text = (
        default_recipe_path()
        .read_text()
        .replace("bounds = [0.0, 0.0, 100.0, 100.0]", "bounds = [10.0, 55.0, 40.0, 85.0]")
    )  # a 30 m plot of the default stand: one of its bumps, dead wood, shrubs, young trees
    assert "bounds = [10.0, 55.0, 40.0, 85.0]" in text
    (tmp_path / "r.toml").write_text(text)
    procs = []
    for kernel in KERNELS:
        (tmp_path / kernel).mkdir()
        env = {**os.environ, "OPENBLAS_CORETYPE": kernel, "OPENBLAS_VERBOSE": "2"}
        if kernel == KERNELS[1] and SIMD:
            env["NPY_DISABLE_CPU_FEATURES"] = " ".join(SIMD)
        procs.append(subprocess.Popen(
            [sys.executable, "-c", BUILD, str(tmp_path / "r.toml"),
             str(tmp_path / kernel / "forest.usda")],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        ))  # fmt: skip
    for kernel, p in zip(KERNELS, procs, strict=True):
        out, err = p.communicate(timeout=900)
        assert p.returncode == 0, err[-2000:]
        assert kernel.lower() in (out + err).lower(), (out + err)[-500:]  # the kernel it ran
        simd = next(line for line in out.splitlines() if line.startswith("simd:")).split()[1:]
        assert simd == (SIMD if kernel == KERNELS[0] else []), out[-500:]

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}

    a, b = (files(tmp_path / k) for k in KERNELS)
    assert len(a) > 30 and a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []


def test_exact_products_are_numpys_to_rounding():
    """The fixed-order products agree with numpy's (BLAS's) to rounding, inverses invert."""
    from usdforest.grow import exact

    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(7, 5, 3)), rng.normal(size=(7, 3, 4))
    np.testing.assert_allclose(exact.matmul(a, b), a @ b, rtol=1e-13, atol=1e-13)
    v = rng.normal(size=3)
    np.testing.assert_allclose(exact.matmul(a, v), a @ v, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(exact.dot(a, v), a @ v, rtol=1e-13, atol=1e-13)
    m = rng.normal(size=(9, 3, 3))
    np.testing.assert_allclose(exact.inv3(m) @ m, np.broadcast_to(np.eye(3), m.shape),
                               atol=1e-9)  # fmt: skip
    np.testing.assert_allclose(exact.det3(m), np.linalg.det(m), rtol=1e-12)
    t = np.zeros((4, 4))
    t[:3, :3], t[3, :3], t[3, 3] = m[0], [1.0, -2.0, 3.0], 1.0
    np.testing.assert_allclose(exact.inv_affine(t) @ t, np.eye(4), atol=1e-9)
    with pytest.raises(ValueError, match="not a row-vector affine"):
        exact.inv_affine(rng.normal(size=(4, 4)))


def test_elementary_functions_are_libms_and_numpys_to_rounding():
    """exact's exp, log, power... are the C library's (Python's math, element by element),
    numpy's to two ulps, with numpy's answers where math raises."""
    from usdforest.grow import exact

    rng = np.random.default_rng(8)
    x, p = rng.uniform(-20, 20, 2000), rng.uniform(1e-3, 60, 2000)
    cases = [
        (exact.exp, np.exp, math.exp, (x,)),
        (exact.log, np.log, math.log, (p,)),
        (exact.log1p, np.log1p, math.log1p, (p - 0.99,)),
        (exact.log2, np.log2, math.log2, (p,)),
        (exact.power, np.power, math.pow, (p, x / 4)),
        (exact.arctan2, np.arctan2, math.atan2, (x, p - 30)),
        (exact.arcsin, np.arcsin, math.asin, (x / 20,)),
        (exact.arccos, np.arccos, math.acos, (x / 20,)),
        (exact.cbrt, np.cbrt, math.cbrt, (x,)),
    ]
    for ours, numpys, libm, args in cases:
        got = ours(*args)
        assert got.dtype == np.float64 and got.shape == args[0].shape
        rows = zip(*(a.tolist() for a in args), strict=True)
        assert got.tolist() == [libm(*a) for a in rows], libm
        np.testing.assert_array_max_ulp(got, numpys(*args), maxulp=2)  # cbrt: 2 apart
        assert isinstance(ours(*(a[0] for a in args)), np.float64)  # a scalar, as a ufunc's
    with np.errstate(all="ignore"):
        edges = np.array([0.0, -0.0, -1.0, -2.0, 1e-320, np.inf, -np.inf, np.nan, 1000.0])
        for ours, numpys in [(exact.exp, np.exp), (exact.log, np.log), (exact.log1p, np.log1p),
                             (exact.log2, np.log2), (exact.arcsin, np.arcsin),
                             (exact.arccos, np.arccos), (exact.cbrt, np.cbrt)]:  # fmt: skip
            got, want = ours(edges), numpys(edges)
            odd = ~np.isfinite(want) | (want == 0)  # nan, infinities, signed zeros: numpy's
            np.testing.assert_array_equal(got[odd], want[odd], err_msg=str(ours))
            zero = want == 0
            assert np.array_equal(np.signbit(got[zero]), np.signbit(want[zero])), ours
            np.testing.assert_array_max_ulp(got[~odd], want[~odd], maxulp=2)
        b, e = (
            np.array([-8.0, -8.0, 0.0, 0.0, 10.0, -10.0, 2.0]),
            np.array([1 / 3, 3.0, -1.0, 0.0, 400.0, 401.0, np.nan]),
        )
        np.testing.assert_array_equal(exact.power(b, e), np.power(b, e))


# what the build writes goes through exact; these may use numpy's own: the sensors' rays
# (Embree's hits differ in their last bit between CPUs anyway), fit's likelihood (its recipe
# is written rounded), the cluster processes' theoretical K (fit and the tests)
NUMPY_ELEMENTARY_ALLOWED = ("sensors/", "sites/fit.py", "sites/gibbsfit.py", "sites/clusters.py")


def test_the_build_uses_no_simd_elementary_functions():
    """No module that writes a forest calls numpy's exp, log, power, arctan2... (whose SIMD
    loops round by CPU) on real numbers: it calls :mod:`usdforest.grow.exact`'s."""
    import re

    import usdforest

    root = Path(usdforest.__file__).parent
    call = re.compile(
        r"\bnp\.(exp|expm1|exp2|log|log1p|log2|log10|power|float_power|arctan2|arctan|"
        r"arcsin|arccos|arctanh|arcsinh|arccosh|tan|tanh|sinh|cosh|cbrt)\("
    )
    found = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel.startswith(NUMPY_ELEMENTARY_ALLOWED) or rel == "grow/exact.py":
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if call.search(line) and "1j" not in line:  # complex exp: numpy's C, no SIMD
                found.append(f"{rel}:{n}: {line.strip()}")
    assert found == []

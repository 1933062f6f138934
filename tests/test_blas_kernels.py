"""The same bytes whatever BLAS kernel the machine's numpy picks (issue 61, item 8): a plot
of the default recipe (its dead wood, colliders, layers under the crowns and thumbnail),
built in two processes that force two OpenBLAS kernels, is the same file for file. Under
Haswell's kernel and this machine's own, a collider's position and the thumbnail differed
in their last bits (BLAS sums in the kernel's order and fuses multiply-adds); usdforest's
geometry goes through :mod:`usdforest.grow.exact` instead. (A 20 m plot came out the same under
both kernels before that too: 30 m is the smallest that showed it.)"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from usdforest.recipe import default_recipe_path

KERNELS = ("Haswell", "Sandybridge")  # both run on any x86-64 CPU with AVX2

BUILD = """
import sys
from usdforest.recipe import read_recipe
from usdforest.usd.forest import write_forest
write_forest(read_recipe(sys.argv[1]), sys.argv[2])
"""


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
        procs.append(subprocess.Popen(
            [sys.executable, "-c", BUILD, str(tmp_path / "r.toml"),
             str(tmp_path / kernel / "forest.usda")],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        ))  # fmt: skip
    for kernel, p in zip(KERNELS, procs, strict=True):
        out, err = p.communicate(timeout=900)
        assert p.returncode == 0, err[-2000:]
        assert kernel.lower() in (out + err).lower(), (out + err)[-500:]  # the kernel it ran

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

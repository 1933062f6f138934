"""Fitting an intensity to raster covariates (issue 38, item 2: ``usdforest fit
--covariates``): the slope against a likelihood solved in the test, a covariate without effect
dropped, the written raster recipe, and bad rasters named."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from usdforest.cli import app
from usdforest.recipe import read_recipe
from usdforest.sites.covariates import read_covariate
from usdforest.sites.fit import fit_stand

SIDE = 400.0
CELLS = 40  # 10 m cells
WINDOW = (0.0, 0.0, SIDE, SIDE)


def field() -> np.ndarray:
    """An elevation-like covariate on 10 m cells, row 0 north."""
    c = (np.arange(CELLS) + 0.5) * SIDE / CELLS
    x, y = np.meshgrid(c, c[::-1])
    return 120 + 15 * np.sin(x / 60) + 10 * np.cos(y / 45) + 3 * np.sin((x + y) / 23)


def simulate(z: np.ndarray, a: float, c: float, seed: int) -> np.ndarray:
    """A Poisson process of intensity exp(a + c z_std), piecewise constant on the cells:
    Poisson counts per cell, uniform inside (exact)."""
    rng = np.random.default_rng(seed)
    zs = (z - z.mean()) / z.std()
    cell = SIDE / CELLS
    counts = rng.poisson(np.exp(a + c * zs) * cell * cell)
    pts = []
    for (r, k), m in np.ndenumerate(counts):
        x0, y1 = k * cell, SIDE - r * cell
        pts.append(np.column_stack([rng.uniform(x0, x0 + cell, m), rng.uniform(y1 - cell, y1, m)]))
    return np.concatenate(pts)


def slope_by_hand(z: np.ndarray, xy: np.ndarray) -> float:
    """The maximum-likelihood slope of exp(a + c z_std) on the cells, a profiled out:
    sum_i z_i = n sum_k z_k e^(c z_k) / sum_k e^(c z_k)."""
    zs = (z - z.mean()) / z.std()
    cell = SIDE / CELLS
    col = np.clip((xy[:, 0] // cell).astype(int), 0, CELLS - 1)
    row = np.clip(((SIDE - xy[:, 1]) // cell).astype(int), 0, CELLS - 1)
    mean_at = zs[row, col].mean()
    flat = zs.ravel()

    def score(c: float) -> float:
        w = np.exp(c * flat)
        return mean_at - (flat * w).sum() / w.sum()

    return brentq(score, -5, 5, xtol=1e-12)


@pytest.fixture
def elevation(tmp_path):
    path = tmp_path / "elevation.npy"
    np.save(path, field())
    return path


def test_a_covariate_slope_is_the_likelihood_s(elevation):
    z = field()
    xy = simulate(z, math.log(0.02), 0.6, seed=5)  # about 3,500 trees
    cov = read_covariate(elevation, WINDOW)
    f = fit_stand(xy, WINDOW, covariates=(cov,))
    assert [c.name for c in f.covariates] == ["elevation"]
    assert not f.trend  # the truth has none, and the test at 5 % does not find one
    (slope,), (se,) = f.slopes, f.slopes_se
    assert slope == pytest.approx(slope_by_hand(z, xy), abs=1e-6)
    assert abs(slope - 0.6) < 3 * se and 0.01 < se < 0.05
    # the written intensity integrates to the trees counted
    assert f.intensity(xy[:, 0], xy[:, 1]).min() > 0
    cell = SIDE / CELLS
    c = (np.arange(CELLS) + 0.5) * cell
    gx, gy = np.meshgrid(c, c[::-1])
    total = f.intensity(gx, gy).sum() * cell * cell
    assert total == pytest.approx(len(xy), rel=1e-6)  # the score equation of b0


def test_a_strauss_first_order_term_takes_the_covariates(tmp_path):
    from usdforest.seeds import stream
    from usdforest.sites.inhibition import Inhibition
    from usdforest.sites.inhibition import simulate as strauss
    from usdforest.sites.pointprocess import Raster, Rectangle

    side, cells = 200.0, 20
    c = (np.arange(cells) + 0.5) * side / cells
    x, y = np.meshgrid(c, c[::-1])
    z = np.sin(x / 30) + 0.5 * np.cos(y / 25)
    path = tmp_path / "moisture.npy"
    np.save(path, z)
    beta = np.exp(math.log(0.04) + 0.7 * (z - z.mean()) / z.std())
    box = (0.0, 0.0, side, side)
    xy = strauss(Inhibition("strauss", 2.5, 0.3), Rectangle(*box), Raster(beta, box),
                 stream(3, "map"))  # fmt: skip
    f = fit_stand(xy, box, covariates=(read_covariate(path, box),))
    assert f.interaction == "strauss"
    assert f.inhibition.radius == pytest.approx(2.5, abs=0.3)
    assert f.first_order[3] == pytest.approx(0.7, abs=0.2)  # beta's slope, not lambda's


def test_a_covariate_without_effect_is_dropped(elevation):
    xy = simulate(field(), math.log(0.02), 0.0, seed=6)
    f = fit_stand(xy, WINDOW, covariates=(read_covariate(elevation, WINDOW),))
    assert f.covariates == () and f.slopes == ()


def test_fit_writes_a_raster_recipe_that_builds_the_fitted_intensity(tmp_path, runner, elevation):
    xy = simulate(field(), math.log(0.01), -0.8, seed=7)
    stems = tmp_path / "stems.csv"
    stems.write_text("x,y\n" + "\n".join(f"{x:.3f},{y:.3f}" for x, y in xy) + "\n")
    out = tmp_path / "fitted.toml"
    noise = tmp_path / "noise.npy"  # a covariate the trees ignore: dropped
    np.save(noise, np.random.default_rng(3).normal(size=(CELLS, CELLS)))
    run = runner.invoke(
        app,
        ["fit", str(stems), "--region", "0,0,400,400", "--covariates", str(elevation),
         "--covariates", str(noise), "-o", str(out), "--json"],
    )  # fmt: skip
    assert run.exit_code == 0, run.output
    summary = json.loads(run.stdout)
    assert summary["covariates"]["elevation"]["coefficient"] == pytest.approx(-0.8, abs=0.15)
    assert summary["covariates_dropped"] == ["noise"]
    assert summary["intensity_terms"] == ["elevation"]
    raster = tmp_path / "fitted.intensity.npy"
    assert raster.exists()
    recipe = read_recipe(out)
    assert recipe.intensity.describe() == {"kind": "raster", "file": "fitted.intensity.npy"}
    grid = np.load(raster)
    assert grid.shape == (CELLS, CELLS)
    # the raster is the fitted intensity at the cells' centres: it counts the map's trees
    assert grid.mean() * SIDE * SIDE == pytest.approx(len(xy), rel=1e-6)
    # more intense where the covariate is low, as the data were made
    z = field()
    assert grid[z < np.quantile(z, 0.2)].mean() > 2 * grid[z > np.quantile(z, 0.8)].mean()


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: np.save(p / "flat.npy", np.full((4, 4), 3.0)), "is constant"),
        (lambda p: np.save(p / "flat.npy", np.zeros(5)), "2D grid"),
        (lambda p: np.save(p / "flat.npy", np.array([[1.0, np.nan], [2, 3]])), "NaN"),
        (lambda p: None, "flat.npy"),  # missing
    ],
)
def test_bad_covariates_are_named(tmp_path, runner, make, message):
    make(tmp_path)
    rng = np.random.default_rng(1)
    stems = tmp_path / "stems.csv"
    stems.write_text(
        "x,y\n" + "\n".join(f"{x:.2f},{y:.2f}" for x, y in rng.uniform(0, 100, (50, 2)))
    )
    out = tmp_path / "f.toml"
    run = runner.invoke(
        app, ["fit", str(stems), "--covariates", str(tmp_path / "flat.npy"), "-o", str(out)]
    )
    assert run.exit_code == 2 and message in run.stderr, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
    assert not out.exists() and not (tmp_path / "f.intensity.npy").exists()


def test_an_output_never_replaces_an_input(tmp_path, runner, elevation):
    stems = tmp_path / "stems.csv"
    xy = simulate(field(), math.log(0.005), 0.3, seed=2)
    stems.write_text("x,y\n" + "\n".join(f"{x:.2f},{y:.2f}" for x, y in xy))
    trap = tmp_path / "z.intensity.npy"  # a covariate where the raster output would go
    np.save(trap, field())
    before = trap.read_bytes()
    run = runner.invoke(
        app, ["fit", str(stems), "--covariates", str(trap), "-o", str(tmp_path / "z.toml"),
              "--force"],
    )  # fmt: skip
    assert run.exit_code == 2 and "is an input of this command" in run.stderr, run.stderr
    assert trap.read_bytes() == before and not (tmp_path / "z.toml").exists()

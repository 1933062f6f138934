"""The Python API: the same forests, scans and flights as the command line, typed results,
nothing printed; the example that writes randomised forests for a training run."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib

import numpy as np
import pytest
from pxr import Usd, UsdGeom

import usdforest
from usdforest.cli import app
from usdforest.errors import UsdForestError
from usdforest.usd.validate import errors, validate


def test_importing_usdforest_loads_neither_numpy_nor_pxr():
    code = (
        "import sys, usdforest; usdforest.load_recipe; "
        "print(json.dumps(['numpy' in sys.modules, 'pxr' in sys.modules]))"
    )
    r = subprocess.run(
        [sys.executable, "-c", "import json; " + code], capture_output=True, text=True, check=True
    )
    assert json.loads(r.stdout) == [False, False]
    assert set(dir(usdforest)) >= {"build_forest", "fly", "grow_tree", "load_recipe", "scan"}


def test_the_api_builds_the_forest_the_command_line_builds(tmp_path, runner, capsys):
    recipe = usdforest.load_recipe("paper-two-tree-stand", seed=9)
    built = usdforest.build_forest(recipe, tmp_path / "a.usda", thumbnail=False)
    assert capsys.readouterr().out == ""  # nothing printed
    r = runner.invoke(
        app,
        ["build", str(tmp_path / "b.usda"), "-p", "paper-two-tree-stand", "--seed", "9", "-q"],
    )
    assert r.exit_code == 0, r.output
    a, b = (tmp_path / f"{x}_assets" / "instances.usdc" for x in "ab")
    assert a.read_bytes() == b.read_bytes()
    assert built.n_trees == 2 and set(built.sites.names) == {"paper-rule-2", "paper-rule-3"}
    # a seed given to build_forest wins over the recipe's
    again = usdforest.build_forest(recipe, tmp_path / "c.usda", seed=9, thumbnail=False)
    assert np.array_equal(again.sites.xy, built.sites.xy)
    with pytest.raises(UsdForestError, match="exists; pass --force"):
        usdforest.build_forest(recipe, tmp_path / "a.usda")


def test_a_recipe_given_as_data_is_the_file_it_came_from(tmp_path):
    path = usdforest.recipes()["paper-ipp-sparse"]
    from_data = usdforest.load_recipe(tomllib.loads(path.read_text()), base=path.parent)
    from_file = usdforest.load_recipe("paper-ipp-sparse")
    assert from_data.seed == from_file.seed and from_data.species_names == from_file.species_names
    assert from_data.expected_trees() == pytest.approx(from_file.expected_trees(), rel=1e-12)
    with pytest.raises(UsdForestError, match="region: missing"):
        usdforest.load_recipe({"seed": 1})


def test_scan_fly_and_grow_return_what_the_command_line_writes(tmp_path, runner):
    stand = tmp_path / "s.usda"
    usdforest.build_forest("paper-two-tree-stand", stand, thumbnail=False)
    shot = usdforest.scan(stand, "lidar", (5, -4, 1.5, 90), settings={"max_range": 30.0})
    assert shot.sensor == "lidar" and shot.settings.max_range == 30.0
    assert shot.pose.yaw == 90 and shot.warnings == () and len(shot.result) > 100
    cfg = tmp_path / "c.toml"
    cfg.write_text("[lidar]\nmax_range = 30.0\n")
    out = tmp_path / "l.npz"
    args = ["scan", str(stand), "--sensor", "lidar", "--pose", "5,-4,1.5,90", "-o", str(out)]
    assert runner.invoke(app, [*args, "--config", str(cfg)]).exit_code == 0
    np.testing.assert_array_equal(np.load(out)["points"], shot.result.points)
    with pytest.raises(UsdForestError, match="unknown lidar preset 'vlp-61'"):
        usdforest.scan(stand, "lidar", (0, 0, 1), preset="vlp-61")
    echo = usdforest.scan(stand, "sonar", "5,-4,1.5,90", preset="paper")
    assert echo.result.reflectors["leaf"] > 0 and echo.result.echo.shape == echo.result.t.shape
    flown = usdforest.fly(stand, line=((0, -6, 1.5), (2, -6, 1.5)), speed=2.0, camera="d435")
    assert flown.lidar.sweeps == 10 and len(flown.camera) == 3 and flown.sonar is None
    r = runner.invoke(
        app,
        ["fly", str(stand), "--line", "0,-6,1.5:2,-6,1.5", "--speed", "2", "-o",
         str(tmp_path / "f"), "--json"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["lidar"]["returns"] == len(flown.lidar)
    usdforest.grow_tree("paper-rule-1", tmp_path / "t.usdc", seed=3)
    (tmp_path / "cli").mkdir()
    r = runner.invoke(
        app, ["tree", str(tmp_path / "cli" / "t.usdc"), "--species", "paper-rule-1", "--seed", "3"]
    )
    assert r.exit_code == 0, r.output
    assert (tmp_path / "t.usdc").read_bytes() == (tmp_path / "cli" / "t.usdc").read_bytes()


def test_the_example_writes_randomised_forests_for_a_training_run(tmp_path, capsys):
    from usdforest.pipelines import random_forests as example

    out = tmp_path / "run"
    written = example.main([str(out), "--count", "3", "--recipe", "quick-mixed", "--seed", "5"])
    assert [p.name for p in written] == [f"forest_{k:04d}.usda" for k in range(3)]
    with (out / "forests.csv").open() as f:
        import csv

        rows = list(csv.DictReader(f))
    assert len({r["seed"] for r in rows}) == 3 and len({r["mix"] for r in rows}) == 3
    for row, path in zip(rows, written, strict=True):
        stage = Usd.Stage.Open(str(path))
        inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
        assert len(inst.GetProtoIndicesAttr().Get()) == int(row["trees"])
        assert int(row["trees_pine"]) + int(row["trees_broadleaf"]) == int(row["trees"])
        weights = [float(x.split("=")[1]) for x in row["mix"].split()]
        assert sum(weights) == pytest.approx(1, abs=1e-3) and 0 <= float(row["hard_core"]) <= 2
    assert errors(validate(written[0])) == []
    # the run is reproducible from its seed
    example.main(
        [str(tmp_path / "again"), "--count", "1", "--recipe", "quick-mixed", "--seed", "5"]
    )
    a, b = (d / "forest_0000_assets" / "instances.usdc" for d in (out, tmp_path / "again"))
    assert a.read_bytes() == b.read_bytes()


TWO_TREES = usdforest.recipes()["paper-two-tree-stand"]
LINE = ((0.0, 0.0, 2.0), (1.0, 0.0, 2.0))
BAD_ARGUMENTS = {
    "build-seed-negative": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", seed=-5),
        "seed: expected an integer from 0 to 2**64-1, got -5",
    ),
    "build-seed-text": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", seed="3"),
        "seed: expected an integer from 0 to 2**64-1, got '3'",
    ),
    "build-workers-negative": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", workers=-2),
        "workers: ",
    ),
    "build-workers-million": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", workers=10**6),
        "workers: ",
    ),
    "build-scheduler-untiled": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", scheduler="not a url"),
        "scheduler: ",
    ),
    "build-untiled-text": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", untiled="yes"),
        "untiled: expected True or False, got 'yes'",
    ),
    "build-untiled-untiled": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", untiled=True),
        "workers, scheduler and untiled apply to a tiled recipe",
    ),
    "build-thumbnail-text": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda", thumbnail="yes"),
        "thumbnail: expected True or False, got 'yes'",
    ),
    "grow-species-number": (
        lambda d: usdforest.grow_tree(123, d / "t.usda"),
        "species: expected a preset's name or a Species, got 123",
    ),
    "grow-seed-negative": (lambda d: usdforest.grow_tree("pine", d / "t.usda", seed=-1), "seed: "),
    "grow-seed-fraction": (
        lambda d: usdforest.grow_tree("pine", d / "t.usda", seed=0.5),
        "seed: ",
    ),
    "grow-variant-negative": (
        lambda d: usdforest.grow_tree("pine", d / "t.usda", variant=-1),
        "variant: ",
    ),
    "grow-variant-text": (
        lambda d: usdforest.grow_tree("pine", d / "t.usda", variant="a"),
        "variant: ",
    ),
    "scan-seed-fraction": (
        lambda d: usdforest.scan(d / "f.usda", "lidar", (0, 0, 2), seed=0.5),
        "seed: ",
    ),
    "scan-settings-text": (
        lambda d: usdforest.scan(d / "f.usda", "lidar", (0, 0, 2), settings="max_range=5"),
        "settings: ",
    ),
    "fly-speed-text": (
        lambda d: usdforest.fly(d / "f.usda", line=LINE, speed="fast"),
        "speed: expected a finite number, got 'fast'",
    ),
    "scan-progress-text": (
        lambda d: usdforest.scan(d / "f.usda", "lidar", (0, 0, 2), progress="yes"),
        "progress: expected True, False, None or a callable",
    ),
    "fly-long-text": (
        lambda d: usdforest.fly(d / "f.usda", line=LINE, long="no"),
        "long: expected True or False, got 'no'",
    ),
    "fly-line-text": (
        lambda d: usdforest.fly(d / "f.usda", line="0,-6,1.5:2,-6,1.5"),
        "line: expected two points of 3 coordinates, got '0,-6,1.5:2,-6,1.5'",
    ),
    "fly-line-word": (
        lambda d: usdforest.fly(d / "f.usda", line=(("a", 0, 1), (1, 0, 1))),
        "line: expected two points of 3 coordinates",
    ),
    "fly-rate-none": (
        lambda d: usdforest.fly(d / "f.usda", line=LINE, lidar_rate=None),
        "lidar_rate: expected a finite number, got None",
    ),
    # issue 61's: builtin errors without the argument's name, and absurd magnitudes
    "load-recipe-number": (lambda d: usdforest.load_recipe(123), "recipe: expected a file name"),
    "scan-stage-none": (
        lambda d: usdforest.scan(None, "lidar", (0, 0, 2)),
        "stage: expected a file name",
    ),
    "scan-pose-none": (
        lambda d: usdforest.scan(d / "f.usda", "lidar", None),
        "pose: expected x, y, z[, yaw, pitch, roll]",
    ),
    "fly-stage-number": (
        lambda d: usdforest.fly(5, line=LINE),
        "stage: expected a file name",
    ),
    "build-unwritable-folder": (
        lambda d: usdforest.build_forest(TWO_TREES, d / "f.usda" / "sub" / "g.usda"),
        "{d}/f.usda/sub/g.usda: {d}/f.usda is a file, not a folder",
    ),
    "fly-camera-number": (
        lambda d: usdforest.fly(d / "f.usda", line=LINE, lidar=None, camera=5),
        "camera: expected a preset's name",
    ),
    "fly-camera-baseline-huge": (
        lambda d: usdforest.fly(d / "f.usda", line=LINE, lidar=None, camera={"baseline": 1e300}),
        "camera.baseline: 1e+300 is outside 0 to 10 m",
    ),
    "scan-camera-noise-huge": (
        lambda d: usdforest.scan(d / "f.usda", "camera", (0, 0, 2), settings={"noise": 1e300}),
        "camera.noise: 1e+300 is outside 0 to 255",
    ),
    "fly-lidar-range-huge": (
        lambda d: usdforest.fly(d / "f.usda", line=LINE, lidar={"max_range": 1e300}),
        "lidar.max_range: must be a number in (0, 100000] m",
    ),
}


@pytest.fixture(scope="module")
def small_forest(tmp_path_factory):
    folder = tmp_path_factory.mktemp("api-forest")
    usdforest.build_forest(TWO_TREES, folder / "f.usda", thumbnail=False)
    return folder


@pytest.mark.parametrize("case", list(BAD_ARGUMENTS), ids=list(BAD_ARGUMENTS))
def test_the_api_names_a_bad_argument_and_writes_nothing(small_forest, tmp_path, case):
    """Each of issue 36's API cases (and their kind): UsdForestError naming the argument,
    never a builtin TypeError or AttributeError, and no file written."""
    call, start = BAD_ARGUMENTS[case]
    for name in ("f.usda", "f_assets"):
        (tmp_path / name).symlink_to(small_forest / name)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(UsdForestError) as err:
        call(tmp_path)
    start = start.replace("{d}", str(tmp_path))
    assert str(err.value).startswith(start), str(err.value)
    assert len(str(err.value).splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_progress_reaches_a_notebook_as_lines_or_a_callback(small_forest, capsys):
    """The API prints nothing unless asked: ``progress=True`` writes the command line's log
    lines to stderr (each stage when it completes, then every 5 s), a callable gets every
    tick."""
    stage = small_forest / "f.usda"
    usdforest.scan(stage, "lidar", (0, 0, 2))
    assert capsys.readouterr() == ("", "")
    usdforest.scan(stage, "lidar", (0, 0, 2), progress=True)
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.strip().splitlines()
    assert lines and all(re.fullmatch(r"[a-z -]+: [\d,]+/[\d,]+ \(\d+ s(, about \d+ s left)?\)", x)
                         for x in lines), lines  # fmt: skip
    assert any(x.startswith("tree prototypes: 2/2") for x in lines), lines
    ticks = []
    usdforest.fly(stage, line=LINE, lidar_rate=10, progress=lambda *t: ticks.append(t))
    sweeps = [t for t in ticks if t[0] == "lidar sweeps"]
    assert sweeps and sweeps[-1][1] == sweeps[-1][2] > 1


def test_fly_takes_settings_tables_as_scan_does(small_forest, tmp_path):
    """A sensor's table of keys over its first preset, in ``fly`` as in ``scan``
    (``fly(camera={...})`` ended in AttributeError): the camera flown is the one scanned."""
    table = {"width": 32, "height": 24, "max_range": 20.0}
    flight = usdforest.fly(small_forest / "f.usda", line=LINE, lidar=None, camera=table)
    scan = usdforest.scan(small_forest / "f.usda", "camera", (0, -6, 1.5), settings=table)
    assert flight.camera.camera == scan.settings
    assert (scan.settings.width, scan.settings.height) == (32, 24)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("season", "spring", "recipe.season: expected summer or autumn or winter"),
        ("wind", {"speed": 8}, "recipe.wind: expected None or a usdforest.grow.sway.WindSpec"),
        ("seed", -1, "recipe.seed: expected an integer"),
        ("tiles", 0.0, "recipe.tiles: expected None or a tile side"),
    ],
)
def test_a_recipe_changed_in_python_is_checked_as_read(field, value, message):
    """``dataclasses.replace`` goes through the same checks as the reader (a season or a
    wind that is none built silently or failed deep inside the build)."""
    import dataclasses

    recipe = usdforest.load_recipe(TWO_TREES)
    with pytest.raises(UsdForestError, match=re.escape(message)):
        dataclasses.replace(recipe, **{field: value})

"""Outputs never replace inputs: a command refuses, whatever --force says, an output that is
(or resolves to) a file it reads, or an output folder that holds one."""

from __future__ import annotations

import shutil

from usdforest.cli import app
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.usd.forest import write_forest

TWO_TREES = default_recipe_path().parent / "paper-two-tree-stand.toml"


def test_a_build_never_replaces_the_folder_that_holds_its_recipe(tmp_path, runner):
    (tmp_path / "f_assets").mkdir()
    recipe = tmp_path / "f_assets" / "recipe.toml"
    shutil.copy(TWO_TREES, recipe)
    before = recipe.read_bytes()
    r = runner.invoke(app, ["build", str(tmp_path / "f.usda"), "-p", str(recipe), "--force"])
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == (
        f"error: {tmp_path / 'f_assets'}: would be replaced, but holds an input of this "
        f"command ({recipe}); write the output elsewhere"
    )
    assert recipe.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["f_assets"]


def test_a_flight_never_replaces_the_path_it_flies(tmp_path, runner):
    """Flying a trajectory a flight wrote (``run_trajectory.csv``) into the same stem would
    overwrite it with itself half-written."""
    write_forest(read_recipe(TWO_TREES), tmp_path / "f.usda", thumbnail=False)
    path = tmp_path / "run_trajectory.csv"
    path.write_text("t,x,y,z\n0,1,1,2\n1,2,1,2\n")
    before = path.read_bytes()
    r = runner.invoke(
        app,
        ["fly", str(tmp_path / "f.usda"), "--path", str(path), "-o", str(tmp_path / "run"),
         "--force", "-q"],
    )  # fmt: skip
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == (
        f"error: {path}: is an input of this command ({path}); write the output elsewhere"
    )
    assert path.read_bytes() == before
    assert not (tmp_path / "run.las").exists()
    # through a symbolic link too
    (tmp_path / "other_trajectory.csv").symlink_to(path)
    r = runner.invoke(
        app,
        ["fly", str(tmp_path / "f.usda"), "--path", str(path), "-o", str(tmp_path / "other"),
         "--force", "-q"],
    )  # fmt: skip
    assert r.exit_code == 2 and "is an input of this command" in r.stderr, r.output
    assert path.read_bytes() == before


def test_fly_names_a_folder_given_as_its_output_stem(tmp_path, runner):
    write_forest(read_recipe(TWO_TREES), tmp_path / "f.usda", thumbnail=False)
    r = runner.invoke(
        app, ["fly", str(tmp_path / "f.usda"), "--line", "1,1,2:2,1,2", "--speed", "1", "-o", "."]
    )
    assert r.exit_code == 2, r.output
    assert r.stderr.strip() == "error: .: the output stem must be a file name, not a folder"

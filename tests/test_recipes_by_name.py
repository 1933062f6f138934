"""Shipped recipes by name (`-p stand-1ha`, `usdforest recipes`), the default species mix of a
recipe without species tables, and `template build` refusing to overwrite."""

from __future__ import annotations

import csv
import json

from usdforest.cli import app
from usdforest.recipe import DEFAULT_SPECIES, read_recipe, shipped_recipes


def test_recipes_lists_every_shipped_forest_recipe(runner):
    r = runner.invoke(app, ["recipes", "--json"])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.stdout)
    names = [row["name"] for row in rows]
    assert {"default", "stand-1ha", "stand-1km2", "quick-mixed", "paper-ipp-sparse"} <= set(names)
    assert "templates" not in names  # the template manifest is no forest
    assert [row["name"] for row in rows if row["default"]] == ["default"]
    one = next(row for row in rows if row["name"] == "stand-1ha")
    assert one["description"].startswith("A 1 ha mixed stand (100 m x 100 m, about 520 trees)")
    plain = runner.invoke(app, ["recipes"])
    assert plain.exit_code == 0 and "stand-1ha" in plain.stdout and "(default)" in plain.stdout


def test_a_shipped_recipe_is_named_without_its_path(tmp_path, runner, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, ["sample", "s.csv", "-p", "paper-ipp-sparse", "--json"])
    assert r.exit_code == 0, r.output
    by_path = runner.invoke(
        app, ["sample", "t.csv", "-p", str(shipped_recipes()["paper-ipp-sparse"]), "--json"]
    )
    assert (tmp_path / "s.csv").read_bytes() == (tmp_path / "t.csv").read_bytes()
    assert json.loads(r.stdout)["counts"] == json.loads(by_path.stdout)["counts"]
    # a file of that name here comes first
    (tmp_path / "paper-ipp-sparse").write_text("seed = [")
    r = runner.invoke(app, ["sample", "u.csv", "-p", "paper-ipp-sparse"])
    assert r.exit_code == 2 and "paper-ipp-sparse: not valid TOML" in r.stderr  # that file
    r = runner.invoke(app, ["build", "f.usda", "-p", "stand-1hx"])
    assert r.exit_code == 2
    assert r.stderr.startswith("error: stand-1hx: no such file, and no shipped recipe")
    assert "stand-1ha" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "f.usda").exists()
    r = runner.invoke(app, ["build", "f.usda", "-p", "missing.toml"])
    assert r.exit_code == 2 and "missing.toml: no such file" in r.stderr


def test_a_recipe_without_species_grows_the_four_presets_equally(tmp_path, runner):
    recipe = tmp_path / "r.toml"
    recipe.write_text(
        "seed = 4\n[region]\nbounds = [0, 0, 200, 200]\n"
        '[intensity]\nkind = "expression"\nexpr = "0.02"\n'
    )
    r = read_recipe(recipe)
    assert r.species_names == DEFAULT_SPECIES
    out = tmp_path / "s.csv"
    assert runner.invoke(app, ["sample", str(out), "-p", str(recipe)]).exit_code == 0
    with out.open() as f:
        species = [row["species"] for row in csv.DictReader(f)]
    counts = {n: species.count(n) for n in DEFAULT_SPECIES}
    # 800 expected sites split equally: each species 200 +- 4 sd (binomial, p = 1/4)
    assert all(
        abs(c - len(species) / 4) < 4 * (len(species) * 3 / 16) ** 0.5 for c in counts.values()
    )
    assert 650 < len(species) < 950


def test_template_build_refuses_to_overwrite_unless_forced(tmp_path, runner):
    from pathlib import Path

    manifest = Path(__file__).parents[1] / "pipelines" / "templates.toml"
    first = runner.invoke(app, ["template", "build", str(manifest), "-o", str(tmp_path)])
    assert first.exit_code == 0, first.output
    built = sorted(tmp_path.glob("*.usdc"))
    assert built
    stamp = [p.stat().st_mtime_ns for p in built]
    again = runner.invoke(app, ["template", "build", str(manifest), "-o", str(tmp_path)])
    assert again.exit_code == 2 and "exists; pass --force" in again.stderr
    assert [p.stat().st_mtime_ns for p in built] == stamp
    forced = runner.invoke(
        app, ["template", "build", str(manifest), "-o", str(tmp_path), "--force"]
    )
    assert forced.exit_code == 0, forced.output


def test_the_tree_counts_recipes_describe_are_what_they_sample():
    """`usdforest recipes` shows each recipe's first sentence; a count of trees in it is what
    the recipe places (``about N``: within 2 %). quick-mixed said 163 after its resampling
    made it 181."""
    import re

    from usdforest.recipe import recipe_description
    from usdforest.sites.sampling import sample_sites

    checked = 0
    for name, path in shipped_recipes().items():
        text = " ".join(recipe_description(path).split())
        m = re.search(r"(about )?(?<!x )\b(\d[\d,]*) trees(?!/)", text)  # not "x 2 trees/m²"
        if m is None:
            continue
        stated = int(m.group(2).replace(",", ""))
        placed = len(sample_sites(read_recipe(path)).xy)
        if m.group(1):
            assert abs(placed - stated) <= 0.02 * stated, (name, stated, placed)
        else:
            assert placed == stated, (name, stated, placed)
        checked += 1
    assert checked >= 5

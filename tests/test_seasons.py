"""Seasons: a winter stand is its summer stand without the broadleaves' leaves (the conifers
and all the wood unchanged), an autumn one wears autumn colours; measured on the composed
stage, by the inventory and by a lidar."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from pxr import Usd, UsdGeom, UsdShade
from stands import BEECH_AND_PINE, build_text

from usdforest import api
from usdforest.errors import RecipeError
from usdforest.grow.species import get_species
from usdforest.recipe import parse_recipe
from usdforest.sensors.scene.scenetypes import CLASS_ID
from usdforest.usd.inventory import stand_figures

MIXED = f"""
seed = 3
[region]
bounds = [0.0, 0.0, 20.0, 20.0]
{BEECH_AND_PINE}
[species.pine]
preset = "scots-pine"
[species.beech]
preset = "european-beech"
[ground]
kind = "plane"
[groundcover]
cover = 0.3
[shrubs]
cover = 0.1
"""


@pytest.fixture(scope="module")
def stands(tmp_path_factory):
    root = tmp_path_factory.mktemp("seasons")
    return {
        "summer": build_text(root, "summer", MIXED),
        "autumn": build_text(root, "autumn", MIXED, season="autumn"),
        "winter": build_text(root, "winter", MIXED, season="winter"),
    }


def _leaves(stage: Usd.Stage, species: str) -> int:
    """Leaf instances of the species' prototype, composed."""
    proto = stage.GetPrimAtPath(f"/Forest/Trees/Prototypes/{species.capitalize()}_0")
    return sum(
        len(UsdGeom.PointInstancer(p).GetProtoIndicesAttr().Get() or [])
        for p in Usd.PrimRange(proto, Usd.TraverseInstanceProxies())
        if p.IsA(UsdGeom.PointInstancer)
    )


def _leaf_colour(stage: Usd.Stage, species: str) -> tuple[float, ...]:
    proto = stage.GetPrimAtPath(f"/Forest/Trees/Prototypes/{species.capitalize()}_0")
    shader = UsdShade.Shader(
        stage.GetPrimAtPath(proto.GetPath().AppendPath("Looks/Leaf/PreviewSurface"))
    )
    return tuple(round(float(v), 5) for v in shader.GetInput("diffuseColor").Get())


def test_winter_takes_the_broadleaves_leaves_and_keeps_the_conifers_and_the_wood(stands):
    summer, winter = (Usd.Stage.Open(str(stands[k])) for k in ("summer", "winter"))
    assert _leaves(summer, "beech") > 10_000 and _leaves(winter, "beech") == 0
    assert _leaves(winter, "pine") == _leaves(summer, "pine") > 1_000
    s_assets, w_assets = (stands[k].parent / f"{k}_assets" for k in ("summer", "winter"))
    assert (w_assets / "trees" / "pine_0.usdc").read_bytes() == (
        s_assets / "trees" / "pine_0.usdc"
    ).read_bytes()
    # the trees stand where they stood, as tall and as thick, over the same floor (what grows
    # there grew in the summer's light): the same ground truth
    for name in ("trees.csv", "groundcover.csv", "understorey.csv", "groundcover.usdc"):
        assert (w_assets / name).read_bytes() == (s_assets / name).read_bytes()
    figures = {k: stand_figures(stands[k]) for k in ("summer", "winter")}
    for key in ("wood_area_index", "basal_area_m2_per_ha"):
        assert figures["winter"][key] == pytest.approx(figures["summer"][key], rel=1e-9)
    # tree by tree, the winter's leaf area is the summer's pine's and nothing of the beech
    trees = {k: figures[k]["per_tree"] for k in ("summer", "winter")}
    leaves = {k: dict(zip(t["species"], t["leaf_area"], strict=True)) for k, t in trees.items()}
    assert leaves["winter"]["beech"] == 0.0 and leaves["summer"]["beech"] > 0.0
    assert leaves["winter"]["pine"] == pytest.approx(leaves["summer"]["pine"], rel=1e-9)
    area = 20.0 * 20.0
    assert figures["winter"]["leaf_area_index"] == pytest.approx(leaves["summer"]["pine"] / area)
    assert figures["summer"]["leaf_area_index"] > 2 * figures["winter"]["leaf_area_index"]


def test_autumn_keeps_the_leaves_in_their_autumn_colours(stands):
    summer, autumn = (Usd.Stage.Open(str(stands[k])) for k in ("summer", "autumn"))
    assert _leaves(autumn, "beech") == _leaves(summer, "beech")
    beech = get_species("european-beech").geometry
    assert _leaf_colour(summer, "beech") == pytest.approx(beech.leaf_color, abs=1e-5)
    assert _leaf_colour(autumn, "beech") == pytest.approx(beech.autumn_color, abs=1e-5)
    # the pine is evergreen: its autumn is its summer
    assert _leaf_colour(autumn, "pine") == _leaf_colour(summer, "pine")
    assert (
        get_species("scots-pine").geometry.autumn_color
        == get_species("scots-pine").geometry.leaf_color
    )


def _from_above(path: Path):
    done = api.scan(
        path, "lidar", (10.0, 10.0, 30.0, 0.0, -90.0), preset="depth-camera",
        settings={"max_range": 60.0},
    )  # fmt: skip
    return done.result


def test_a_lidar_from_above_meets_the_floor_where_the_beech_leaves_were(stands):
    summer, winter = _from_above(stands["summer"]), _from_above(stands["winter"])
    s, w = {}, {}
    for table, r in ((s, summer), (w, winter)):
        for k in range(len(r)):
            table[int(r.ray[k])] = (int(r.cls[k]), int(r.tree[k]), float(r.range[k]))
    floor = (CLASS_ID["ground"], CLASS_ID["ground_vegetation"])
    leaf = CLASS_ID["leaf"]
    beech = 0  # trees.csv: the beech is tree 0, the pine tree 1
    through = [k for k, (c, t, _) in s.items() if c == leaf and t == beech]
    assert len(through) > 1000
    for k, hit in s.items():
        if hit[0] in floor or hit[1] == 1:  # the floor and the pine: met as in summer
            assert w[k] == pytest.approx(hit, abs=1e-4)
    # a ray that met a beech leaf goes on: to the beech's wood, the pine or the ground
    assert all(w[k][2] > s[k][2] for k in through if k in w)
    # the floor's returns grow by those rays at least (the leafless shrubs let more through)
    gained = sum(1 for k in through if w.get(k, (None,))[0] in floor)
    n_floor = [sum(1 for c, _, _ in t.values() if c in floor) for t in (s, w)]
    assert n_floor[1] >= n_floor[0] + gained and gained > 0.4 * len(through)


def test_seasons_and_leaf_fractions_are_checked(tmp_path):
    # the caller's season is named as the caller's, not as the recipe's
    with pytest.raises(
        RecipeError, match=r"^season: 'spring' is not one of summer, autumn, winter$"
    ):
        parse_recipe(tomllib.loads(MIXED), tmp_path, "r.toml", season="spring")
    with pytest.raises(RecipeError, match=r"^r\.toml: season: 'spring' is not one of summer"):
        parse_recipe(tomllib.loads('season = "spring"\n' + MIXED), tmp_path, "r.toml")
    bad = MIXED.replace(
        '[species.beech]\npreset = "european-beech"\n',
        '[species.beech]\npreset = "european-beech"\ngeometry = { winter_leaf_on = 1.5 }\n',
    )
    with pytest.raises(RecipeError, match=r"species\.beech\.geometry\.winter_leaf_on: 1\.5"):
        parse_recipe(tomllib.loads(bad), tmp_path, "r.toml")
    # a beech that keeps a fifth of its (dry) leaves through winter: marcescence
    half = MIXED.replace(
        '[species.beech]\npreset = "european-beech"\n',
        '[species.beech]\npreset = "european-beech"\ngeometry = { winter_leaf_on = 0.2 }\n',
    )
    recipe = parse_recipe(tomllib.loads(half), tmp_path, "r.toml", season="winter")
    assert recipe.species["beech"].species.geometry.leaf_on == 0.2
    assert recipe.species["pine"].species.geometry.leaf_on == 1.0
    (tmp_path / "r.toml").write_text(MIXED)
    out = tmp_path / "w.usda"
    cmd = [sys.executable, "-m", "usdforest", "build", str(out), "-p", str(tmp_path / "r.toml"),
           "--season", "spring", "-q"]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True)
    assert run.returncode != 0 and not out.exists()
    assert run.stderr.strip().count("\n") == 0 and "season" in run.stderr

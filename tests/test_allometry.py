"""Allometric species, stand sizes and inventories, measured on composed stages with pxr.

The equations the trees must follow are written out here from their sources (not imported):
Näslund height curves (Luke's metsi parameters), Repola 2009 pine foliage x SLA 6.2
(Majasalmi et al. 2013), Repola 2008 birch foliage x SLA 13.55.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom
from stands import SPECIES

from usdforest.errors import RecipeError
from usdforest.grow.allometry import ALLOMETRY
from usdforest.grow.species import get_species
from usdforest.recipe import read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.inventory import stand_figures
from usdforest.usd.tree import build_tree
from usdforest.usd.validate import validate

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


def pine_height(d_cm):  # Näslund, p = 2, a = 0.894, b = 0.185
    return 1.3 + d_cm**2 / (0.894 + 0.185 * d_cm) ** 2


def pine_leaf_area(d_cm, h):  # Repola 2009 needles (kg) x 6.2 m²/kg
    ds = 2 + 1.25 * d_cm
    return 6.2 * math.exp(-6.303 + 14.472 * ds / (ds + 6) - 3.976 * h / (h + 1) + 0.1135)


def birch_leaf_area(d_cm):  # Repola 2008 (over 11 cm) x 13.55 m²/kg
    ds = 2 + 1.25 * d_cm
    return 13.55 * math.exp(-29.566 + 33.372 * ds / (ds + 2) + 0.0385)


INVENTORY = (
    """
seed = 3
sites = [
  {{ x = 5, y = 5, species = "pine", dbh = 0.22, height = 19.0 }},
  {{ x = 15, y = 8, species = "pine", dbh = 0.12, height = 13.5 }},
  {{ x = 22, y = 20, species = "beech", dbh = 0.3, height = 16.0 }},
  {{ x = 8, y = 24, species = "birch", dbh = 0.16, height = 15.0 }},
  {{ x = 25, y = 5, species = "spruce", dbh = 0.25, height = 20.0, crown_radius = 1.2 }},
]
[region]
bounds = [0, 0, 30, 30]
"""
    + SPECIES
    + """{extra}
"""
)


@pytest.fixture(scope="module")
def inventory(tmp_path_factory):
    d = tmp_path_factory.mktemp("inv")
    (d / "r.toml").write_text(INVENTORY.format(extra=""))
    out = d / "f.usda"
    write_forest(read_recipe(d / "r.toml"), out, thumbnail=False)
    return out


def test_an_inventory_is_reproduced_on_the_composed_stage(inventory):
    assert validate(inventory) == []
    f = stand_figures(inventory)
    t = f["per_tree"]
    want = {
        "pine": [(0.22, 19.0), (0.12, 13.5)],
        "beech": [(0.3, 16.0)],
        "birch": [(0.16, 15.0)],
        "spruce": [(0.25, 20.0)],
    }
    for name, rows in want.items():
        got = sorted(
            zip(t["dbh"][t["species"] == name], t["height"][t["species"] == name], strict=True)
        )
        for (d, h), (gd, gh) in zip(sorted(rows), got, strict=True):
            assert gd == pytest.approx(d, rel=0.05), name
            assert gh == pytest.approx(h, rel=0.05), name
    # leaf area against the published foliage equations (within 30 %)
    for name, d, _h, area in (
        ("pine", 22, 19.0, pine_leaf_area(22, 19.0)),
        ("birch", 16, 15.0, birch_leaf_area(16)),
    ):
        sel = (t["species"] == name) & np.isclose(t["dbh"], d / 100, rtol=0.05)
        assert t["leaf_area"][sel][0] == pytest.approx(area, rel=0.3), name


def test_an_inventory_crown_radius_sizes_the_crown(inventory):
    # the spruce row gives a 1.2 m crown radius (its allometry: 2.9 m): the composed crown's
    # half-width, read from the prototype's bound, follows the row
    stage = Usd.Stage.Open(str(inventory))
    proto = next(p for p in stage.Traverse() if p.GetName() == "Spruce_0")
    box = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"]).ComputeLocalBound(proto)
    r = box.ComputeAlignedRange()
    half = 0.25 * (r.GetSize()[0] + r.GetSize()[1])
    assert half == pytest.approx(1.2, rel=0.3)


def test_trunks_taper_to_a_closed_point(inventory):
    stage = Usd.Stage.Open(str(inventory))
    proto = next(p for p in stage.Traverse() if p.GetName() == "Pine_0")
    trunk = next(
        p
        for p in Usd.PrimRange(proto, Usd.TraverseInstanceProxies())
        if p.IsA(UsdGeom.Mesh) and "/Trunk" in str(p.GetPath())
    )
    mesh = UsdGeom.Mesh(trunk)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    edges = np.sort(np.concatenate([idx[:, [0, 1]], idx[:, [1, 2]], idx[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # closed: no cut top
    pts = np.asarray(mesh.GetPointsAttr().Get())
    top = pts[pts[:, 2] >= pts[:, 2].max() - 1e-6]
    assert len(top) == 1  # one apex vertex


@pytest.mark.parametrize(
    "name", ["scots-pine", "norway-spruce", "european-beech", "sessile-oak", "silver-birch"]
)
def test_species_grow_to_their_allometry_and_differ_by_seed(name):
    a, b, c = (build_tree(get_species(name), s) for s in (0, 1, 2))
    for t in (a, b, c):
        h = t.extent[1, 2]
        assert h == pytest.approx(t.size.height, rel=0.08)
        slender = t.size.height / t.size.dbh
        assert 40 <= slender <= 180
        area = (t.placement.leaf_scale[:, 0] ** 2).sum()
        m = t.templates[t.grown.species.geometry.leaf].measurements
        assert area * m["leaf_area"] / m["length"] ** 2 == pytest.approx(t.size.leaf_area, 0.1)


@pytest.mark.parametrize(
    "name", ["scots-pine", "norway-spruce", "european-beech", "sessile-oak", "silver-birch"]
)
def test_crown_width_varies_from_seed_to_seed(name):
    # the reference tree over 12 seeds: crown width (mean x/y extent) with a CV of at least
    # 8 %, heights with the height curve's residual, no two trees alike
    trees = [build_tree(get_species(name), s) for s in range(12)]
    widths = np.array([np.ptp(t.extent[:, :2], axis=0).mean() for t in trees])
    heights = np.array([t.extent[1, 2] for t in trees])
    assert widths.std(ddof=1) / widths.mean() >= 0.08
    assert heights.std(ddof=1) / heights.mean() >= 0.04
    assert len({t.placement.n_wood for t in trees}) >= 10


def test_the_pine_height_curve_is_the_published_one():
    sp = get_species("scots-pine")
    t = build_tree(sp, 0)
    # the reference tree (20 cm) within the 8 % residual's 3 sigma of Näslund's curve
    assert abs(math.log(t.size.height / pine_height(20.0))) < 0.24


def test_a_stand_has_size_variety_and_crowns_rise_with_density(tmp_path):
    def build(value, name):
        (tmp_path / f"{name}.toml").write_text(f"""
seed = 5
[region]
bounds = [0, 0, 40, 40]
[intensity]
kind = "constant"
value = {value}
[species.pine]
preset = "scots-pine"
[species.pine.stand]
dbh_mean = 0.16
dbh_cv = 0.3
""")
        out = tmp_path / f"{name}.usda"
        b = write_forest(read_recipe(tmp_path / f"{name}.toml"), out, thumbnail=False)
        return b, stand_figures(out)

    sparse, fs = build(0.02, "sparse")
    dense, fd = build(0.15, "dense")
    assert fd["dbh_m"]["cv"] >= 0.2 and fd["height_m"]["cv"] >= 0.08
    assert len(dense.prototypes) > 5
    base = lambda b: np.mean([t.size.crown_base / t.size.height for t in b.trees.values()])  # noqa: E731
    assert base(dense) > base(sparse) + 0.03
    assert fd["leaf_area_index"] > fs["leaf_area_index"]


def _crown_offsets(forest: Path) -> tuple[np.ndarray, np.ndarray]:
    """Each tree's instance transform (n, 4, 4) and its crown centre's horizontal offset
    from its trunk (n, 2): the mean of its prototype's composed leaf positions, turned and
    scaled as the instance is."""
    stage = Usd.Stage.Open(str(forest))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    mats = np.asarray(
        pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    idx = np.asarray(pi.GetProtoIndicesAttr().Get())
    centre = []
    for target in pi.GetPrototypesRel().GetTargets():
        # the tree's own leaves and each limb's (a limb's group has no transform of its own)
        positions = [
            np.asarray(UsdGeom.PointInstancer(p).GetPositionsAttr().Get(), dtype=float)
            for p in Usd.PrimRange(stage.GetPrimAtPath(target), Usd.TraverseInstanceProxies())
            if p.IsA(UsdGeom.PointInstancer) and p.GetName() == "Leaves"
        ]
        centre.append(np.concatenate([x.reshape(-1, 3) for x in positions]).mean(0))
    return mats, np.einsum("nj,njk->nk", np.asarray(centre)[idx], mats[:, :3, :3])[:, :2]


def test_crowns_grow_away_from_their_neighbours(tmp_path):
    # on the composed stage: each tree's crown centre (the mean of its composed leaf
    # positions) sits off its trunk on the side away from its nearest neighbour (8 size
    # classes a species, not 24: each instance is turned from its own neighbour whatever its
    # class; with the crowns turned at random the mean cosine is about 0)
    (tmp_path / "r.toml").write_text("""
seed = 9
[region]
bounds = [0, 0, 40, 40]
[intensity]
kind = "constant"
value = 0.06
[forest]
hard_core = 1.0
variants = 8
[species.pine]
preset = "scots-pine"
[species.beech]
preset = "european-beech"
""")
    out = tmp_path / "f.usda"
    write_forest(read_recipe(tmp_path / "r.toml"), out, thumbnail=False)
    mats, offset = _crown_offsets(out)
    xy = mats[:, 3, :2]
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
    nearest = d.argmin(axis=1)
    close = d.min(axis=1) < 3.0
    away = xy - xy[nearest]
    cos = np.sum(offset * away, axis=1) / (
        np.linalg.norm(offset, axis=1) * np.linalg.norm(away, axis=1)
    )
    assert close.sum() > 30
    assert cos[close].mean() > 0.4  # 0 for crowns turned at random
    assert np.median(np.linalg.norm(offset[close], axis=1)) > 0.2  # metres


def test_an_understory_is_a_second_entry_of_a_preset_with_its_own_stand(tmp_path):
    # small beeches under large pines: one preset twice, each with its own DBH distribution;
    # on the composed stage two layers, the understory wholly below the canopy's crowns (8 size
    # classes a species, not 24: each tree's DBH and height are its class's times its own
    # scale; with the entry's stand table ignored the understory is as large as the canopy)
    (tmp_path / "r.toml").write_text("""
seed = 4
[region]
bounds = [0, 0, 40, 40]
[intensity]
kind = "constant"
value = 0.08
[mix]
pine = 0.6
beech-understory = 0.4
[forest]
hard_core = 1.0
variants = 8
[species.pine]
preset = "scots-pine"
[species.pine.stand]
dbh_mean = 0.28
dbh_cv = 0.2
[species.beech-understory]
preset = "european-beech"
[species.beech-understory.stand]
dbh_mean = 0.06
dbh_cv = 0.3
dbh_min = 0.02
""")
    out = tmp_path / "f.usda"
    b = write_forest(read_recipe(tmp_path / "r.toml"), out, thumbnail=False)
    t = stand_figures(out)["per_tree"]
    under, over = t["species"] == "beech-understory", t["species"] == "pine"
    assert under.sum() > 20 and over.sum() > 40
    assert np.percentile(t["height"][under], 90) < 0.6 * np.percentile(t["height"][over], 10)
    assert np.median(t["dbh"][under]) == pytest.approx(0.06, rel=0.2)
    # the crowns of all but the smallest pines start above the understory's tops (each
    # tree's crown base: its class's, scaled as the tree is)
    protos = [b.prototypes[i] for i in b.proto_index]
    base = np.array([b.trees[p].size.crown_base for p in protos]) * b.sites.scale
    pines = np.array([p[0] == "pine" for p in protos])
    assert np.percentile(base[pines], 5) > np.percentile(t["height"][under], 90)


def test_an_inventory_yaw_is_kept_when_neighbours_press(tmp_path):
    # two pines 2 m apart press each other; the one whose row gives a yaw keeps it, the other
    # is turned so that its one-sided crown faces away from its neighbour (-x)
    (tmp_path / "r.toml").write_text("""
seed = 2
sites = [
  { x = 10, y = 10, species = "pine", dbh = 0.25, height = 20.0, yaw = 30.0 },
  { x = 12, y = 10, species = "pine", dbh = 0.25, height = 20.5 },
  { x = 8, y = 10, species = "pine", dbh = 0.12, height = 12.0 },
]
[region]
bounds = [0, 0, 20, 20]
[species.pine]
preset = "scots-pine"
""")
    out = tmp_path / "f.usda"
    write_forest(read_recipe(tmp_path / "r.toml"), out, thumbnail=False)
    rows = np.genfromtxt(out.parent / "f_assets" / "trees.csv", delimiter=",", names=True)
    assert rows["yaw"][np.isclose(rows["x"], 10)][0] == pytest.approx(30.0, abs=1e-3)
    mats, offset = _crown_offsets(out)
    i = int(np.argmin(np.abs(mats[:, 3, 0] - 12.0)))
    assert offset[i, 0] > 0.1  # the x = 12 tree leans to +x, away


def test_the_shipped_1ha_stand_has_published_stand_figures(shipped):
    # Asner, Scurlock & Hicke 2003: one-sided LAI 3-9 in temperate forests; Majasalmi et al.
    # 2013: branch area 0.15-0.18 of leaf area (wood with stems here: at most 0.4); a
    # 33-year Scots pine stand has DBH and height CVs of 0.26 and 0.23 (Forests 14:1779)
    out, _ = shipped("stand-1ha")  # (validated by test_forest's shipped recipes' test)
    f = stand_figures(out)
    assert 3.0 <= f["leaf_area_index"] <= 9.0
    assert f["wood_to_leaf_area"] <= 0.4
    assert f["dbh_m"]["cv"] >= 0.25 and f["height_m"]["cv"] >= 0.15
    assert f["crown_footprint_cover"] >= 0.6
    assert 300 <= f["stems_per_ha"] <= 900
    # the pines follow Näslund's curve and Repola's foliage tree by tree (median ratio)
    t = f["per_tree"]
    pine = t["species"] == "scots-pine"
    d_cm, h = t["dbh"][pine] * 100, t["height"][pine]
    assert abs(np.median(np.log(h / pine_height(d_cm)))) < 0.05
    la = np.array([pine_leaf_area(d, hh) for d, hh in zip(d_cm, h, strict=True)])
    assert np.median(t["leaf_area"][pine] / la) == pytest.approx(1.0, abs=0.3)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("[species.pine.stand]\ndbh_mean = 18", "looks like centimetres"),
        ("[species.pine.stand]\ndbh_cv = -1", "dbh_cv"),
    ],
)
def test_bad_stand_tables_are_named(tmp_path, extra, message):
    (tmp_path / "r.toml").write_text(INVENTORY.format(extra=extra))
    with pytest.raises(RecipeError, match=message):
        read_recipe(tmp_path / "r.toml")


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ('{ x = 1, y = 1, species = "pine", dbh = 22, height = 19 }', "looks like centimetres"),
        ('{ x = 1, y = 1, species = "pine", dbh = 0.5, height = 5 }', "slenderness of 10"),
        ('{ x = 1, y = 1, species = "pine", height = 300 }', "not a tree height"),
    ],
)
def test_bad_inventory_rows_are_named(tmp_path, row, message):
    text = INVENTORY.format(extra="").replace(
        '{ x = 5, y = 5, species = "pine", dbh = 0.22, height = 19.0 }', row
    )
    (tmp_path / "r.toml").write_text(text)
    with pytest.raises(RecipeError, match=message):
        read_recipe(tmp_path / "r.toml")


def test_a_stem_map_csv_builds_and_bad_ones_exit_2(tmp_path):
    (tmp_path / "stems.csv").write_text(
        "x,y,species,dbh,height\n3,4,pine,0.2,18\n12,9,pine,0.1,12.5\n"
    )
    text = INVENTORY.format(extra="")
    start = text.index("sites = [")
    text = text[:start] + 'sites = "stems.csv"\n' + text[text.index("]\n", start) + 2 :]
    (tmp_path / "r.toml").write_text(text)
    out = tmp_path / "f.usda"
    write_forest(read_recipe(tmp_path / "r.toml"), out, thumbnail=False)
    f = stand_figures(out)
    assert sorted(np.round(f["per_tree"]["dbh"], 2)) == [0.1, 0.2]
    # the species the map does not plant grow one prototype each, not an inventory's 64
    assets = sorted(p.stem for p in (tmp_path / "f_assets" / "trees").iterdir())
    assert [a for a in assets if not a.startswith("pine_")] == ["beech_0", "birch_0", "spruce_0"]
    assert 1 <= sum(a.startswith("pine_") for a in assets) <= 2
    # a bad one beside it (the forest's pipeline.toml still reads stems.csv)
    (tmp_path / "bad.csv").write_text("x,y,dbh\n3,4,0.2\n")
    (tmp_path / "bad.toml").write_text(text.replace('"stems.csv"', '"bad.csv"'))
    script = Path(sys.executable).parent / "usdforest"
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "usdforest.entry"]
    p = subprocess.run(
        [*cmd, "build", "g.usda", "-p", "bad.toml"], cwd=tmp_path, capture_output=True, text=True
    )
    assert p.returncode == 2 and "needs the columns" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "g.usda").exists()


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        (
            "3,4,pine,0.2,18\n12,9,pine,0.1,12.5\n3,4,pine,0.3,20\n",
            r"stems.csv line 4: \(3, 4\) is within 1 cm of sites: stems.csv line 2; two trunks",
        ),
        ("3,4,pine,0.2,18\n3.005,4,pine,0.1,12.5\n", r"line 3: \(3.005, 4\) is within 1 cm of"),
        ("".join("5,5,pine,0.2,18\n" for _ in range(1000)), r"line 3: \(5, 5\) is within 1 cm"),
    ],
    ids=["a-row-twice", "5-mm-apart", "1000-at-one-point"],
)
def test_trunks_at_one_point_are_refused_naming_both_rows(tmp_path, rows, message):
    (tmp_path / "stems.csv").write_text("x,y,species,dbh,height\n" + rows)
    text = INVENTORY.format(extra="")
    start = text.index("sites = [")
    text = text[:start] + 'sites = "stems.csv"\n' + text[text.index("]\n", start) + 2 :]
    (tmp_path / "r.toml").write_text(text)
    with pytest.raises(RecipeError, match=message):
        read_recipe(tmp_path / "r.toml")


@pytest.mark.parametrize("yaw", ["1e300", "-361", "720", "inf"])
def test_an_absurd_yaw_is_refused_with_its_row(tmp_path, yaw):
    (tmp_path / "stems.csv").write_text(
        f"x,y,species,dbh,height,yaw\n3,4,pine,0.2,18,10\n12,9,pine,0.1,12.5,{yaw}\n"
    )
    text = INVENTORY.format(extra="")
    start = text.index("sites = [")
    text = text[:start] + 'sites = "stems.csv"\n' + text[text.index("]\n", start) + 2 :]
    (tmp_path / "r.toml").write_text(text)
    with pytest.raises(RecipeError, match=r"stems.csv line 3(\.|: )yaw"):
        read_recipe(tmp_path / "r.toml")


def soderberg_beech(d_cm, age=100.0):
    """Söderberg 1992 (SLU Dept. of Forest Survey Report 52, p. 42): beech, southern Sweden,
    height (m) of a tree of DBH ``d_cm`` in a stand of ``age`` years, latitude 56°, 100 m
    altitude, no spruce, a county of region 5, with the report's log-bias correction."""
    x = (
        -144.07 / (10 * d_cm + 50)
        + 0.72319e-2 * age
        - 0.27244e-4 * age**2
        - 0.57810e-5 * 56 * 100
        - 0.18416
        + 5.2974
        + 0.01296
    )
    return np.exp(x) / 10


def soderberg_oak(d_cm, si=26.0, d_max=70.0):
    """Söderberg 1992: oak, southern Sweden, pine site index ``si`` m, the plot's largest tree
    ``d_max`` cm, latitude 56°, 100 m altitude, no spruce, region 5."""
    u = 1 / (10 * d_cm + 50)
    x = (
        -258.11 * u
        + 0.63100e4 * u**2
        + 0.13039e-2 * si * 10
        - 0.41543e-5 * 56 * 100
        - 0.32505 * d_cm / d_max
        - 0.047987
        + 5.7884
        + 0.01584
    )
    return np.exp(x) / 10


def test_broadleaf_heights_follow_the_stand_grown_curves(tmp_path):
    # beech and oak in a stand, DBH 10-60 cm: every 10 cm class within 15 % of Söderberg's
    # individual-tree functions (the bar), as the composed stage gives them
    recipe = tmp_path / "broadleaf.toml"
    recipe.write_text(
        """seed = 4
[region]
bounds = [0, 0, 60, 60]
[intensity]
kind = "constant"
value = 0.04
[mix]
european-beech = 0.5
sessile-oak = 0.5
[forest]
variants = 8
hard_core = 2.0
[species.european-beech.stand]
dbh_mean = 0.32
dbh_cv = 0.4
[species.sessile-oak.stand]
dbh_mean = 0.32
dbh_cv = 0.4
"""
    )
    out = tmp_path / "broadleaf.usda"
    write_forest(read_recipe(recipe), out, thumbnail=False)
    t = stand_figures(out)["per_tree"]
    for name, curve in (("european-beech", soderberg_beech), ("sessile-oak", soderberg_oak)):
        mine = t["species"] == name
        d_cm, h = t["dbh"][mine] * 100, t["height"][mine]
        assert mine.sum() >= 30 and d_cm.max() > 45
        for lo in range(10, 60, 10):
            band = (d_cm >= lo) & (d_cm < lo + 10)
            if band.sum() >= 3:
                ratio = np.exp(np.median(np.log(h[band] / curve(d_cm[band]))))
                assert abs(ratio - 1) < 0.15, (name, lo, ratio)
        # at 8 m, the beech yield table's slenderness (Wiedemann 1931: 102-144)
        assert 100 <= 8.0 / (ALLOMETRY[name].dbh(8.0) / 100) <= 144

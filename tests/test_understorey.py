"""The understorey: hazel and bramble shrubs by the cover of their crowns, and the stand's
young trees by stems per hectare, both drawn to the light under the crowns; measured on the
composed stage, labelled, validated, kept out of the stand's figures, seen by the sensors as
no tree's."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from pxr import Usd, UsdGeom
from scipy import stats

from usdforest.errors import RecipeError
from usdforest.grow.understorey import (
    RegenerationSpec,
    ShrubSpec,
    place_regeneration,
    place_shrubs,
    regeneration_heights,
)
from usdforest.recipe import parse_recipe
from usdforest.sites.pointprocess import Rectangle
from usdforest.usd.forest import write_forest
from usdforest.usd.inventory import stand_figures
from usdforest.usd.layers import class_labels, open_stage
from usdforest.usd.validate import validate

SIDE = 30.0
SHRUB_COVER = 0.1
DENSITY = 2000.0  # young trees per hectare


def _recipe(tmp_path: Path, extra: str = "", shrubs: str = f"cover = {SHRUB_COVER}"):
    import tomllib

    text = f"""seed = 11
[region]
bounds = [0.0, 0.0, {SIDE}, {SIDE}]
[intensity]
kind = "constant"
value = 0.02
[mix]
european-beech = 0.6
scots-pine = 0.4
[forest]
variants = 1
lod = "proxy"
[ground]
kind = "plane"
[shrubs]
{shrubs}
[regeneration]
density = {DENSITY}
{extra}"""
    return parse_recipe(tomllib.loads(text), tmp_path, "us.toml")


@pytest.fixture(scope="module")
def forest(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("understorey")
    out = tmp / "f.usda"
    write_forest(_recipe(tmp), out, thumbnail=False)
    return out


def _rows(out: Path, name: str) -> list[dict]:
    with (out.parent / f"{out.stem}_assets" / name).open() as f:
        return list(csv.DictReader(f))


def _crown_points(stage: Usd.Stage, proto: Usd.Prim) -> np.ndarray:
    """Every point of a prototype's wood meshes and placed leaf meshes, in its own space."""
    cache = UsdGeom.XformCache()
    inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(proto), float))
    out = []
    it = iter(Usd.PrimRange(proto))
    for p in it:
        if UsdGeom.Imageable(p).GetPurposeAttr().Get() in ("proxy", "guide"):
            it.PruneChildren()
        elif p.IsA(UsdGeom.Mesh):
            m = np.asarray(cache.GetLocalToWorldTransform(p), float) @ inv
            pts = np.asarray(UsdGeom.Mesh(p).GetPointsAttr().Get(), float)
            out.append(pts @ m[:3, :3] + m[3, :3])
        elif p.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            pi = UsdGeom.PointInstancer(p)
            xf = np.asarray(
                pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
            )
            idx = np.asarray(pi.GetProtoIndicesAttr().Get())
            to = np.asarray(cache.GetLocalToWorldTransform(p), float) @ inv
            for k, target in enumerate(pi.GetPrototypesRel().GetTargets()):
                leaf = stage.GetPrimAtPath(target)
                own = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(leaf), float))
                pts = np.concatenate(
                    [
                        np.asarray(UsdGeom.Mesh(m).GetPointsAttr().Get(), float)
                        @ (np.asarray(cache.GetLocalToWorldTransform(m), float) @ own)[:3, :3]
                        + (np.asarray(cache.GetLocalToWorldTransform(m), float) @ own)[3, :3]
                        for m in Usd.PrimRange(leaf)
                        if m.IsA(UsdGeom.Mesh)
                    ]
                )
                for x in xf[idx == k] @ to:
                    out.append(pts @ x[:3, :3] + x[3, :3])
    return np.concatenate(out)


def test_shrub_crowns_cover_what_the_recipe_asks_and_young_trees_number_its_density(forest):
    """The union of every composed shrub's crown (the hull of its meshes' points on the
    ground, placed by the instancer) covers ``cover`` of the plot; the young trees are
    ``density`` per hectare; ``stats`` says both and keeps them out of the stand's trees."""
    stage = open_stage(forest, full=True)  # every plant at its full detail, as stats sees it
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Understorey"))
    xf = np.asarray(
        inst.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    idx = np.asarray(inst.GetProtoIndicesAttr().Get())
    crowns = []
    for k, target in enumerate(inst.GetPrototypesRel().GetTargets()):
        proto = stage.GetPrimAtPath(target)
        if "shrub" not in class_labels(proto):
            continue
        hull = shapely.convex_hull(shapely.multipoints(_crown_points(stage, proto)[:, :2]))
        for m in xf[idx == k]:
            crowns.append(
                shapely.affinity.affine_transform(
                    hull, [m[0, 0], m[1, 0], m[0, 1], m[1, 1], m[3, 0], m[3, 1]]
                )
            )
    union = shapely.union_all(crowns)
    assert union.area / SIDE**2 == pytest.approx(SHRUB_COVER, rel=0.01)
    # one shrub a cell: no two crowns overlap
    assert sum(c.area for c in crowns) == pytest.approx(union.area, rel=1e-6)
    rows = _rows(forest, "understorey.csv")
    young = [r for r in rows if r["layer"] == "regeneration"]
    assert len(young) == round(DENSITY * SIDE**2 / 1e4)
    f = stand_figures(forest)
    assert f["shrub_cover"] == pytest.approx(SHRUB_COVER, rel=0.01)
    assert f["regeneration_stems_per_ha"] == pytest.approx(DENSITY)
    assert sum(f["shrubs_per_ha"].values()) * SIDE**2 / 1e4 == pytest.approx(len(rows) - len(young))
    trees = _rows(forest, "trees.csv")
    assert f["trees"] == len(trees)  # the understorey is not the stand's
    assert validate(forest) == []


def test_plants_are_labelled_instanced_tree_assets_on_the_ground(forest):
    stage = Usd.Stage.Open(str(forest))
    inst = stage.GetPrimAtPath("/Forest/Understorey")
    assert Usd.ModelAPI(inst).GetKind() == "group"
    targets = UsdGeom.PointInstancer(inst).GetPrototypesRel().GetTargets()
    layers = {}
    for t in targets:
        proto = stage.GetPrimAtPath(t)
        labels = class_labels(proto)
        data = proto.GetCustomDataByKey("usdforest")
        assert labels[0] in ("shrub", "regeneration") and len(labels) == 2
        layers.setdefault(labels[0], []).append(labels[1])
        assert proto.GetVariantSet("lod").GetVariantSelection() == "proxy"
        assert "tree" not in labels
        assert data["layer"] == labels[0]
    assert sorted(set(layers["shrub"])) == ["bramble", "hazel"]
    assert len(layers["shrub"]) == 2 * ShrubSpec().variants
    assert sorted(set(layers["regeneration"])) == ["european-beech", "scots-pine"]
    # young trees: each row's height is its prototype's at full detail, times its scale,
    # within the recipe's range
    stage = open_stage(forest, full=True)
    inst = stage.GetPrimAtPath("/Forest/Understorey")
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"])
    heights = {}
    for t in targets:
        r = bbox.ComputeUntransformedBound(stage.GetPrimAtPath(t)).ComputeAlignedRange()
        heights[t.name] = r.GetMax()[2]
    rows = _rows(forest, "understorey.csv")
    lo, hi = RegenerationSpec().height
    for r in rows:
        if r["layer"] == "regeneration":
            assert lo * 0.99 <= float(r["height"]) <= hi * 1.01
        assert float(r["z"]) == pytest.approx(-0.01)
    xf = np.asarray(
        UsdGeom.PointInstancer(inst).ComputeInstanceTransformsAtTime(
            Usd.TimeCode.Default(), Usd.TimeCode.Default()
        )
    )
    idx = np.asarray(UsdGeom.PointInstancer(inst).GetProtoIndicesAttr().Get())
    # the composed vertical scale (a yaw leaves +Z alone; the determinant would also carry the
    # half-precision quaternions' error in x and y, up to 6e-4)
    scale = xf[:, 2, 2]
    measured = np.array([heights[targets[k].name] for k in idx]) * scale
    # the CSV keeps millimetres
    assert measured == pytest.approx([float(r["height"]) for r in rows], rel=1e-3, abs=6e-4)


def test_young_trees_follow_the_light_heights_and_the_stands_species():
    """Cells under a crown of LAI 4 (light exp(-2)) hold exp(-2) times the young trees of
    open cells; heights are log-uniform (Kolmogorov-Smirnov); species by their shares."""
    region = Rectangle(0.0, 0.0, 40.0, 40.0)
    crowns = (np.array([[10.0, 20.0]]), np.array([10.0]), np.array([4.0]))
    spec = RegenerationSpec(density=20_000.0, cell=2.0)
    shares = np.array([3.0, 1.0])
    p = place_regeneration(spec, region, 5, crowns, (np.zeros((0, 2)), np.zeros(0)), shares)
    n = len(p)
    assert n == 3200
    # the cells whose centres the crown covers: 78 of 400
    cx, cy = np.meshgrid(np.arange(1.0, 40.0, 2.0), np.arange(1.0, 40.0, 2.0))
    under = np.hypot(cx - 10.0, cy - 20.0).ravel() <= 10.0
    k = int(under.sum())
    share_dark = k * math.exp(-2) / (k * math.exp(-2) + (400 - k))
    cell = (np.floor(p.xy[:, 1] / 2) * 20 + np.floor(p.xy[:, 0] / 2)).astype(int)
    dark = under[cell].mean()
    assert dark == pytest.approx(share_dark, abs=4 * math.sqrt(share_dark / n))
    assert set(np.round(p.light, 12)) == {round(math.exp(-2), 12), 1.0}
    lo, hi = spec.height
    ks = stats.kstest((np.log(p.height) - math.log(lo)) / math.log(hi / lo), "uniform")
    assert ks.pvalue > 1e-3
    species = p.proto // spec.classes
    assert species.mean() == pytest.approx(0.25, abs=4 * math.sqrt(0.25 * 0.75 / n))
    classes = regeneration_heights(spec)
    grown = classes[p.proto % spec.classes]
    assert np.abs(np.log(p.height / grown)).max() <= math.log(hi / lo) / spec.classes / 2 + 1e-9
    # stems keep their clearance
    stems = np.array([[20.0, 20.0]])
    q = place_regeneration(spec, region, 5, crowns, (stems, np.array([0.3])), shares)
    assert np.hypot(*(q.xy - stems).T).min() >= 0.3 + spec.clearance


def test_shrubs_take_the_brightest_cells_first_and_refuse_too_much_cover():
    region = Rectangle(0.0, 0.0, 50.0, 50.0)
    crowns = (np.array([[12.5, 25.0]]), np.array([14.0]), np.array([6.0]))
    footprint, reach = np.full(6, 8.0), np.full(6, 2.0)
    spec = ShrubSpec(cover=0.1)
    p = place_shrubs(spec, region, 3, crowns, (np.zeros((0, 2)), np.zeros(0)), footprint, reach)
    covered = np.sum(footprint[p.proto] * p.scale**2)
    assert covered / region.area == pytest.approx(0.1, rel=1e-9)
    # light exp(-3) under the crown: about 5 % the weight of an open cell
    assert (p.light < 0.1).mean() < 0.1
    with pytest.raises(RecipeError, match=r"shrubs\.cover: 0\.6 is more than the cells hold"):
        place_shrubs(
            ShrubSpec(cover=0.6), region, 3, crowns, (np.zeros((0, 2)), np.zeros(0)),
            footprint, reach,
        )  # fmt: skip


def test_the_recipe_checks_its_tables(tmp_path):
    for extra, shrubs, key in (
        ("", "cover = 0.1\nhazel = 0.9", "add up to 1"),
        ("", "cover = 0.1\nvariants = 0", r"shrubs\.variants"),
        ("", "cover = 0.9", r"shrubs\.cover"),
        ("height = [4.0, 1.0]", "", r"regeneration\.height"),
        ("classes = 2.5", "", r"regeneration\.classes"),
        ("densty = 3", "", "densty"),
    ):
        with pytest.raises(RecipeError, match=key):
            _recipe(tmp_path, extra, shrubs)


def test_a_tiled_forest_has_the_same_understorey(forest, tmp_path):
    from dataclasses import replace

    out = tmp_path / "t.usda"
    write_forest(replace(_recipe(tmp_path), tiles=15.0), out, thumbnail=False)
    assert (out.parent / "t_assets" / "understorey.csv").read_bytes() == (
        forest.parent / f"{forest.stem}_assets" / "understorey.csv"
    ).read_bytes()
    assert validate(out) == []


def test_sensors_see_shrubs_as_no_trees_and_the_canopy_gaps_pass_them(forest):
    """A ray straight down onto a hazel meets its wood or leaves with no tree id; a ray that
    meets a shrub first is a gap in the trees' canopy."""
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.scenetypes import CLASS_ID

    rows = [r for r in _rows(forest, "understorey.csv") if r["name"] == "hazel"]
    row = max(rows, key=lambda r: float(r["light"]))
    x, y = float(row["x"]), float(row["y"])
    scene = extract_scene(forest, centre=np.array([x, y, 2.0]), radius=6.0, cache=False)
    rng = np.random.default_rng(1)
    xy = np.array([x, y]) + rng.uniform(-0.4, 0.4, (400, 2))
    origins = np.column_stack([xy, np.full(len(xy), 30.0)])
    hit = SceneCaster(scene).first_hit(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
    low = hit.hit & (hit.t > 30.0 - float(row["height"]) - 0.1)  # below the shrub's top
    shrub = low & np.isin(hit.cls, [CLASS_ID["trunk"], CLASS_ID["branch"], CLASS_ID["leaf"]])
    assert shrub.sum() > 20
    assert (hit.tree[shrub] == -1).all()
    # the canopy's gap fractions count them as passed: the understorey's prims, and only them
    from usdforest.sensors.optics.gaps import understorey_paths

    under = understorey_paths(scene)
    assert under[hit.path[shrub]].all()
    trees = np.isin(hit.cls, [CLASS_ID["trunk"], CLASS_ID["branch"], CLASS_ID["leaf"]]) & ~shrub
    assert not under[hit.path[trees & (hit.tree >= 0)]].any()

"""Ground vegetation: grass, herb, fern and moss patches whose mean cover is the recipe's and
whose cover follows the light under the crowns (Beer-Lambert), measured on the composed stage
(the union of the patches' shadows and nadir rays), labelled, validated, on a litter floor
and seen by the sensors as their own class."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from pxr import Usd, UsdGeom, UsdShade
from shapely import affinity

from usdforest.errors import RecipeError
from usdforest.grow.groundcover import FORMS, GroundCoverSpec, floor_light, place_ground_cover
from usdforest.recipe import parse_recipe
from usdforest.sites.pointprocess import Rectangle
from usdforest.usd.floor import patch_shapes
from usdforest.usd.forest import write_forest
from usdforest.usd.inventory import stand_figures
from usdforest.usd.layers import class_labels, mesh_triangles
from usdforest.usd.validate import validate

COVER = 0.35
SIDE = 24.0


def _recipe(tmp_path: Path, extra: str = "", cover: float = COVER):
    import tomllib

    text = f"""seed = 7
[region]
bounds = [0.0, 0.0, {SIDE}, {SIDE}]
[intensity]
kind = "constant"
value = 0.03
[mix]
european-beech = 1.0
[forest]
variants = 1
lod = "proxy"
[ground]
kind = "plane"
[groundcover]
cover = {cover}
{extra}"""
    return parse_recipe(tomllib.loads(text), tmp_path, "gc.toml")


@pytest.fixture(scope="module")
def forest(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("groundcover")
    out = tmp / "f.usda"
    write_forest(_recipe(tmp), out, thumbnail=False)
    return out


def _rows(out: Path, name: str) -> list[dict]:
    with (out.parent / f"{out.stem}_assets" / name).open() as f:
        return list(csv.DictReader(f))


def _shadows(stage: Usd.Stage) -> dict[str, list]:
    """Per growth form, each composed patch's shadow on the ground: its prototype's triangles
    projected and joined once (shapely), then moved by each instance's transform."""
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/GroundVegetation"))
    xf = np.asarray(
        inst.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    idx = np.asarray(inst.GetProtoIndicesAttr().Get())
    cache = UsdGeom.XformCache()
    out: dict[str, list] = {f: [] for f in FORMS}
    for k, target in enumerate(inst.GetPrototypesRel().GetTargets()):
        proto = stage.GetPrimAtPath(target)
        inv = np.asarray(cache.GetLocalToWorldTransform(proto).GetInverse(), dtype=float)
        tri = np.concatenate(
            [
                mesh_triangles(m, np.asarray(cache.GetLocalToWorldTransform(m), float) @ inv)
                for m in Usd.PrimRange(proto)
                if m.IsA(UsdGeom.Mesh)
            ]
        )
        polys = shapely.polygons(tri[:, :, :2].astype(float))
        shadow = shapely.union_all(polys[shapely.area(polys) > 0])
        form = proto.GetCustomDataByKey("usdforest")["form"]
        for m in xf[idx == k]:
            # row vectors: x' = x m[0,0] + y m[1,0] + m[3,0]
            out[form].append(
                affinity.affine_transform(
                    shadow, [m[0, 0], m[1, 0], m[0, 1], m[1, 1], m[3, 0], m[3, 1]]
                )
            )
    return out


def _union_area(shadows: list, tiles: int = 6) -> tuple[float, float]:
    """The area of the union of ``shadows`` inside the region and outside it (their sum: the
    union's area), joined tile by tile: the region cut into ``tiles`` x ``tiles`` squares,
    each square's pieces of the shadows joined alone, and the pieces outside the region
    joined alone. The same area (the tiles and the outside partition the plane), in a third
    of the time of one union of all (a union's cost grows faster than its pieces')."""
    geoms = np.array(shadows, dtype=object)
    step = SIDE / tiles
    inside = 0.0
    for i in range(tiles):
        for j in range(tiles):
            box = shapely.box(i * step, j * step, (i + 1) * step, (j + 1) * step)
            parts = shapely.intersection(geoms, box)
            parts = parts[~shapely.is_empty(parts)]
            inside += shapely.union_all(parts).area if len(parts) else 0.0
    rest = shapely.difference(geoms, shapely.box(0.0, 0.0, SIDE, SIDE))
    rest = rest[~shapely.is_empty(rest)]
    return inside, (shapely.union_all(rest).area if len(rest) else 0.0)


def test_composed_patches_cover_what_the_recipe_asks(forest):
    """The union of every composed patch's shadow, clipped to the region, covers ``cover`` of
    it; ``stats`` reports the same, per form too."""
    stage = Usd.Stage.Open(str(forest))
    shadows = _shadows(stage)
    region = shapely.box(0.0, 0.0, SIDE, SIDE)
    inside, outside = _union_area([s for f in FORMS for s in shadows[f]])
    measured = inside / region.area
    assert measured == pytest.approx(COVER, rel=0.02)
    # no patch strays outside its cell: nothing of it falls outside the region
    assert inside + outside == pytest.approx(inside, rel=1e-6)
    figures = stand_figures(forest)
    assert figures["ground_vegetation_cover"] == pytest.approx(measured, rel=0.01)
    for form in FORMS:
        share = sum(_union_area(shadows[form])) / region.area if shadows[form] else 0
        assert figures["ground_vegetation_cover_by_form"][form] == pytest.approx(
            share, rel=0.01, abs=1e-9
        )
    rows = _rows(forest, "groundcover.csv")
    cells = (SIDE / GroundCoverSpec().cell) ** 2
    assert len(rows) == cells  # one patch in every cell
    assert figures["ground_vegetation_patches_per_ha"] == pytest.approx(cells / (SIDE**2 / 1e4))
    # the CSV keeps 4 decimals of each patch's m²
    assert sum(float(r["area"]) for r in rows) / SIDE**2 == pytest.approx(COVER, rel=1e-4)


def test_nadir_rays_meet_vegetation_on_the_cover_fraction(forest):
    """Rays straight down from 1 m, between the stems, meet ground vegetation first on the
    cover fraction of them (a binomial sample: 4 sigma)."""
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.scenetypes import CLASS_ID

    scene = extract_scene(forest, cache=False)
    rng = np.random.default_rng(3)
    n = 20_000
    xy = rng.uniform(0.0, SIDE, (n, 2))
    stems = np.array([[float(r["x"]), float(r["y"])] for r in _rows(forest, "trees.csv")])
    far = np.min(np.linalg.norm(xy[:, None] - stems[None], axis=2), axis=1) > 0.6
    xy = xy[far]
    origins = np.column_stack([xy, np.full(len(xy), 1.0)])
    hit = SceneCaster(scene).first_hit(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
    green = hit.cls == CLASS_ID["ground_vegetation"]
    assert set(np.unique(hit.cls)) <= {CLASS_ID["ground"], CLASS_ID["ground_vegetation"]}
    share = float(green.mean())
    sigma = math.sqrt(COVER * (1 - COVER) / len(xy))
    # the sample leaves out the cells round the stems, which are darker: their cover is less
    # than the mean, so the rest of the plot holds a little more
    assert COVER - 2 * sigma < share < COVER * 1.1
    # vegetation is met above the ground and below the tallest patch
    assert (hit.t[green] < 1.0).all() and (hit.t[green] > 1.0 - 0.75).all()
    # the tree ids of vegetation hits are no tree's
    assert (hit.tree[green] == -1).all()


def test_cover_follows_the_light_under_the_crowns():
    """Beer-Lambert light under crowns written here; cells' covers in proportion to it where
    no cap binds, and the mean exactly the recipe's."""
    region = Rectangle(0.0, 0.0, 40.0, 40.0)
    crowns = (np.array([[10.0, 10.0], [30.0, 30.0], [12.0, 14.0]]), np.array([6.0, 8.0, 4.0]),
              np.array([3.0, 2.0, 4.0]))  # fmt: skip
    shapes = patch_shapes()
    spec = GroundCoverSpec(cover=0.2, light_response=1.0)
    p = place_ground_cover(spec, region, 11, crowns, shapes)
    # the light written from the definition: exp(-0.5 * the LAI of every crown over a cell)
    centre = np.floor(p.base[:, :2] / spec.cell) * spec.cell + spec.cell / 2
    lai = np.zeros(len(centre))
    for xy, r, la in zip(*crowns, strict=True):
        lai += np.where(np.linalg.norm(centre - xy, axis=1) <= r, la, 0.0)
    assert p.light == pytest.approx(np.exp(-0.5 * lai))
    assert np.isclose(floor_light(centre, *crowns), p.light).all()
    assert p.area.sum() / region.area == pytest.approx(0.2, rel=1e-9)
    caps = np.array([shapes[f].cap for f in FORMS])[p.form]
    free = p.cover < caps - 1e-9
    ratio = p.cover[free] / p.light[free]
    assert ratio == pytest.approx(np.full(free.sum(), ratio[0]), rel=1e-9)
    assert (p.cover <= caps + 1e-12).all()
    # darker cells hold less: the shaded quarter's mean cover is below the open quarter's
    shaded = p.light < 0.5
    assert shaded.any() and p.cover[shaded].mean() < 0.5 * p.cover[p.light == 1.0].mean()
    # without a light response every cell has the same cover
    flat = place_ground_cover(replace_spec(spec, light_response=0.0), region, 11, crowns, shapes)
    assert np.ptp(flat.cover) < 1e-12
    # the forms take their shares of the cells (a multinomial draw of 400)
    counts = np.bincount(p.form, minlength=4) / len(p)
    assert counts == pytest.approx(spec.shares, abs=4 * math.sqrt(0.35 * 0.65 / 400))


def replace_spec(spec: GroundCoverSpec, **kw) -> GroundCoverSpec:
    from dataclasses import replace

    return replace(spec, **kw)


def test_patches_are_labelled_instanced_on_litter_and_validate(forest):
    assert validate(forest) == []
    stage = Usd.Stage.Open(str(forest))
    inst = stage.GetPrimAtPath("/Forest/GroundVegetation")
    assert inst.IsA(UsdGeom.PointInstancer)
    assert Usd.ModelAPI(inst).GetKind() == "group"
    targets = UsdGeom.PointInstancer(inst).GetPrototypesRel().GetTargets()
    assert [t.name for t in targets] == [f.capitalize() for f in FORMS]
    for t in targets:
        proto = stage.GetPrimAtPath(t)
        form = proto.GetCustomDataByKey("usdforest")["form"]
        assert class_labels(proto) == ["ground_vegetation", form]
        meshes = [m for m in Usd.PrimRange(proto) if m.IsA(UsdGeom.Mesh)]
        assert meshes and all(class_labels(m) == ["ground_vegetation"] for m in meshes)
        assert all(UsdGeom.Mesh(m).GetDoubleSidedAttr().Get() for m in meshes)
        assert proto.GetPrimStack()[-1].layer.identifier.endswith(".usdc")
    # every patch rests on the plane (1 cm down) and the extents hold it
    rows = _rows(forest, "groundcover.csv")
    assert {float(r["z"]) for r in rows} == {-0.01}
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default"])
    ext = bbox.ComputeWorldBound(inst).ComputeAlignedRange()
    box = np.array(UsdGeom.PointInstancer(inst).GetExtentAttr().Get(), dtype=float)
    assert (box[0] <= np.array(ext.GetMin()) + 1e-3).all()
    assert (box[1] >= np.array(ext.GetMax()) - 1e-3).all()
    hint = np.array(stage.GetPrimAtPath("/Forest").GetAttribute("extentsHint").Get(), float)
    assert (hint[0] <= box[0] + 1e-6).all() and (hint[1] >= box[1] - 1e-6).all()
    # the floor is leaf litter
    ground = stage.GetPrimAtPath("/Forest/Ground/Mesh")
    assert class_labels(ground) == ["ground", "litter"]
    material, _ = UsdShade.MaterialBindingAPI(ground).ComputeBoundMaterial()
    assert material.GetPrim().GetName() == "Litter"
    assert material.GetPrim().GetAttribute("omni:simready:nonvisual:base").Get() == (
        "dead_leaf_grass"
    )


def test_a_tiled_forest_has_the_same_patches(forest, tmp_path):
    from dataclasses import replace

    tiled = replace(_recipe(tmp_path), tiles=12.0)
    out = tmp_path / "t.usda"
    write_forest(tiled, out, thumbnail=False)
    assert (out.parent / "t_assets" / "groundcover.csv").read_bytes() == (
        forest.parent / f"{forest.stem}_assets" / "groundcover.csv"
    ).read_bytes()
    assert validate(out) == []
    assert stand_figures(out)["ground_vegetation_cover"] == pytest.approx(COVER, rel=0.01)


def test_the_recipe_checks_its_table_and_a_cover_beyond_the_patches(tmp_path):
    for extra, key in (
        ("grass = 0.9", "add up to 1"),
        ("cell = 0.01", r"groundcover\.cell"),
        ("light_response = -1", r"groundcover\.light_response"),
        ("litter = 1", r"groundcover\.litter"),
        ("covers = 3", "covers"),
    ):
        with pytest.raises(RecipeError, match=key):
            _recipe(tmp_path, extra)
    with pytest.raises(RecipeError, match=r"groundcover\.cover"):
        _recipe(tmp_path, cover=1.5)
    with pytest.raises(RecipeError, match=r"groundcover\.cover: 0\.9 is more than"):
        place_ground_cover(
            GroundCoverSpec(cover=0.9),
            Rectangle(0.0, 0.0, 10.0, 10.0),
            1,
            (np.zeros((0, 2)), np.zeros(0), np.zeros(0)),
            patch_shapes(),
        )


def test_the_cli_refuses_a_bad_table_in_one_line(tmp_path):
    import subprocess
    import sys

    recipe = tmp_path / "bad.toml"
    recipe.write_text(
        '[region]\nbounds = [0.0, 0.0, 10.0, 10.0]\n[intensity]\nkind = "constant"\n'
        "value = 0.01\n[groundcover]\ncover = 0.3\nmoss = 0.9\n"
    )
    out = tmp_path / "f.usda"
    r = subprocess.run(
        [sys.executable, "-m", "usdforest", "build", str(out), "--pipeline", str(recipe)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert "groundcover: grass + herb + fern + moss" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_the_sonar_hears_every_blade_as_a_leaf_of_its_own_class(forest):
    """Each grass blade, herb leaf and fern pinna is one reflector (pieces of the CAD mesh
    counted here with trimesh) carrying its placed area (the composed mesh's); moss echoes as
    the ground under it; the sonar sums the blades as their own class."""
    import trimesh

    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.sonar.model import PRESETS, Targets, echo_from_targets

    stage = Usd.Stage.Open(str(forest))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/GroundVegetation"))
    xf = np.asarray(
        inst.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    idx = np.asarray(inst.GetProtoIndicesAttr().Get())
    cache = UsdGeom.XformCache()
    pieces, area = 0, 0.0
    for k, target in enumerate(inst.GetPrototypesRel().GetTargets()):
        proto = stage.GetPrimAtPath(target)
        if proto.GetCustomDataByKey("usdforest")["form"] == "moss":
            continue
        inv = np.asarray(cache.GetLocalToWorldTransform(proto).GetInverse(), dtype=float)
        tri = np.concatenate(
            [
                mesh_triangles(m, np.asarray(cache.GetLocalToWorldTransform(m), float) @ inv)
                for m in Usd.PrimRange(proto)
                if m.IsA(UsdGeom.Mesh)
            ]
        ).astype(float)
        mesh = trimesh.Trimesh(tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3))
        mesh.merge_vertices()
        parts = trimesh.graph.connected_components(
            mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1
        )
        pieces += len(parts) * int((idx == k).sum())
        for m in xf[idx == k]:
            placed = tri.reshape(-1, 3) @ m[:3, :3] + m[3, :3]
            area += float(trimesh.triangles.area(placed.reshape(-1, 3, 3)).sum())
    scene = extract_scene(forest, cache=False)
    blades = scene.leaves.on_ground
    assert int(blades.sum()) == pieces
    # a blade's area after the patch's stretch (more across than up), from its mean normal:
    # exact for a flat blade, within a few per cent for these gently curved ones
    assert float(scene.leaves.area[blades].sum()) == pytest.approx(area, rel=0.05)
    assert (scene.leaves.tree[blades] == -1).all()
    # a sonar a metre above the floor, looking down, hears them as their own class
    row = max(
        _rows(forest, "groundcover.csv"), key=lambda r: float(r["cover"]) * (r["form"] == "grass")
    )
    x, y = float(row["x"]), float(row["y"])
    cfg = PRESETS["paper"]
    echo = echo_from_targets(Targets(scene.leaves), Pose(x, y, 1.0, 0.0, -90.0, 0.0), cfg)
    assert np.abs(echo.parts["ground_vegetation"]).max() > 0
    assert echo.reflectors["ground_vegetation"] > 0

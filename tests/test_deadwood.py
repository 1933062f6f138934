"""Dead wood: snags, stumps, logs and fallen branches by volume per hectare (German NFI 2012
defaults), measured on the composed stage, drawn as the recipe's distributions say, clear of
the stems, labelled, validated, seen by the sensors and stopping a ball in a physics engine."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from optional import optional_tool
from physics_probe import roll as roll_ball
from pxr import Usd, UsdGeom
from scipy import integrate
from scipy.special import gamma

from usdforest.errors import UsdForestError
from usdforest.grow.allometry import weibull_for
from usdforest.grow.deadwood import KINDS, DeadWoodSpec, place_dead_wood
from usdforest.recipe import parse_recipe
from usdforest.sites.pointprocess import Rectangle
from usdforest.sites.terrain import HeightField
from usdforest.usd.debris import piece_shapes
from usdforest.usd.forest import write_forest
from usdforest.usd.inventory import stand_figures
from usdforest.usd.layers import class_labels
from usdforest.usd.validate import validate

VOLUME = 60.0  # m³/ha: three times the managed mean, so a 40 m plot holds a few dozen pieces
SHARES = {"lying": 0.49, "standing": 0.23, "stumps": 0.28}  # BWI 2012


def _recipe(tmp_path: Path, extra: str = "", volume: float = VOLUME):
    import tomllib

    text = f"""seed = 5
[region]
bounds = [0.0, 0.0, 40.0, 40.0]
[intensity]
kind = "constant"
value = 0.02
[mix]
scots-pine = 1.0
[species.scots-pine]
[forest]
variants = 1
lod = "proxy"
[ground]
kind = "plane"
[deadwood]
volume = {volume}
{extra}"""
    return parse_recipe(tomllib.loads(text), tmp_path, "dw.toml")


@pytest.fixture(scope="module")
def forest(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("deadwood")
    out = tmp / "f.usda"
    write_forest(_recipe(tmp), out, thumbnail=False)
    return out


def _rows(out: Path, name: str) -> list[dict]:
    with (out.parent / f"{out.stem}_assets" / name).open() as f:
        return list(csv.DictReader(f))


def _composed_pieces(stage: Usd.Stage):
    """Each instance's mesh placed by its instance transform, with its prototype's kind."""
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/DeadWood"))
    xf = np.asarray(
        inst.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    idx = np.asarray(inst.GetProtoIndicesAttr().Get())
    meshes = []
    for target in inst.GetPrototypesRel().GetTargets():
        proto = stage.GetPrimAtPath(target)
        mesh = next(UsdGeom.Mesh(m) for m in Usd.PrimRange(proto) if m.IsA(UsdGeom.Mesh))
        pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=float)
        faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        kind = proto.GetCustomDataByKey("usdforest")["kind"]
        meshes.append((pts, faces, kind))
    for m, k in zip(xf, idx, strict=True):
        pts, faces, kind = meshes[k]
        placed = pts @ m[:3, :3] + m[3, :3]
        yield trimesh.Trimesh(placed, faces, process=False), kind


def test_composed_dead_wood_holds_the_recipes_volume_per_compartment(forest):
    stage = Usd.Stage.Open(str(forest))
    area_ha = 40 * 40 / 1e4
    volume = dict.fromkeys(KINDS, 0.0)
    pieces = 0
    for mesh, kind in _composed_pieces(stage):
        assert mesh.is_watertight
        volume[kind] += mesh.volume  # trimesh's own volume of each placed piece
        pieces += 1
    lying = volume["log"] + volume["branch"]
    asked = VOLUME * area_ha
    # each compartment is filled to its share (the last piece cut to the remainder)
    assert lying == pytest.approx(SHARES["lying"] * asked, rel=0.01)
    assert volume["snag"] == pytest.approx(SHARES["standing"] * asked, rel=0.01)
    assert volume["stump"] == pytest.approx(SHARES["stumps"] * asked, rel=0.01)
    # the ground truth agrees piece by piece in sum, and `usdforest stats` reads the same
    rows = _rows(forest, "deadwood.csv")
    assert len(rows) == pieces
    table = sum(math.pi / 4 * float(r["diameter"]) ** 2 * float(r["length"]) for r in rows)
    assert table == pytest.approx(sum(volume.values()), rel=1e-3)
    figures = stand_figures(forest)
    assert figures["dead_wood_m3_per_ha"] == pytest.approx(VOLUME, rel=0.01)
    for kind in KINDS:
        assert figures["dead_wood_by_kind_m3_per_ha"][kind] == pytest.approx(
            volume[kind] / area_ha, rel=1e-3
        )
    # the trees are still counted as trees only
    assert figures["trees"] == len(_rows(forest, "trees.csv"))


def test_dead_wood_is_labelled_instanced_and_validates(forest):
    assert validate(forest) == []
    stage = Usd.Stage.Open(str(forest))
    inst = stage.GetPrimAtPath("/Forest/DeadWood")
    assert inst.IsA(UsdGeom.PointInstancer)
    assert Usd.ModelAPI(inst).GetKind() == "group"
    targets = UsdGeom.PointInstancer(inst).GetPrototypesRel().GetTargets()
    assert len(targets) == 16  # 4 kinds x 4 decay classes
    for t in targets:
        proto = stage.GetPrimAtPath(t)
        kind = proto.GetCustomDataByKey("usdforest")["kind"]
        assert class_labels(proto) == ["dead_wood", kind]
        assert Usd.ModelAPI(proto).GetKind() == "component"
        meshes = [m for m in Usd.PrimRange(proto) if m.IsA(UsdGeom.Mesh)]
        assert meshes and all(class_labels(m) == ["dead_wood"] for m in meshes)
        assert proto.GetPrimStack()[-1].layer.identifier.endswith(".usdc")  # a template
    # the instancer's extent and /Forest's extentsHint hold every placed piece
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for mesh, _ in _composed_pieces(stage):
        lo, hi = np.minimum(lo, mesh.bounds[0]), np.maximum(hi, mesh.bounds[1])
    for box in (
        UsdGeom.PointInstancer(inst).GetExtentAttr().Get(),
        stage.GetPrimAtPath("/Forest").GetAttribute("extentsHint").Get(),
    ):
        box = np.array(box, dtype=float)
        assert (box[0] <= lo + 1e-3).all() and (box[1] >= hi - 1e-3).all()
    # every piece stands or lies on the plane: standing feet 1 cm down, lying pieces resting
    # (orientations are half floats, as Blender reads them: a 10 m log's end moves <= 1 cm)
    for mesh, kind in _composed_pieces(stage):
        low = mesh.bounds[0, 2]
        if kind in ("snag", "stump"):
            assert low == pytest.approx(-0.01, abs=1e-3)
        else:  # decay classes 3-4 sink by at most a quarter of their thickness
            assert -0.26 * np.ptp(mesh.vertices[:, 2]) - 0.01 <= low <= 0.01


def test_diameters_follow_the_truncated_weibull_and_the_inventorys_thick_share():
    spec = DeadWoodSpec(volume=130.0)  # a beech reserve's mean (Christensen et al. 2005)
    region = Rectangle(0.0, 0.0, 100.0, 100.0)
    p = place_dead_wood(spec, region, 11, np.zeros((0, 2)), np.zeros(0), piece_shapes())
    # the theory: the Weibull of mean 0.20 m and CV 0.5 truncated at 0.10 m, pieces weighted
    # by d² (volume at lengths independent of d)
    k, lam = weibull_for(0.20, 0.5)
    g1, g2 = gamma(1 + 1 / k), gamma(1 + 2 / k)  # its mean and CV, checked independently
    assert lam * g1 == pytest.approx(0.20) and math.sqrt(g2 / g1**2 - 1) == pytest.approx(0.5)

    def pdf(d):
        return (k / lam) * (d / lam) ** (k - 1) * math.exp(-((d / lam) ** k))

    def d2(d):
        return d * d * pdf(d)

    thick = integrate.quad(d2, 0.30, 3.0)[0] / integrate.quad(d2, 0.10, 3.0)[0]
    v = p.volume
    share = v[p.diameter >= 0.30].sum() / v.sum()
    # the defaults are calibrated: BWI 2012 found 47 % of the volume in pieces of 30 cm+
    assert thick == pytest.approx(0.47, abs=0.03)
    # the drawn pieces follow (volume weights are heavy-tailed: a few thick logs swing it)
    assert share == pytest.approx(thick, abs=0.06)
    assert p.diameter.min() >= 0.10 - 1e-9
    # truncated mean: E[d | d >= 0.10]
    mean = integrate.quad(lambda d: d * pdf(d), 0.10, 3.0)[0] / integrate.quad(pdf, 0.10, 3.0)[0]
    sizes = p.diameter[:-3]  # the compartments' last pieces are cut to the remainder
    assert sizes.mean() == pytest.approx(mean, rel=4 * sizes.std() / mean / math.sqrt(len(sizes)))
    # decay classes: a quarter each, within 4 binomial standard deviations
    n = len(p)
    for c in range(1, 5):
        assert abs(np.count_nonzero(p.decay == c) - n / 4) < 4 * math.sqrt(n * 0.25 * 0.75)
    # thin lying pieces are fallen branches, thick ones logs
    lying = np.isin(p.kind, [KINDS.index("log"), KINDS.index("branch")])
    branch = p.kind == KINDS.index("branch")
    assert np.array_equal(branch[lying], p.diameter[lying] < spec.branch_diameter)


def test_pieces_keep_clear_of_stems_and_of_each_other():
    rng = np.random.default_rng(0)
    stems = rng.uniform(0, 60, (150, 2))
    radius = np.full(150, 0.2)
    spec = DeadWoodSpec(volume=80.0, clearance=0.1)
    shapes = piece_shapes()
    p = place_dead_wood(spec, Rectangle(0.0, 0.0, 60.0, 60.0), 2, stems, radius, shapes)
    a, b = p.base[:, :2], (p.base + p.axis * p.length[:, None])[:, :2]
    reach = np.array(
        [shapes[(KINDS[k], int(d))].reach for k, d in zip(p.kind, p.decay, strict=True)]
    )
    r = p.diameter / 2 * reach

    def distances(points, a0, b0):
        """Distances of ``points (m, 2)`` from every segment ``a0``-``b0`` ``(n, 2)``."""
        ab = b0 - a0
        t = np.einsum("mnk,nk->mn", points[:, None] - a0[None], ab)
        t = np.clip(t / np.maximum((ab * ab).sum(axis=1), 1e-18), 0, 1)
        return np.linalg.norm(points[:, None] - (a0[None] + t[..., None] * ab[None]), axis=2)

    for i in range(len(p)):
        # sampled along the piece's axis: an independent check of the placement's geometry
        pts = a[i] + np.linspace(0, 1, 100)[:, None] * (b[i] - a[i])
        to_stems = np.linalg.norm(pts[:, None] - stems[None], axis=2).min(axis=0)
        assert (to_stems >= r[i] + radius + spec.clearance - 1e-6).all()
        others = np.arange(i)
        if others.size:
            d = distances(pts, a[others], b[others]).min(axis=0)
            assert (d >= r[i] + r[others] + spec.clearance - 1e-6).all()


def test_logs_follow_and_rest_on_a_slope():
    ground = HeightField(np.tile(np.linspace(0.0, 10.0, 51), (51, 1)), (0.0, 0.0, 50.0, 50.0))
    spec = DeadWoodSpec(volume=40.0, decay=(1.0, 0.0, 0.0, 0.0))
    shapes = piece_shapes()
    p = place_dead_wood(
        spec, Rectangle(5.0, 5.0, 45.0, 45.0), 3, np.zeros((0, 2)), np.zeros(0), shapes, ground
    )
    lying = np.isin(p.kind, [KINDS.index("log"), KINDS.index("branch")])
    tip = p.base + p.axis * p.length[:, None]
    # the axis climbs with the ground: dz/dx = 0.2 (10 m over 50 m)
    slope = (tip[lying, 2] - p.base[lying, 2]) / (tip[lying, 0] - p.base[lying, 0])
    assert np.allclose(slope, 0.2, atol=0.02)
    # a standing piece's foot is below the ground everywhere under it
    standing = ~lying
    foot = p.base[standing]
    assert (foot[:, 2] <= ground.height(foot[:, 0], foot[:, 1]) - 0.01 + 1e-6).all()


def test_a_crowded_plot_is_a_clear_error_and_the_recipe_checks_its_table(tmp_path):
    spec = DeadWoodSpec(volume=2000.0)
    with pytest.raises(UsdForestError, match="deadwood: no room"):
        place_dead_wood(
            spec,
            Rectangle(0.0, 0.0, 10.0, 10.0),
            1,
            np.zeros((0, 2)),
            np.zeros(0),
            piece_shapes(),
        )
    from usdforest.errors import RecipeError

    for extra, key in (
        ("lying = 0.9", "add up to 1"),
        ("decay = [0.5, 0.5, 0.5, 0.5]", "deadwood.decay"),
        ("snag_height = [12.0, 2.0]", "deadwood.snag_height"),
        ("diameter_cv = 9.0", "deadwood.diameter_cv"),
        ("volumes = 3", "volumes"),
    ):
        with pytest.raises(RecipeError, match=key):
            _recipe(tmp_path, extra)
    with pytest.raises(RecipeError, match=r"deadwood\.volume"):
        _recipe(tmp_path, volume=5000.0)


def test_a_tiled_forest_has_the_same_dead_wood_with_its_colliders(forest, tmp_path):
    """Tiles do not change the pieces (placed among every stem, as untiled); a tiled forest
    keeps their colliders in deadwood.usdc, its tiles holding only their trees'."""
    from dataclasses import replace

    tiled = replace(_recipe(tmp_path), tiles=20.0)
    out = tmp_path / "t.usda"
    write_forest(tiled, out, thumbnail=False)
    assert (out.parent / "t_assets" / "deadwood.csv").read_bytes() == (
        forest.parent / f"{forest.stem}_assets" / "deadwood.csv"
    ).read_bytes()
    assert validate(out) == []
    stage = Usd.Stage.Open(str(out))
    colliders = stage.GetPrimAtPath("/Forest/Colliders").GetChildren()
    assert len(colliders) == len(_rows(forest, "deadwood.csv"))
    assert all(c.GetName().startswith("D_") for c in colliders)
    volume = sum(mesh.volume for mesh, _ in _composed_pieces(stage))
    assert volume == pytest.approx(VOLUME * 0.16, rel=0.01)


def test_sensors_see_dead_wood_as_its_own_class(forest):
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.scenetypes import CLASS_ID
    from usdforest.sensors.sonar.wood import scene_cylinders

    rows = _rows(forest, "deadwood.csv")
    log = max((r for r in rows if r["kind"] == "log"), key=lambda r: float(r["diameter"]))
    x, y, z = (float(log[k]) for k in ("x", "y", "z"))
    scene = extract_scene(forest, centre=np.array([x, y, z]), radius=8.0, cache=False)
    assert (scene.cls == CLASS_ID["dead_wood"]).any()
    cyl = scene_cylinders(scene, 0.5)
    dead = cyl.cls == CLASS_ID["dead_wood"]
    # the sonar's cylinder nearest the log's middle has the log's radius (its slice of a
    # barked, tapering log; the ground truth is the equal-volume diameter)
    near = np.argmin(np.where(dead, np.linalg.norm(cyl.centre - [x, y, z], axis=1), np.inf))
    assert cyl.radius[near] == pytest.approx(float(log["diameter"]) / 2, rel=0.15)
    assert np.linalg.norm(cyl.centre[near] - [x, y, z]) < 0.5
    # no dead-wood cylinder is wider than the thickest piece
    assert cyl.radius[dead].max() < max(float(r["diameter"]) for r in rows)
    # a nadir ray onto the log's middle from 5 m up meets dead wood at its top
    from usdforest.sensors.cast.raycast import SceneCaster

    hit = SceneCaster(scene).first_hit(np.array([[x, y, z + 5.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert hit.cls[0] == CLASS_ID["dead_wood"]
    assert 5.0 - float(log["diameter"]) < float(hit.t[0]) < 5.0


def test_newton_stops_a_ball_at_a_log(forest):
    py = optional_tool("USDFOREST_PHYSICS_PYTHON", "newton", ".venv-physics", "newton")
    rows = _rows(forest, "deadwood.csv")
    log = max((r for r in rows if r["kind"] == "log"), key=lambda r: float(r["diameter"]))
    x, y, z = (float(log[k]) for k in ("x", "y", "z"))
    az = math.radians(float(log["azimuth"]))
    across = np.array([-math.sin(az), math.cos(az)])  # roll the ball at the log from its side
    start = np.array([x, y]) - 2.0 * across
    physics = forest.parent / f"{forest.stem}_assets" / "physics.usda"

    end = np.array(roll_ball(py, physics, (*start, z), (*(1.5 * across), 0.0), 2.0)["position"][:2])
    # it travelled 3 m free; against the log it stops a ball radius and the log's short of it
    travelled = float((end - start) @ across)
    assert travelled < 2.0 - 0.2 - float(log["diameter"]) / 2 + 0.1
    stage = Usd.Stage.Open(str(physics))
    names = [p.GetName() for p in stage.GetPrimAtPath("/Forest/Colliders").GetChildren()]
    assert sum(n.startswith("D_") for n in names) == len(rows)

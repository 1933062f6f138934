"""Tiled forests: payload tiles composed back into the untiled forest, loaded one at a time."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from usdforest.errors import RecipeError
from usdforest.recipe import default_recipe_path, load_toml, parse_recipe, read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.validate import validate

QUICK = default_recipe_path().parent / "quick-mixed.toml"


def _recipe(tmp_path, **extra):
    """The quick mixed stand (fixed-grammar trees: tiling is about where trees go), changed
    by ``extra``."""
    data = {**load_toml(QUICK), **extra}
    return parse_recipe(data, QUICK.parent, str(tmp_path / "r.toml"))


def _trees(stage: Usd.Stage) -> dict[int, tuple[np.ndarray, int]]:
    """Every composed tree by id: its world position and its prototype's name (the forest's
    instancers, not the leaves' inside the trees)."""
    return {i: (m[3, :3], name) for i, (m, name) in _instances(stage).items()}


def _rows(path) -> dict[int, np.ndarray]:
    with open(path) as f:
        return {int(r["id"]): np.array([float(r[k]) for k in "xyz"]) for r in csv.DictReader(f)}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tiles")
    flat = tmp / "flat.usda"
    tiled = tmp / "tiled.usda"
    recipe = _recipe(tmp, tiles={"size": 40.0})
    write_forest(recipe, flat, thumbnail=False, untiled=True)
    write_forest(recipe, tiled, thumbnail=False)
    return flat, tiled


def test_tiles_compose_into_the_untiled_forest(built):
    flat, tiled = built
    assert validate(tiled) == []
    a = _trees(Usd.Stage.Open(str(flat)))
    b = _trees(Usd.Stage.Open(str(tiled)))
    assert len(a) > 100 and sorted(a) == sorted(b)
    for i, (x, name) in a.items():
        assert b[i][1] == name
        np.testing.assert_allclose(b[i][0], x, atol=1e-4)
    # the same trunk colliders
    stages = [Usd.Stage.Open(str(f)) for f in (flat, tiled)]
    caps = [
        sorted(
            tuple(
                np.round(
                    UsdGeom.Xformable(p)
                    .ComputeLocalToWorldTransform(Usd.TimeCode.Default())
                    .ExtractTranslation(),
                    3,
                )
            )
            for p in s.Traverse()
            if p.IsA(UsdGeom.Capsule) and "/Prototypes/" not in p.GetPath().pathString
        )
        for s in stages
    ]
    assert len(caps[0]) == len(caps[1]) > 100
    np.testing.assert_allclose(caps[0], caps[1], atol=2e-3)
    # every tree where its tile's CSV puts it; tiles.csv indexes them (trees and extents)
    assets = tiled.parent / "tiled_assets"
    with (assets / "tiles.csv").open() as f:
        index = list(csv.DictReader(f))
    rows = {}
    for t in index:
        part = _rows(assets / t["csv"])
        assert len(part) == int(t["trees"]) and (assets / t["layer"]).is_file()
        lo = np.array([float(t[k]) for k in ("min_x", "min_y", "min_z")])
        hi = np.array([float(t[k]) for k in ("max_x", "max_y", "max_z")])
        for x in part.values():  # the trunk bases lie inside their tile's extent
            assert np.all(x >= lo - 1e-3) and np.all(x <= hi + 1e-3)
        rows.update(part)
    assert sorted(rows) == sorted(b) == list(range(len(b)))
    for i, (x, _) in b.items():
        np.testing.assert_allclose(x, rows[i], atol=1e-3)


def test_a_tile_loads_alone(built):
    _, tiled = built
    stage = Usd.Stage.Open(str(tiled), Usd.Stage.LoadNone)
    tiles = stage.GetPrimAtPath("/Forest/Tiles").GetAllChildren()  # unloaded ones too
    assert len(tiles) == 9
    assert not any(p.IsA(UsdGeom.PointInstancer) for p in stage.Traverse())
    # the unloaded tiles still bound their trees
    hints = {p.GetName(): UsdGeom.ModelAPI(p).GetExtentsHint() for p in tiles}
    assert all(len(h) == 2 for h in hints.values())
    stage.Load("/Forest/Tiles/Tile_1_1")
    loaded = [
        p.GetPath().pathString
        for p in stage.Traverse()
        if p.IsA(UsdGeom.PointInstancer) and Usd.ModelAPI(p).GetKind() == "group"
    ]
    assert loaded == ["/Forest/Tiles/Tile_1_1/Trees"]
    trees = _trees(stage)
    rows = _rows(tiled.parent / "tiled_assets" / "tiles" / "Tile_1_1.csv")
    assert sorted(trees) == sorted(rows) and len(rows) > 5
    for i, (x, _) in trees.items():
        np.testing.assert_allclose(x, rows[i], atol=1e-3)
        assert 40 <= rows[i][0] < 80 and 40 <= rows[i][1] < 80
    # and inside the extent its unloaded prim announced (tile-local, moved by its translate)
    lo, hi = (np.array(v) for v in hints["Tile_1_1"])
    pos = np.array([x for x, _ in trees.values()]) - [40, 40, 0]
    assert np.all(pos >= lo - 1e-4) and np.all(pos <= hi + 1e-4)


def test_a_drone_survey_of_the_tiled_forest_on_two_workers_is_the_untiled_ones(built, tmp_path):
    """Issue 62, item 6: a drone survey over tile edges (tiles of 40 m; the region 20-60 m
    crosses the edge at 40 m both ways), its lines Dask tasks on two workers, each task
    gathering its own scene from the payload tiles it reaches: the same bytes in every line
    as the survey of the tiled forest in one process, and what the survey of the untiled
    forest sees: the same points but for a grazing few (a tile's trees sit at its translate
    plus tile-local float32 positions, so a pulse that grazes an edge may hit or miss by a
    last bit; 1 of 39,548 hit a leaf 5 cm above the twig it hit untiled)."""
    pytest.importorskip("distributed", reason="needs dask.distributed (usdforest[dask])")
    import laspy

    import usdforest

    flat, tiled = built
    plan = {
        "survey": {"kind": "flight", "region": [20.0, 20.0, 60.0, 60.0], "height": 30.0,
                   "scan_angle": 40.0},
        "lidar": {"pulse_rate": 20000.0},
    }  # fmt: skip
    usdforest.survey(flat, plan, out=tmp_path / "flat")
    here = usdforest.survey(tiled, plan, out=tmp_path / "here")
    usdforest.survey(tiled, plan, out=tmp_path / "tiled", workers=2)
    lines = sorted((tmp_path / "tiled" / "lines").glob("*.las"))
    assert [p.name for p in lines] == [f"line_{k + 1:03d}.las" for k in range(len(here.parts))]
    assert len(lines) >= 2
    for k, path in enumerate(lines):
        assert path.read_bytes() == (tmp_path / "here" / "lines" / path.name).read_bytes()
        a, b = laspy.read(str(tmp_path / "flat" / "lines" / path.name)), laspy.read(str(path))
        assert len(b.points) == len(here.parts[k]) > 1000
        assert abs(len(a.points) - len(b.points)) <= 1e-3 * len(a.points)
        for cls in range(7):
            na = np.count_nonzero(np.asarray(a.classification) == cls)
            nb = np.count_nonzero(np.asarray(b.classification) == cls)
            assert abs(na - nb) <= max(2, 1e-3 * na), (path.name, cls, na, nb)
        ta, tb = np.unique(a.treeID), np.unique(b.treeID)
        assert np.array_equal(ta, tb), path.name
    # its trees stand in several tiles
    hit = set().union(*(set(np.unique(laspy.read(str(f)).treeID)) for f in lines)) - {0}
    owner = {
        i: csv_path.stem
        for csv_path in (tiled.parent / "tiled_assets" / "tiles").glob("Tile_*.csv")
        for i in _rows(csv_path)
    }
    assert len({owner[int(t) - 1] for t in hit}) >= 4


@pytest.mark.parametrize(
    ("tiles", "fragment"),
    [
        ({"size": 0}, "tiles.size: must be > 0"),
        ({"size": 50, "shape": "hex"}, "tiles: unknown key 'shape'"),
        ({}, "tiles.size: missing"),
        (5, "tiles: expected a table"),
    ],
)
def test_bad_tiles_are_named(tmp_path, tiles, fragment):
    with pytest.raises(RecipeError) as err:
        _recipe(tmp_path, tiles=tiles)
    assert fragment in str(err.value)


def test_two_dask_workers_write_the_same_bytes_as_one(tmp_path):
    """A 4-tile forest on a 2-worker LocalCluster: every file byte for byte the one-process
    build's (the tasks finish in any order; the root lists the tiles in tile order)."""
    pytest.importorskip("distributed", reason="Dask tiles need dask.distributed (usdforest[dask])")
    recipe = _recipe(tmp_path, tiles={"size": 50.0})
    one, two = tmp_path / "one" / "f.usda", tmp_path / "two" / "f.usda"
    one.parent.mkdir()
    two.parent.mkdir()
    a = write_forest(recipe, one, thumbnail=False)
    b = write_forest(recipe, two, thumbnail=False, workers=2)
    assert a.n_tiles == b.n_tiles == 4
    files = sorted(p.relative_to(one.parent) for p in one.parent.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(two.parent) for p in two.parent.rglob("*") if p.is_file())
    assert len([f for f in files if f.suffix == ".usdc" and "tiles" in f.parts]) == 4
    for f in files:
        assert (one.parent / f).read_bytes() == (two.parent / f).read_bytes(), f
    assert validate(two) == []
    # an existing cluster, by its address
    from distributed import LocalCluster

    three = tmp_path / "three" / "f.usda"
    three.parent.mkdir()
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        write_forest(recipe, three, thumbnail=False, scheduler=cluster.scheduler_address)
    for f in files:
        assert (one.parent / f).read_bytes() == (three.parent / f).read_bytes(), f


def test_an_unreachable_scheduler_is_named(tmp_path, runner, monkeypatch):
    from usdforest import cluster
    from usdforest.cli import app

    # a closed port is retried until the connect timeout (10 s in a build): 1 s here
    monkeypatch.setattr(
        cluster.connect, "__defaults__", (1.0, cluster.WORKER_TIMEOUT, cluster.CONNECT_GRACE)
    )

    p = tmp_path / "t.toml"
    p.write_text(default_recipe_path().read_text() + "\n[tiles]\nsize = 50\n", encoding="utf-8")
    out = tmp_path / "f.usda"
    r = runner.invoke(
        app, ["build", str(out), "-p", str(p), "-q", "--scheduler", "tcp://127.0.0.1:9"]
    )
    assert (
        r.exit_code == 2
        and "--scheduler tcp://127.0.0.1:9: no Dask scheduler answered within 1 s" in r.stderr
    )
    assert not out.exists() and not (tmp_path / "f_assets").exists()


def test_each_tile_has_the_ground_its_trees_stand_on(tmp_path):
    """A raster ground cut per tile: every tree on its own tile's ground mesh (a ray cast
    down that mesh alone, in the composed stage), the tiles' grounds together as wide as the
    untiled ground (region plus margin)."""
    import trimesh

    x = np.linspace(-5.0, 85.0, 46)
    y = np.linspace(55.0, -5.0, 31)
    gx, gy = np.meshgrid(x, y)
    np.save(tmp_path / "dem.npy", 0.1 * gx + 6.0 * np.exp(-((gx - 40) ** 2 + (gy - 25) ** 2) / 200))
    data = {
        "seed": 3,
        "region": {"bounds": [0.0, 0.0, 80.0, 50.0]},
        "intensity": {"kind": "constant", "value": 0.03},
        "species": {"paper-rule-1": {}},
        "forest": {"variants": 1, "colliders": "none"},
        "ground": {"kind": "raster", "file": "dem.npy", "bounds": [-5, -5, 85, 55]},
        "tiles": {"size": 30.0},
    }
    out = tmp_path / "g.usda"
    build = write_forest(parse_recipe(data, tmp_path, str(tmp_path / "g.toml")), out)
    assert build.n_tiles == 6 and validate(out) == []
    stage = Usd.Stage.Open(str(out))
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    checked = 0
    for tile in stage.GetPrimAtPath("/Forest/Tiles").GetChildren():
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(tile.GetPath().AppendPath("Ground/Mesh")))
        m = np.asarray(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
        pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=float) @ m[:3, :3] + m[3, :3]
        tri = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        lo, hi = np.minimum(lo, pts[:, :2].min(axis=0)), np.maximum(hi, pts[:, :2].max(axis=0))
        ground = trimesh.Trimesh(pts, tri, process=False)
        trees = {
            i: x for i, (x, _) in _trees_under(stage, tile.GetPath().AppendPath("Trees")).items()
        }
        origins = np.array([[x[0], x[1], 1e3] for x in trees.values()])
        hits, rays, _ = ground.ray.intersects_location(
            origins, np.tile([0, 0, -1.0], (len(origins), 1))
        )
        z = np.full(len(origins), np.nan)
        z[rays] = hits[:, 2]
        np.testing.assert_allclose(z, [x[2] for x in trees.values()], atol=1e-4)
        checked += len(trees)
    assert checked == build.n_trees
    np.testing.assert_allclose(lo, [-5, -5], atol=1e-9)
    np.testing.assert_allclose(hi, [85, 55], atol=1e-9)


def _trees_under(stage: Usd.Stage, path) -> dict:
    return {
        i: v
        for i, v in _trees(stage).items()
        if i
        in set(
            np.asarray(
                UsdGeom.PointInstancer(stage.GetPrimAtPath(path)).GetIdsAttr().Get()
            ).tolist()
        )
    }


def test_empty_tiles_keep_their_ground_and_hints_hold_it(tmp_path):
    """A clearing leaves tiles without trees: they still carry their ground (a robot drives
    across them), and every tile's extentsHint holds what it composes, ground included."""
    recipe = _recipe(
        tmp_path,
        intensity={
            "kind": "gaussian-mixture",
            "base": 0.03,
            "bumps": [{"x": 50.0, "y": 50.0, "sigma": 12.0, "peak": -0.2}],
        },
        tiles={"size": 20.0},
    )
    out = tmp_path / "c.usda"
    build = write_forest(recipe, out, thumbnail=False)
    stage = Usd.Stage.Open(str(out))
    tiles = stage.GetPrimAtPath("/Forest/Tiles").GetChildren()
    assert build.n_tiles == len(tiles) == 25
    empty = [t for t in tiles if not UsdGeom.PointInstancer(t.GetChild("Trees")).GetIdsAttr().Get()]
    assert empty, "the clearing should leave a tile without trees"
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render", "proxy"], True)
    boxes = []
    for t in tiles:
        assert t.GetChild("Ground").GetChild("Mesh").IsValid()
        lo, hi = (np.array(v) for v in UsdGeom.ModelAPI(t).GetExtentsHint())
        got = cache.ComputeUntransformedBound(t).ComputeAlignedRange()
        assert np.all(np.array(got.GetMin()) >= lo - 1e-4) and np.all(
            np.array(got.GetMax()) <= hi + 1e-4
        )
        shift = np.array(t.GetAttribute("xformOp:translate").Get())
        boxes.append((lo + shift, hi + shift))
    # the tiles' grounds cover the plot and its 5 m margin
    for x in np.linspace(-4.9, 104.9, 12):
        for y in np.linspace(-4.9, 104.9, 12):
            assert any(b[0][0] <= x <= b[1][0] and b[0][1] <= y <= b[1][1] for b in boxes), (x, y)


def test_a_failing_tile_task_is_an_error_and_leaves_nothing(tmp_path, monkeypatch):
    pytest.importorskip("distributed", reason="Dask tiles need dask.distributed (usdforest[dask])")
    from distributed import LocalCluster

    import usdforest.usd.landscape as landscape
    from usdforest.errors import UsdForestError

    def full_disk(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(landscape, "tile_task", full_disk)
    out = tmp_path / "f.usda"
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        with pytest.raises(UsdForestError, match=r"a tile task failed: OSError: .*No space left"):
            write_forest(
                _recipe(tmp_path, tiles={"size": 50.0}),
                out,
                thumbnail=False,
                scheduler=cluster.scheduler_address,
            )
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_tile_task_never_creates_its_folder(tmp_path):
    from usdforest.errors import UsdForestError
    from usdforest.usd.landscape import tile_task

    with pytest.raises(UsdForestError, match="a shared disk is needed"):
        tile_task(tmp_path / "gone", None, None)
    assert not (tmp_path / "gone").exists()


def test_dask_options_need_a_tiled_recipe(tmp_path, runner):
    from usdforest.cli import app

    r = runner.invoke(app, ["build", str(tmp_path / "f.usda"), "--workers", "2", "-q"])
    assert r.exit_code == 2 and "apply to a tiled recipe" in r.stderr


def _instances(stage: Usd.Stage) -> dict[int, tuple[np.ndarray, str]]:
    """Every composed tree by id: its whole instance transform in the world (position,
    turn and scale) and its prototype's name."""
    out = {}
    for p in stage.Traverse():
        if not p.IsA(UsdGeom.PointInstancer) or Usd.ModelAPI(p).GetKind() != "group":
            continue
        pi = UsdGeom.PointInstancer(p)
        xf = np.asarray(
            pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
        )
        w = np.asarray(UsdGeom.Xformable(p).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
        names = [t.name for t in pi.GetPrototypesRel().GetTargets()]
        idx = np.asarray(pi.GetProtoIndicesAttr().Get())
        for i, m, k in zip(np.asarray(pi.GetIdsAttr().Get()), xf @ w, idx, strict=True):
            out[int(i)] = (m, names[k])
    return out


def _csv_lines(folder) -> list[str]:
    """Every tree row of a forest's ground truth: ``trees.csv``, or its tiles' CSVs."""
    parts = sorted((folder / "tiles").glob("*.csv")) or [folder / "trees.csv"]
    return sorted(line for p in parts for line in p.read_text().splitlines()[1:])


def test_a_recipe_gives_the_same_trees_with_or_without_tiles(tmp_path):
    """Issue 25: one sampling scheme. An allometric stand over 2 x 2 cells of 250 m, with a
    hard core, built untiled and in tiles of 125 m (owning the trees in their boxes; an edge
    on the cells' edge) and of 250 m (a cell each, owning its trees): the same tree assets
    byte for byte (the size classes come from the whole stand), and every tree with the same
    id, the same prototype and the same transform (its size, and its turn away from
    neighbours that may stand in another tile), and the same row of ground truth."""
    base = """
seed = 5
[region]
bounds = [0, 0, 330, 290]
[intensity]
kind = "expression"
expr = "0.004 + 0.03 * exp(-((x - 250) ** 2 + (y - 240) ** 2) / 2000)"
[forest]
hard_core = 1.2
variants = 3
colliders = "none"
[species.pine]
preset = "scots-pine"
"""
    builds = {}
    for name, tiles in (
        ("flat", ""),
        ("t125", "[tiles]\nsize = 125\n"),
        ("t250", "[tiles]\nsize = 250\n"),
    ):
        (tmp_path / f"{name}.toml").write_text(base + tiles)
        out = tmp_path / f"{name}.usda"
        b = write_forest(read_recipe(tmp_path / f"{name}.toml"), out, thumbnail=False)
        builds[name] = (b, out)
    flat, _ = builds["flat"]
    assert flat.n_tiles == 0 and flat.n_trees > 400 and len(flat.prototypes) == 3
    ref = _instances(Usd.Stage.Open(str(builds["flat"][1])))
    assert sorted(ref) == list(range(flat.n_trees))
    ref_csv = _csv_lines(tmp_path / "flat_assets")
    assert len(ref_csv) == flat.n_trees
    for name in ("t125", "t250"):
        b, out = builds[name]
        assert b.n_tiles > 1 and b.trees_by_species == flat.trees_by_species
        assert validate(out) == []
        for tree in (tmp_path / "flat_assets" / "trees").iterdir():
            assert (
                tmp_path / f"{name}_assets" / "trees" / tree.name
            ).read_bytes() == tree.read_bytes()
        got = _instances(Usd.Stage.Open(str(out)))
        assert sorted(got) == sorted(ref)
        for i, (m, proto) in ref.items():
            assert got[i][1] == proto
            np.testing.assert_allclose(got[i][0], m, atol=1e-4)
        assert _csv_lines(tmp_path / f"{name}_assets") == ref_csv
    # neighbours across tile edges press crowns: some trees are turned away from them
    yaw = np.degrees(np.arctan2(*np.array([m[0, 1::-1] for m, _ in ref.values()]).T))
    assert len(set(np.round(yaw, 3))) > 0.9 * len(ref)

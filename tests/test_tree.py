"""Tree assets: composed USD read back with pxr, validation, determinism, structure."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdShade

from usdforest.cli import app
from usdforest.species import PRESETS, get_species
from usdforest.usd.stats import stage_info
from usdforest.usd.tree import write_tree
from usdforest.validate import validate

TREES = [n for n, s in PRESETS.items() if s.kind == "tree"]


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict[str, tuple[Path, object]]:
    root = tmp_path_factory.mktemp("trees")
    return {
        n: (root / f"{n}.usda", write_tree(get_species(n), root / f"{n}.usda", seed=3))
        for n in TREES
    }


@pytest.mark.parametrize(("k", "branches"), [(1, 8), (2, 12), (3, 16)])
def test_paper_branch_counts_from_composed_usd(built, k, branches):
    path, _ = built[f"paper-rule-{k}"]
    info = stage_info(path)
    assert info["branches_by_order"]["0"] == 1
    assert info["branches_by_order"]["1"] == branches
    stage = Usd.Stage.Open(str(path))
    orders = [
        p.GetAttribute("usdforest:order").Get()
        for p in stage.GetPrimAtPath("/Tree/Branches").GetChildren()
    ]
    axes = {
        p.GetAttribute("usdforest:axis").Get()
        for p in stage.GetPrimAtPath("/Tree/Branches").GetChildren()
        if p.GetAttribute("usdforest:order").Get() == 1
    }
    assert len(axes) == branches and orders.count(1) >= branches


@pytest.mark.parametrize("name", TREES)
def test_validates_clean(built, name):
    path, _ = built[name]
    assert validate(path) == []


@pytest.mark.parametrize("name", TREES)
def test_structure_model_hierarchy_and_materials(built, name):
    path, b = built[name]
    stage = Usd.Stage.Open(str(path))
    tree = stage.GetDefaultPrim()
    assert tree.GetPath() == "/Tree" and tree.IsModel() and tree.IsComponent()
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1
    trunk = stage.GetPrimAtPath("/Tree/Trunk")
    assert trunk.GetTypeName() == "Xform" and Usd.ModelAPI(trunk).GetKind() == "subcomponent"
    assert trunk.IsInstance()
    assert trunk.GetAttribute("usdforest:order").Get() == 0
    data = tree.GetCustomDataByKey("usdforest")
    assert data["species"] == name and data["seed"] == b.grown.seed
    assert data["lsystem"]["leaves"] == b.placement.n_leaves
    assert list(tree.GetAttribute("semantics:labels:species").Get()) == [name]
    # a branch's composed mesh is bound to the tree's bark, not the template's own material
    some = next(iter(stage.GetPrimAtPath("/Tree/Branches").GetChildren()))
    mesh = some.GetChild("Mesh")
    assert mesh.IsInstanceProxy() and mesh.IsA(UsdGeom.Mesh)
    mat, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    assert mat.GetPath() == "/Tree/Looks/Bark"
    leaves = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Tree/Leaves"))
    proto_mesh = stage.GetPrimAtPath(leaves.GetPrototypesRel().GetTargets()[0]).GetChild("Mesh")
    mat, _ = UsdShade.MaterialBindingAPI(proto_mesh).ComputeBoundMaterial()
    assert mat.GetPath() == "/Tree/Looks/Leaf"


@pytest.mark.parametrize("name", TREES)
def test_leaf_instancer_arrays(built, name):
    path, b = built[name]
    stage = Usd.Stage.Open(str(path))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Tree/Leaves"))
    n = b.placement.n_leaves
    assert len(pi.GetPositionsAttr().Get()) == n
    ids = np.asarray(pi.GetIdsAttr().Get())
    assert ids.dtype == np.int64 and np.array_equal(ids, np.arange(n))
    q = np.array([[x.GetReal(), *x.GetImaginary()] for x in pi.GetOrientationsAttr().Get()])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=2e-3)
    assert pi.GetOrientationsAttr().GetTypeName() == "quath[]"
    assert stage_info(path)["leaves"] == n
    # the instancer's authored extent contains every instance's computed bounds
    authored = np.array(pi.GetExtentAttr().Get())
    computed = np.array(pi.ComputeExtentAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default()))
    assert np.all(authored[0] <= computed[0] + 1e-4) and np.all(authored[1] >= computed[1] - 1e-4)


@pytest.mark.parametrize("name", TREES)
def test_extents_hint_contains_composed_geometry(built, name):
    path, _ = built[name]
    stage = Usd.Stage.Open(str(path))
    tree = stage.GetDefaultPrim()
    hint = np.array(tree.GetAttribute("extentsHint").Get())
    box = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"]).ComputeWorldBound(tree)
    r = box.ComputeAlignedRange()
    lo, hi = np.array(r.GetMin()), np.array(r.GetMax())
    tol = 1e-4 * (1 + np.abs(hint).max())
    assert np.all(hint[0] <= lo + tol) and np.all(hint[1] >= hi - tol)
    # and it is tight: the trunk touches the ground, the tree is as tall as its skeleton
    assert hint[0, 2] == pytest.approx(lo[2], abs=0.05)
    assert hint[1, 2] == pytest.approx(hi[2], abs=0.05)


@pytest.mark.parametrize("name", TREES)
def test_branches_start_on_their_parent_and_leaves_on_young_wood(built, name):
    _, b = built[name]
    p, sk = b.placement, b.grown.skeleton
    child = np.flatnonzero(p.parent >= 0)
    par = p.parent[child]
    base, pbase = p.translate[child], p.translate[par]
    rot = np.array(
        [Gf.Matrix3d(Gf.Rotation(Gf.Quatd(q[3], *q[:3]))).GetTranspose() for q in p.orient[par]]
    )
    paxis = rot[:, :, 2]  # parent's +Z (growth axis) in tree space
    t = np.clip(np.sum((base - pbase) * paxis, axis=1), 0, p.length[par])
    dist = np.linalg.norm(base - (pbase + paxis * t[:, None]), axis=1)
    # within the parent's radius of its axis (wood runs are straight chords of the skeleton)
    assert np.all(dist <= np.maximum(p.radius[par], 0.05 * p.length[par]) + 1e-6)
    assert np.all(p.radius[child] <= p.radius[par] + 1e-9)
    # leaves: within the twig's radius of a terminal segment (or its base node)
    seg = p.leaf_segment
    terminal = sk.is_terminal()
    a, e = sk.start[seg], sk.end[seg]
    d = e - a
    u = np.clip(np.sum((p.leaf_position - a) * d, axis=1) / np.sum(d * d, axis=1), 0, 1)
    gap = np.linalg.norm(p.leaf_position - (a + d * u[:, None]), axis=1)
    assert np.all(gap <= sk.radius[seg] + 1e-6)
    node_of_terminal = np.zeros(sk.n_segments, dtype=bool)
    kids = np.flatnonzero(terminal & (sk.parent >= 0))
    node_of_terminal[sk.parent[kids]] = True
    at_node = np.isclose(u, 1.0)
    assert np.all(terminal[seg] | (node_of_terminal[seg] & at_node))


def test_composed_leaf_count_equals_leaf_sites_with_one_leaf_per_site(tmp_path):
    sp = get_species("paper-rule-2")
    sp = replace(sp, geometry=replace(sp.geometry, leaves_per_site=1.0))
    b = write_tree(sp, tmp_path / "t.usdc", seed=1)
    assert stage_info(tmp_path / "t.usdc")["leaves"] == b.grown.skeleton.n_leaves > 100


def test_same_seed_same_bytes_other_seed_other_tree(tmp_path):
    sp = get_species("broadleaf")
    write_tree(sp, tmp_path / "a" / "t.usda", seed=5)
    write_tree(sp, tmp_path / "b" / "t.usda", seed=5)
    write_tree(sp, tmp_path / "c" / "t.usda", seed=6)
    write_tree(sp, tmp_path / "d" / "t.usda", seed=5, variant=1)
    a, b, c, d = ((tmp_path / x / "t.usda").read_bytes() for x in "abcd")
    assert a == b and a != c and a != d
    for x in ("a", "b"):
        names = sorted(p.name for p in (tmp_path / x / "t_assets" / "templates").iterdir())
        assert names == sorted(
            p.name for p in (tmp_path / "a" / "t_assets" / "templates").iterdir()
        )


def test_output_folder_is_relocatable(tmp_path):
    write_tree(get_species("pine"), tmp_path / "src" / "pine.usdc", seed=2)
    shutil.move(tmp_path / "src", tmp_path / "moved")
    assert validate(tmp_path / "moved" / "pine.usdc") == []
    assert stage_info(tmp_path / "moved" / "pine.usdc")["meshes"] > 1000


def test_tree_cli_and_overwrite_refusal(tmp_path, runner):
    out = tmp_path / "t.usda"
    r = runner.invoke(app, ["tree", str(out), "--species", "paper-rule-1", "--json"])
    assert r.exit_code == 0, r.output
    stats = json.loads(r.stdout)
    assert stats["branches_by_order"]["1"] == 8
    before = out.read_bytes()
    r = runner.invoke(app, ["tree", str(out), "--species", "pine"])
    assert r.exit_code == 2 and "--force" in r.stderr and out.read_bytes() == before
    r = runner.invoke(app, ["tree", str(out), "--species", "pine", "--force"])
    assert r.exit_code == 0 and out.read_bytes() != before
    r = runner.invoke(app, ["validate", str(out)])
    assert r.exit_code == 0 and "clean" in r.stdout
    r = runner.invoke(app, ["info", str(out), "--json"])
    assert json.loads(r.stdout)["trees"] == 1


def test_validate_reports_problems_with_exit_1(tmp_path, runner):
    stage = Usd.Stage.CreateNew(str(tmp_path / "bad.usda"))
    UsdGeom.Mesh.Define(stage, "/M").CreatePointsAttr([(0, 0, 0), (1, 0, 0), (float("nan"), 0, 0)])
    stage.Save()
    r = runner.invoke(app, ["validate", str(tmp_path / "bad.usda"), "--json"])
    assert r.exit_code == 1
    data = json.loads(r.stdout)
    sources = {f["source"] for f in data["findings"]}
    assert {"usdforest:extent", "usdforest:finite", "MissingDefaultPrim"} <= sources
    r = runner.invoke(app, ["validate", str(tmp_path / "missing.usda")])
    assert r.exit_code == 2 and "no such file" in r.stderr


PIPELINE = """
seed = 1
[species.tall_pine]
preset = "pine"
iterations = 12
[species.tall_pine.geometry]
leaves_per_site = 2
[species.weed]
axiom = "F"
rules = ["F -> F[+FL][-FL]F"]
iterations = 3
[species.weed.turtle]
angle = 30.0
radius = 0.03
"""


def test_tree_from_pipeline_species(tmp_path, runner):
    p = tmp_path / "p.toml"
    p.write_text(PIPELINE)
    r = runner.invoke(app, ["tree", str(tmp_path / "a.usda"), "-p", str(p), "-s", "weed", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["species"] == "weed"
    assert validate(tmp_path / "a.usda") == []
    r = runner.invoke(app, ["tree", str(tmp_path / "b.usda"), "-p", str(p), "--json"])
    assert json.loads(r.stdout)["species"] == "tall_pine"


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("[species.x]\npreset = 'oak'\n", "species.x.preset: unknown species 'oak'"),
        ("[species.x]\npreset = 'pine'\ncolour = 1\n", "species.x: unknown key 'colour'"),
        (
            "[species.x]\npreset = 'pine'\n[species.x.geometry]\nleaf_size = -1\n",
            "species.x.geometry.leaf_size: must be > 0",
        ),
        (
            "[species.x]\npreset = 'pine'\n[species.x.geometry]\nleaf_sise = 1\n",
            "species.x.geometry: unknown key 'leaf_sise'",
        ),
        (
            "[species.x]\npreset = 'pine'\n[species.x.turtle]\nangle = 'big'\n",
            "species.x.turtle.angle: expected a number",
        ),
        ("[species.x]\naxiom = 'F'\nrules = ['F -> F[']\n", "unbalanced brackets"),
        ("[species.x]\naxiom = 'F'\n", "needs both 'axiom' and 'rules'"),
        ("[species.x]\npreset = 'pine'\niterations = 1000\n", "iterations: 1000 is not between"),
        ("seed = 1\n", "no [species.NAME] tables"),
    ],
)
def test_bad_pipeline_species(tmp_path, runner, text, fragment):
    p = tmp_path / "p.toml"
    p.write_text(text)
    r = runner.invoke(app, ["tree", str(tmp_path / "t.usda"), "-p", str(p)])
    assert r.exit_code == 2
    assert fragment in r.stderr and str(p) in r.stderr
    assert not (tmp_path / "t.usda").exists() and not (tmp_path / "t_assets").exists()


def test_species_from_extracted_profile(cad_samples, tmp_path, runner):
    ex = tmp_path / "tree2"
    assert (
        runner.invoke(
            app, ["template", "extract", str(cad_samples / "Tree_2.obj"), "-o", str(ex)]
        ).exit_code
        == 0
    )
    p = tmp_path / "p.toml"
    p.write_text('[species.tree2]\nprofile = "tree2/profile.toml"\n')
    r = runner.invoke(app, ["tree", str(tmp_path / "t.usda"), "-p", str(p), "--json"])
    assert r.exit_code == 0, r.output
    stats = json.loads(r.stdout)
    assert stats["branches_by_order"]["1"] == 6  # the model's six branches
    assert stats["height"] == pytest.approx(4.93, abs=0.1)
    assert validate(tmp_path / "t.usda") == []
    used = stage_info(tmp_path / "t.usda")["layers"]
    assert "t_assets/templates/trunk.usdc" in used and "t_assets/templates/branch.usdc" in used

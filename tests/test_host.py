"""Forests in other people's stages: `usdforest wrap` writes a Y-up centimetre (or any) host
that composes the forest upright and to scale, and `validate` checks the assets a host
composes instead of refusing the host's own units."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from usdforest.cli import app
from usdforest.recipe import read_recipe, shipped_recipes
from usdforest.usd.forest import write_forest
from usdforest.usd.validate import errors, validate


@pytest.fixture(scope="module")
def forest(tmp_path_factory):
    out = tmp_path_factory.mktemp("forest") / "stand.usda"
    write_forest(read_recipe(shipped_recipes()["paper-two-tree-stand"]), out, thumbnail=False)
    return out


def _box(stage: Usd.Stage, path: str) -> np.ndarray:
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"])
    r = cache.ComputeWorldBound(stage.GetPrimAtPath(path)).ComputeAlignedRange()
    return np.array([r.GetMin(), r.GetMax()])


@pytest.mark.parametrize(("up", "units", "scale"), [("Y", "cm", 100.0), ("Z", "mm", 1000.0)])
def test_a_wrapped_forest_stands_upright_and_to_scale(tmp_path, runner, forest, up, units, scale):
    host = tmp_path / "host.usda"
    r = runner.invoke(app, ["wrap", str(forest), "-o", str(host), "--up", up, "--units", units])
    assert r.exit_code == 0, r.output
    stage = Usd.Stage.Open(str(host))
    assert UsdGeom.GetStageUpAxis(stage) == up
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx({"cm": 0.01, "mm": 0.001}[units])
    assert stage.GetDefaultPrim().GetPath() == "/World"
    own = _box(Usd.Stage.Open(str(forest)), "/Forest")
    got = _box(stage, "/World/Forest")
    if up == "Y":  # (x, y, z) -> (x, z, -y): up is +Y, north is -Z
        want = np.array([[own[0, 0], own[0, 2], -own[1, 1]], [own[1, 0], own[1, 2], -own[0, 1]]])
    else:
        want = own
    np.testing.assert_allclose(got, want * scale, rtol=1e-5, atol=1e-3 * scale)
    height = got[1, 1 if up == "Y" else 2] - got[0, 1 if up == "Y" else 2]
    assert height == pytest.approx((own[1, 2] - own[0, 2]) * scale, rel=1e-5)
    assert errors(validate(host)) == []
    assert runner.invoke(app, ["validate", str(host)]).exit_code == 0


def _bare_host(path, forest, up: str, mpu: float, transform: Gf.Matrix4d | None = None):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    world = UsdGeom.Xform.Define(stage, "/World")
    placed = UsdGeom.Xform.Define(stage, "/World/Forest")
    if transform is not None:
        placed.AddTransformOp().Set(transform)
    placed.GetPrim().GetReferences().AddReference(str(forest))
    stage.SetDefaultPrim(world.GetPrim())
    stage.Save()
    return path


def test_validate_names_a_forest_referenced_without_the_correction(tmp_path, runner, forest):
    small = _bare_host(tmp_path / "small.usda", forest, "Y", 0.01)
    found = [f for f in validate(small) if f.source == "usdforest:placement"]
    assert [(f.path, f.severity) for f in found] == [("/World/Forest", "error")]
    assert "is 0.01x its size" in found[0].message and "usdforest wrap" in found[0].message
    lying = _bare_host(tmp_path / "lying.usda", forest, "Y", 1.0)
    (msg,) = [f.message for f in validate(lying) if f.source == "usdforest:placement"]
    assert msg.startswith("is tilted 90.0 degrees from the stage's up axis Y")
    squashed = _bare_host(
        tmp_path / "squashed.usda", forest, "Z", 1.0, Gf.Matrix4d().SetScale(Gf.Vec3d(1, 1, 2))
    )
    (msg,) = [f.message for f in validate(squashed) if f.source == "usdforest:placement"]
    assert msg == "is not scaled uniformly"
    r = runner.invoke(app, ["validate", str(small)])
    assert r.exit_code == 1 and "placement" in r.stdout
    # a usdforest asset itself must still be Z-up metres
    assert errors(validate(forest)) == []


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--up", "X"], "--up: 'X' is not Y or Z"),
        (["--units", "furlong"], "--units: 'furlong' is not one of m, dm, cm, mm, in, ft"),
        (["--name", "1st"], "--name: '1st' is not a valid prim name"),
    ],
)
def test_wrap_refuses_bad_options(tmp_path, runner, forest, args, fragment):
    host = tmp_path / "h.usda"
    r = runner.invoke(app, ["wrap", str(forest), "-o", str(host), *args])
    assert r.exit_code == 2 and fragment in r.stderr, r.output
    assert not host.exists()


def test_wrap_refuses_what_is_not_a_usdforest_asset_and_existing_hosts(tmp_path, runner, forest):
    host = tmp_path / "h.usda"
    yup = _bare_host(tmp_path / "yup.usda", forest, "Y", 0.01)
    r = runner.invoke(app, ["wrap", str(yup), "-o", str(host)])
    assert r.exit_code == 2 and "is not Z-up in metres" in r.stderr
    r = runner.invoke(app, ["wrap", str(tmp_path / "none.usda"), "-o", str(host)])
    assert r.exit_code == 2 and "none.usda: no such file" in r.stderr
    assert not host.exists()
    assert runner.invoke(app, ["wrap", str(forest), "-o", str(host)]).exit_code == 0
    r = runner.invoke(app, ["wrap", str(forest), "-o", str(host), "--up", "Z"])
    assert r.exit_code == 2 and "exists; pass --force" in r.stderr
    assert runner.invoke(app, ["wrap", str(forest), "-o", str(host), "--force"]).exit_code == 0


def test_wrap_never_replaces_its_asset_or_a_layer_it_composes(tmp_path, runner, forest):
    """`wrap a.usda -o a.usda --force` wrote a host that referenced itself over its input;
    a host written over one of the forest's own layers (here: through a symbolic link to
    it) would break the forest. Both are refused, whatever --force says, and nothing
    changes."""
    import shutil

    copy = tmp_path / "stand.usda"
    shutil.copy(forest, copy)
    shutil.copytree(forest.parent / "stand_assets", tmp_path / "stand_assets")
    before = copy.read_bytes()
    r = runner.invoke(app, ["wrap", str(copy), "-o", str(copy), "--force"])
    assert r.exit_code == 2, r.output
    assert f"{copy}: is an input of this command" in r.stderr
    assert copy.read_bytes() == before
    inner = sorted((tmp_path / "stand_assets").rglob("*.usd*"))[0]
    inner_bytes = inner.read_bytes()
    link = tmp_path / "host.usda"
    link.symlink_to(inner)
    r = runner.invoke(app, ["wrap", str(copy), "-o", str(link), "--force"])
    assert r.exit_code == 2 and "is an input of this command" in r.stderr, r.output
    assert inner.read_bytes() == inner_bytes
    assert errors(validate(copy)) == []
    assert sorted(x.name for x in tmp_path.iterdir()) == ["host.usda", "stand.usda", "stand_assets"]


@pytest.mark.parametrize(
    ("suffix", "content", "fragment"),
    [
        (".txt", b"hello\n", "Cannot determine file format"),
        (".png", b"\x89PNG\r\n\x1a\n" + bytes(range(256)), "Cannot determine file format"),
        (".usda", bytes(range(256)) * 8, "is not a valid usda layer"),
        (".usdc", None, "crate file corrupt, possibly truncated"),
    ],
    ids=["text", "png", "random", "truncated-crate"],
)
def test_wrap_names_a_file_that_is_no_usd_layer(
    tmp_path, runner, forest, suffix, content, fragment
):
    if content is None:  # the first half of the forest's largest crate file
        crate = max(
            (forest.parent / "stand_assets").rglob("*.usdc"), key=lambda p: p.stat().st_size
        )
        content = crate.read_bytes()[: crate.stat().st_size // 2]
    bad = tmp_path / f"bad{suffix}"
    bad.write_bytes(content)
    host = tmp_path / "h.usda"
    r = runner.invoke(app, ["wrap", str(bad), "-o", str(host)])
    assert r.exit_code == 2, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {bad}: not a USD layer"), r.stderr
    assert fragment in lines[0], lines[0]
    assert not host.exists()

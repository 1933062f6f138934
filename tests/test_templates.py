"""Template layers: structure read back with pxr, validation, the shipped library."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdShade

from usdforest.cad.library import read_manifest, template_dir
from usdforest.cli import app
from usdforest.errors import RecipeError
from usdforest.usd.template import read_template
from usdforest.usd.validate import validate

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "pipelines" / "templates.toml"
SHIPPED = sorted(template_dir().glob("*.usdc"))


def test_library_has_the_starter_parts():
    names = {p.stem for p in SHIPPED}
    assert {
        "trunk",
        "branch_straight",
        "branch_curved_a",
        "branch_curved_b",
        "twig",
        "leaf_broadleaf",
        "leaf_beech",
        "leaf_oak",
        "leaf_birch",
        "needle_fascicle",
    } <= names
    parts = {read_template(p).name: read_template(p).part for p in SHIPPED}
    assert parts["trunk"] == "trunk" and parts["twig"] == "twig"
    assert parts["leaf_broadleaf"] == parts["needle_fascicle"] == parts["leaf_oak"] == "leaf"


@pytest.mark.parametrize("name", ["branch_curved_a", "branch_curved_b"])
def test_thickened_variants_keep_the_bend(name):
    # NAME_xK: every cross-section K times as wide about the centreline, the same centreline
    base = read_template(template_dir() / f"{name}.usdc")
    for k in (2, 4, 8):
        v = read_template(template_dir() / f"{name}_x{k}.usdc")
        assert v.part == "branch"
        assert v.base_radius == pytest.approx(k * base.base_radius, rel=0.02)
        assert v.tip_radius == pytest.approx(k * base.tip_radius, rel=0.02)
        # the bend off the chord (placement shears the tip onto the axis): slices widened
        # horizontally tilt the measured centreline a little, 1-25 % here
        u = np.linspace(0.0, 1.0, len(base.centreline))[:, None]
        bend = [np.abs(t.centreline - u * t.centreline[-1]).max() for t in (base, v)]
        assert 0.98 <= bend[1] / bend[0] <= 1.3
        assert np.ptp(v.hull[:, 2]) == pytest.approx(np.ptp(base.hull[:, 2]), rel=1e-3)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_template_structure_and_validation(path):
    assert validate(path) == []
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Z"
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    root = stage.GetDefaultPrim()
    assert root.GetPath() == Sdf.Path("/Template") and root.GetTypeName() == "Xform"
    assert Usd.ModelAPI(root).GetKind() == "component"
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Template/Mesh"))
    pts = np.array(mesh.GetPointsAttr().Get())
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
    idx = np.array(mesh.GetFaceVertexIndicesAttr().Get())
    assert np.all(counts == 3) and idx.size == 3 * counts.size and idx.max() < len(pts)
    normals = np.array(mesh.GetNormalsAttr().Get())
    assert normals.shape == pts.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    ext = np.array(mesh.GetExtentAttr().Get())
    np.testing.assert_allclose(ext, [pts.min(axis=0), pts.max(axis=0)], atol=1e-6)
    data = root.GetCustomDataByKey("usdforest")
    assert data["measurements"]["triangles"] == counts.size
    # unit length along the part's axis
    axis = 0 if data["part"] == "leaf" else 2
    assert np.ptp(pts[:, axis]) == pytest.approx(1.0, abs=1e-6)
    mat, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert mat and mat.GetSurfaceOutput().HasConnectedSource()
    label = mesh.GetPrim().GetAttribute("semantics:labels:class").Get()
    classes = {
        "leaf": "leaf",
        "trunk": "trunk",
        "deadwood": "dead_wood",
        "groundcover": "ground_vegetation",
    }
    expected = classes.get(data["part"], "branch")
    assert list(label) == [expected]


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_texture_coordinates_and_sensor_material(path):
    """Bark: v is the corner's height, u goes once round the axis with no triangle spanning
    the seam. Leaves: u along the blade, v across it, both over [0, 1]. Materials carry the
    SimReady non-visual base RTX lidar and radar read; leaves are double-sided."""
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Template/Mesh"))
    pts = np.array(mesh.GetPointsAttr().Get(), dtype=float)
    idx = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetTypeName() == "texCoord2f[]"
    assert st.IsIndexed()
    uv = np.array(st.ComputeFlattened(), dtype=float)
    assert len(np.unique(np.array(st.Get()), axis=0)) == len(st.Get())  # each value once
    part = read_template(path).part
    mat, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    base = mat.GetPrim().GetAttribute("omni:simready:nonvisual:base").Get()
    if part in ("leaf", "groundcover"):  # a patch's u, v: its footprint's x, y
        assert st.GetInterpolation() == "vertex" and uv.shape == (len(pts), 2)
        assert uv.min() >= 0.0 and uv.max() <= 1.0
        assert np.corrcoef(uv[:, 0], pts[:, 0])[0, 1] > 0.999
        assert np.corrcoef(uv[:, 1], pts[:, 1])[0, 1] > 0.999
        assert base == "leaf_grass" and mesh.GetDoubleSidedAttr().Get()
        return
    assert st.GetInterpolation() == "faceVarying" and uv.shape == (idx.size, 2)
    corners = pts[idx.ravel()]
    np.testing.assert_allclose(uv[:, 1], np.clip(corners[:, 2], 0, 1), atol=2e-6)
    u = uv[:, 0].reshape(-1, 3)
    side = np.all(np.abs(corners[:, 2].reshape(-1, 3) - 0.5) < 0.48, axis=1)  # not end caps
    assert np.ptp(u[side], axis=1).max() < 0.5
    assert 0.85 < np.ptp(u) < 1.5  # once round (the seam's triangles reach past 1)
    assert base == "bark"
    if "curved" in path.stem or path.stem.startswith("deadwood_branch"):
        return  # its rings are not level (a bent or crooked branch), so a level slice is no ring
    # u increases counter-clockwise: on a ring near mid-height it follows atan2 about the
    # ring's centre (an independent centre: the mean of the ring's points)
    z0 = corners[np.argmin(np.abs(corners[:, 2] - 0.5)), 2]
    ring = np.abs(corners[:, 2] - z0) < 3e-3
    assert len(np.unique(idx.ravel()[ring])) >= 6
    c = pts[np.unique(idx.ravel()[ring]), :2].mean(axis=0)
    ang = np.mod(np.arctan2(*(corners[ring, :2] - c).T[::-1]) / (2 * np.pi), 1.0)
    d = np.abs(np.mod(uv[ring, 0] - ang + 0.5, 1.0) - 0.5)
    assert np.median(d) < 0.03


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_templates_are_built_from_the_committed_cad(path):
    prov = read_template(path)
    stage = Usd.Stage.Open(str(path))
    data = stage.GetDefaultPrim().GetCustomDataByKey("usdforest")
    source = template_dir() / "cad" / data["provenance"]["source"]
    assert hashlib.sha256(source.read_bytes()).hexdigest() == data["provenance"]["sha256"]
    assert prov.measurements["length"] > 0


def test_manifest_rebuild_is_byte_identical(tmp_path):
    manifest = read_manifest(MANIFEST)
    # 16 tree parts, 16 dead-wood pieces, 4 ground-vegetation patches
    assert len(manifest.templates) == 39
    from usdforest.cad.library import build_manifest

    a = build_manifest(manifest, tmp_path / "a")
    b = build_manifest(manifest, tmp_path / "b")
    for pa, pb in zip(a, b, strict=True):
        assert pa.read_bytes() == pb.read_bytes()
        shipped = template_dir() / pa.name
        assert pa.read_bytes() == shipped.read_bytes(), f"{shipped} is out of date"


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    line = next((ln for ln in text.splitlines() if ln.startswith("flags")), "")
    return set(line.split(":", 1)[-1].split())


# an OpenBLAS kernel forced on a CPU without its instructions would crash the interpreter
KERNEL_NEEDS = {"Prescott": "pni", "Haswell": "avx2", "SkylakeX": "avx512f"}  # pni: SSE3


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="OpenBLAS x86 kernels")
@pytest.mark.parametrize("kernel", list(KERNEL_NEEDS))
def test_rebuild_is_byte_identical_with_other_blas_kernels(tmp_path, kernel):
    """Different OpenBLAS kernels change eigenvectors and sums in their last bits; the stored
    (rounded) templates must not change."""
    if KERNEL_NEEDS[kernel] not in _cpu_flags():
        pytest.skip(f"this CPU lacks {KERNEL_NEEDS[kernel]} for the {kernel} kernel")
    env = {**os.environ, "OPENBLAS_CORETYPE": kernel}
    env.pop("OPENBLAS_L2_SIZE", None)
    out = tmp_path / kernel
    r = subprocess.run(
        [sys.executable, "-m", "usdforest.cli", "template", "build", str(MANIFEST), "-o", str(out)],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    built = sorted(out.glob("*.usdc"))
    assert len(built) == 39
    for p in built:
        assert p.read_bytes() == (template_dir() / p.name).read_bytes(), f"{p.name} ({kernel})"


def test_stored_measurements_are_rounded():
    for p in SHIPPED:
        layer = Sdf.Layer.FindOrOpen(str(p))
        data = layer.GetPrimAtPath("/Template").customData["usdforest"]
        for k, v in data["measurements"].items():
            if isinstance(v, float):
                assert float(f"{v:.7g}") == v, (p.name, k, v)
        assert float(f"{data['normalisedBaseRadius']:.7g}") == data["normalisedBaseRadius"]


def test_template_build_cli(tmp_path, runner):
    r = runner.invoke(app, ["template", "build", str(MANIFEST), "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert len(list(tmp_path.glob("*.usdc"))) == 39
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        (
            'outptu = "x"\n[[template]]\nname="a"\nsource="a.stl"\npart="leaf"\n',
            "unknown key 'outptu'",
        ),
        ('[[template]]\nname="a"\nsource="a.stl"\npart="root"\n', "template[0].part: 'root'"),
        (
            '[[template]]\nname="a"\nsource="a.stl"\npart="leaf"\ncolour=[1,0,0]\n',
            "unknown key 'colour'",
        ),
        (
            '[[template]]\nname="a"\nsource="a.stl"\npart="leaf"\ncolor=[2,0,0]\n',
            "template[0].color",
        ),
        (
            '[[template]]\nname="a"\npart="leaf"\n',
            "template[0].source: expected a non-empty string",
        ),
        ('[[template]]\nname="a"\nsource="a.stl"\npart="leaf"\nunits="yd"\n', "units: 'yd'"),
        (
            '[[template]]\nname="a"\nsource="a.stl"\npart="branch"\nthicken=0.5\n',
            "template[0].thicken: expected a number from 1 to 16",
        ),
        (
            '[[template]]\nname="a"\nsource="a.stl"\npart="leaf"\nthicken=2\n',
            "only a branch is thickened",
        ),
        ("template = [", "not valid TOML"),
        ('output="."\n', "template: expected a non-empty array of tables"),
    ],
)
def test_manifest_errors_name_the_key(tmp_path, text, fragment):
    p = tmp_path / "m.toml"
    p.write_text(text)
    with pytest.raises(RecipeError) as exc:
        read_manifest(p)
    assert fragment in str(exc.value) and str(p) in str(exc.value)


def test_import_writes_a_valid_layer_and_refuses_overwrite(tmp_path, runner):
    src = template_dir() / "cad" / "twig.stl"
    out = tmp_path / "twig.usdc"
    r = runner.invoke(
        app,
        [
            "template",
            "import",
            str(src),
            "--part",
            "twig",
            "-o",
            str(out),
            "--units",
            "m",
            "--up",
            "Z",
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    assert info["measurements"]["length"] == pytest.approx(0.3, rel=1e-3)
    assert validate(out) == []
    before = out.read_bytes()
    r = runner.invoke(app, ["template", "import", str(src), "--part", "leaf", "-o", str(out)])
    assert r.exit_code == 2 and "--force" in r.stderr
    assert out.read_bytes() == before


def test_template_list_cli(runner):
    r = runner.invoke(app, ["template", "list", "--json"])
    rows = json.loads(r.stdout)
    assert {row["name"] for row in rows} >= {"trunk", "leaf_broadleaf"}


def test_templates_folder_is_self_contained_when_copied(tmp_path):
    # template layers reference nothing outside themselves
    for p in SHIPPED:
        shutil.copy(p, tmp_path / p.name)
        layer = Sdf.Layer.FindOrOpen(str(tmp_path / p.name))
        assert not layer.GetExternalReferences()


def test_a_template_is_read_once_until_its_file_changes(tmp_path, monkeypatch):
    import usdforest.usd.template as template

    path = tmp_path / "t.usdc"
    shutil.copyfile(template_dir() / "trunk.usdc", path)
    reads = []
    real = template._read_template
    monkeypatch.setattr(template, "_read_template", lambda p: reads.append(p) or real(p))
    first = read_template(path)
    assert read_template(path) is first and len(reads) == 1
    # the same file by another spelling of its path: the same reading, under that path
    other = read_template(tmp_path / "." / "t.usdc")
    assert other.path == tmp_path / "." / "t.usdc" and np.array_equal(other.hull, first.hull)
    assert len(reads) == 1
    # replaced by another template: read again
    shutil.copyfile(template_dir() / "twig.usdc", path)
    os.utime(path, ns=(0, path.stat().st_mtime_ns + 10**9))
    assert read_template(path).name == "twig" and len(reads) == 2

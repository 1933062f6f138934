"""CAD import: formats, units, up axis, normalised frames, measurements and bad input."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom

from usdforest.cad.library import template_dir
from usdforest.cad.parts import import_part, read_cad
from usdforest.cli import app
from usdforest.errors import CADError

CAD = template_dir() / "cad"


def cylinder(path: Path, *, scale: float = 1.0, along_y: bool = False, fmt: str | None = None):
    """A 1.2 m tall cylinder of radius 0.05 m standing on the origin, in the file's units."""
    m = trimesh.creation.cylinder(radius=0.05, height=1.2, sections=24)
    m.apply_translation([0, 0, 0.6])
    if along_y:
        m.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, [1, 0, 0]))
    m.apply_scale(scale)
    m.export(path, file_type=fmt)
    return m


@pytest.mark.parametrize(
    ("name", "fmt"),
    [("c.stl", None), ("c.stl", "stl_ascii"), ("c.obj", None), ("c.ply", None), ("c.glb", None)],
)
def test_known_mesh_round_trips_every_format(tmp_path, name, fmt):
    src = cylinder(tmp_path / name, fmt=fmt)
    raw = read_cad(tmp_path / name)
    assert raw.n_triangles == len(src.faces) == 24 * 4
    t = import_part(tmp_path / name, "branch", units="m", up="Z")
    m = t.measurements
    assert m.length == pytest.approx(1.2, rel=1e-5)
    assert m.base_radius == pytest.approx(0.05, rel=1e-3)
    assert m.tip_radius == pytest.approx(0.05, rel=1e-3)
    assert m.surface_area == pytest.approx(src.area, rel=1e-6)
    assert m.triangles == 96
    # normalised frame: base centre at the origin, growth along +Z, unit length
    lo, hi = t.vertices.min(axis=0), t.vertices.max(axis=0)
    np.testing.assert_allclose(lo, [-0.05 / 1.2, -0.05 / 1.2, 0], atol=2e-3)
    np.testing.assert_allclose(hi, [0.05 / 1.2, 0.05 / 1.2, 1], atol=2e-3)
    assert t.normalised_base_radius == pytest.approx(0.05 / 1.2, rel=1e-3)
    assert np.allclose(np.linalg.norm(t.normals, axis=1), 1.0)


@pytest.mark.parametrize(("units", "scale"), [("mm", 1000.0), ("cm", 100.0), ("in", 1 / 0.0254)])
def test_units_explicit_and_auto(tmp_path, units, scale):
    cylinder(tmp_path / "c.stl", scale=scale)
    t = import_part(tmp_path / "c.stl", "branch", units=units, up="Z")
    assert t.measurements.length == pytest.approx(1.2, rel=1e-5)
    assert t.provenance["units"] == units
    auto = import_part(tmp_path / "c.stl", "branch", units="auto", up="Z")
    assert auto.provenance["units"] == units
    assert auto.measurements.length == pytest.approx(1.2, rel=1e-5)
    bounds = np.array([auto.provenance["originalBoundsMin"], auto.provenance["originalBoundsMax"]])
    assert np.ptp(bounds[:, 2]) == pytest.approx(1.2 * scale, rel=1e-5)


def test_y_up_obj_becomes_z_up(tmp_path):
    cylinder(tmp_path / "y.obj", along_y=True)
    raw = read_cad(tmp_path / "y.obj")
    assert np.ptp(raw.vertices[:, 1]) == pytest.approx(1.2, rel=1e-6)  # Y-up in the file
    t = import_part(tmp_path / "y.obj", "trunk", units="m", up="auto")
    assert t.provenance["upAxis"] == "Y"
    assert t.measurements.length == pytest.approx(1.2, rel=1e-5)
    from usdforest.cad.parts import to_metres_z_up

    mesh, _, _ = to_metres_z_up(raw, "m", "Y", "trunk")
    assert mesh.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert mesh.vertices[:, 2].max() == pytest.approx(1.2, rel=1e-6)


def test_tapered_branch_base_is_the_thick_end(tmp_path):
    # a cone-like branch standing on its thin end: the base must be the thick (top) end
    m = trimesh.creation.cone(radius=0.1, height=1.0, sections=16)
    m.apply_transform(trimesh.transformations.rotation_matrix(math.pi, [1, 0, 0]))
    m.export(tmp_path / "cone.stl")
    t = import_part(tmp_path / "cone.stl", "branch", units="m", up="Z")
    base = t.vertices[t.vertices[:, 2] < 0.02]
    tip = t.vertices[t.vertices[:, 2] > 0.98]
    assert np.abs(base[:, :2]).max() > 5 * np.abs(tip[:, :2]).max()


def test_shipped_leaf_frame_and_area():
    t = import_part(CAD / "leaf_broadleaf.obj", "leaf", units="m", up="Z")
    src = trimesh.load(CAD / "leaf_broadleaf.obj", force="mesh")
    assert t.vertices[:, 0].min() == pytest.approx(0.0, abs=1e-3)  # attachment at the origin
    assert t.vertices[:, 0].max() == pytest.approx(1.0, abs=1e-9)  # blade along +X, unit
    assert np.ptp(t.vertices[:, 1]) > 5 * np.ptp(t.vertices[:, 2])  # flat in XY
    tri = t.vertices[t.faces]
    normal_sum = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).sum(axis=0)
    assert normal_sum[2] > 0  # blade normal +Z
    assert t.measurements.leaf_area == pytest.approx(src.area, rel=1e-6)
    assert t.measurements.equivalent_disk_radius == pytest.approx(
        math.sqrt(src.area / math.pi), rel=1e-6
    )
    assert 0.14 < t.measurements.length < 0.16


@pytest.mark.parametrize("name", ["leaf_broadleaf", "leaf_beech", "leaf_oak", "leaf_birch"])
def test_shipped_leaves_attach_at_their_petioles(name):
    # the shipped layer's origin is the petiole (a stalk, round in section), not the pointed
    # tip, which over its last few percent is narrower than a petiole and flat
    stage = Usd.Stage.Open(str(template_dir() / f"{name}.usdc"))
    v = np.concatenate(
        [
            np.array(UsdGeom.Mesh(p).GetPointsAttr().Get())
            for p in stage.Traverse()
            if p.IsA(UsdGeom.Mesh)
        ]
    )
    stalk = v[v[:, 0] < 0.03]
    assert np.ptp(stalk[:, 1]) > 0.005 and np.ptp(stalk[:, 2]) > 0.005  # a tube, not a point
    assert np.abs(stalk[:, 1]).max() < 0.15 * np.abs(v[:, 1]).max()  # and thin


def test_needle_fascicle_attaches_at_its_sheath():
    t = import_part(CAD / "needle_fascicle.stl", "leaf", units="m", up="Z")
    near = t.vertices[t.vertices[:, 0] < 0.05]
    far = t.vertices[t.vertices[:, 0] > 0.95]
    assert np.ptp(near[:, 1]) < np.ptp(far[:, 1])


def test_cleaning_merges_duplicates_and_drops_degenerate_faces(tmp_path):
    v = np.array(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 2, 0]], float
    )
    f = np.array([[0, 1, 2], [3, 5, 4], [0, 1, 3], [0, 1, 2]])  # a degenerate and a repeat
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "d.obj")
    raw = read_cad(tmp_path / "d.obj")
    assert raw.n_triangles == 2 and len(raw.vertices) == 4


# --------------------------------------------------------------------------- bad input


def write_bad(tmp_path: Path, kind: str) -> Path:
    if kind == "truncated-stl":
        p = tmp_path / "t.stl"
        good = trimesh.creation.box().export(file_type="stl")
        p.write_bytes(good[: len(good) - 30])
    elif kind == "billions-stl":
        p = tmp_path / "b.stl"
        p.write_bytes(b"\0" * 80 + struct.pack("<I", 3_000_000_000) + b"\0" * 100)
    elif kind == "obj-missing-vertex":
        p = tmp_path / "m.obj"
        p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n")
    elif kind == "empty":
        p = tmp_path / "e.stl"
        p.write_bytes(b"")
    elif kind == "nan":
        p = tmp_path / "n.obj"
        p.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    elif kind == "not-a-mesh":
        p = tmp_path / "x.ply"
        p.write_text("hello, this is a shopping list\n" * 10)
    elif kind == "not-a-mesh-obj":
        p = tmp_path / "x.obj"
        p.write_text("# only comments\nmtllib nothing.mtl\n")
    elif kind == "unknown-format":
        p = tmp_path / "x.fbx"
        p.write_bytes(b"Kaydara FBX Binary")
    elif kind == "ascii-stl-no-facets":
        p = tmp_path / "a.stl"
        p.write_text("solid empty\nendsolid empty\n")
    else:
        raise AssertionError(kind)
    return p


BAD = {
    "truncated-stl": "truncated binary STL: header claims 12 triangles (684 bytes) but the file",
    "billions-stl": "header claims 3,000,000,000 triangles, over the limit",
    "obj-missing-vertex": "line 5: face refers to vertex 9 but only 3 vertices are defined",
    "empty": "the file is empty",
    "nan": "1 vertices have NaN or infinite coordinates",
    "not-a-mesh": "not a PLY file",
    "not-a-mesh-obj": "OBJ file with no vertices",
    "unknown-format": "unknown CAD format '.fbx'",
    "ascii-stl-no-facets": "not an STL file",
}


@pytest.mark.parametrize("kind", sorted(BAD))
def test_bad_files_raise_clear_errors(tmp_path, kind):
    p = write_bad(tmp_path, kind)
    with pytest.raises(CADError) as exc:
        import_part(p, "branch")
    assert str(exc.value).startswith(p.name) or str(exc.value).startswith(str(p))
    assert BAD[kind] in str(exc.value)


@pytest.mark.parametrize("kind", sorted(BAD))
def test_bad_files_via_cli_exit_2_and_write_nothing(tmp_path, runner, kind):
    p = write_bad(tmp_path, kind)
    out = tmp_path / "out" / "t.usdc"
    r = runner.invoke(app, ["template", "import", str(p), "--part", "leaf", "-o", str(out)])
    assert r.exit_code == 2
    assert p.name in r.stderr and BAD[kind] in r.stderr
    assert "Traceback" not in r.output + r.stderr
    assert not out.exists()
    assert not list(tmp_path.glob("out/*"))


def test_missing_file_and_unknown_part(tmp_path, runner):
    r = runner.invoke(
        app,
        [
            "template",
            "import",
            str(tmp_path / "nope.stl"),
            "--part",
            "leaf",
            "-o",
            str(tmp_path / "o.usdc"),
        ],
    )
    assert r.exit_code == 2 and "no such file" in r.stderr
    cylinder(tmp_path / "c.stl")
    r = runner.invoke(
        app,
        [
            "template",
            "import",
            str(tmp_path / "c.stl"),
            "--part",
            "root",
            "-o",
            str(tmp_path / "o.usdc"),
        ],
    )
    assert r.exit_code == 2 and "unknown part 'root'" in r.stderr
    r = runner.invoke(
        app,
        [
            "template",
            "import",
            str(tmp_path / "c.stl"),
            "--part",
            "leaf",
            "--units",
            "furlong",
            "-o",
            str(tmp_path / "o.usdc"),
        ],
    )
    assert r.exit_code == 2 and "unknown units 'furlong'" in r.stderr
    assert not (tmp_path / "o.usdc").exists()


def test_text_files_in_other_encodings_import(tmp_path):
    """A Latin-1 comment in an OBJ (charset-normalizer is a dependency for this)."""
    from usdforest.cad.parts import read_cad

    p = tmp_path / "latin.obj"
    p.write_bytes(b"# caf\xe9 \xff\xfe comment\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    m = read_cad(p)
    assert m.n_triangles == 1 and m.vertices.shape == (3, 3)

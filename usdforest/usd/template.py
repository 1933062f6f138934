"""Template layers: one CAD-derived part, normalised, as ``/Template`` (Xform) holding a Mesh."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from usdforest.cad.uvs import leaf_uvs, wood_uvs
from usdforest.errors import UsdForestError
from usdforest.grow.bounds import hull_vertices
from usdforest.grow.placement import WoodShape, centreline_of
from usdforest.usd.layers import (
    T,
    attr,
    bind_material,
    extent_of,
    ints,
    new_layer,
    preview_material,
    prim,
    save_layer,
    semantic_label,
    triangle_mesh,
)

if TYPE_CHECKING:  # trimesh loads with the CAD importer, not with every template reader
    from usdforest.cad.parts import TemplatePart

SEMANTIC_CLASS = {
    "trunk": "trunk",
    "branch": "branch",
    "twig": "branch",
    "leaf": "leaf",
    "deadwood": "dead_wood",
    "groundcover": "ground_vegetation",
}
GREEN_PARTS = ("leaf", "groundcover")  # thin blades: double-sided, a leaf's material

# Stored precision. Eigen-decompositions and sums differ in their last bits between BLAS
# kernels and library versions; rounding before storing keeps the bytes identical everywhere.
POINT_DECIMALS = 6  # template frame is unit length: 1e-6 of the part's length
SIGNIFICANT_DIGITS = 7  # measurements and normalised radii


def significant(x: float, digits: int = SIGNIFICANT_DIGITS) -> float:
    """``x`` rounded to ``digits`` significant digits (ints pass through)."""
    if isinstance(x, bool | int):
        return x
    return float(f"{float(x):.{digits}g}")


def stable_points(a: np.ndarray, decimals: int = POINT_DECIMALS) -> np.ndarray:
    """Coordinates rounded to ``decimals`` (``-0`` folded into ``0``) before float32 storage."""
    return np.round(np.asarray(a, dtype=np.float64), decimals) + 0.0


def template_layer(part: TemplatePart) -> Sdf.Layer:
    """Author a template layer for ``part`` (in memory).

    ``/Template`` is an Xform (kind component) with customData ``usdforest`` holding the part
    type, real measurements and provenance; ``/Template/Mesh`` carries points, face counts and
    indices, vertex normals, extent, displayColor and a bound UsdPreviewSurface material under
    ``/Template/Looks``.
    """
    layer = new_layer("Template", comment=f"usdforest template {part.name!r} ({part.part})")
    m = part.measurements
    with Sdf.ChangeBlock():
        root = prim(layer, "Template", "Xform")
        root.kind = "component"
        root.assetInfo = {"name": part.name}
        root.customData = {
            "usdforest": {
                "part": part.part,
                "name": part.name,
                "frame": _frame_doc(part.part),
                "normalisedBaseRadius": significant(part.normalised_base_radius),
                "normalisedTipRadius": significant(part.normalised_tip_radius),
                "measurements": {k: significant(v) for k, v in m.as_dict().items()},
                "provenance": _plain(part.provenance),
            }
        }
        points = stable_points(part.vertices)
        extent = extent_of(points)
        attr(root, "extentsHint", T.Float3Array, extent)
        looks = prim(root, "Looks", "Scope")
        material = preview_material(
            looks,
            "Leaf" if part.part in GREEN_PARTS else "Bark",
            part.color,
            nonvisual="leaf_grass" if part.part in GREEN_PARTS else "bark",
            roughness=0.6 if part.part in GREEN_PARTS else 0.9,
        )
        mesh = triangle_mesh(root, "Mesh", points, part.faces, stable_points(part.normals))
        attr(mesh, "doubleSided", T.Bool, part.part in GREEN_PARTS, uniform=True)
        _texture_coordinates(mesh, part.part, points, part.faces)
        attr(
            mesh,
            "primvars:displayColor",
            T.Color3fArray,
            Vt.Vec3fArray([tuple(part.color)]),
            interpolation="constant",
        )
        bind_material(mesh, material)
        semantic_label(mesh, SEMANTIC_CLASS[part.part])
    return layer


def _texture_coordinates(
    mesh: Sdf.PrimSpec, part: str, points: np.ndarray, faces: np.ndarray
) -> None:
    """Indexed ``primvars:st`` (see :mod:`usdforest.cad.uvs`) from the stored (rounded) points,
    rounded like them: each distinct coordinate stored once, ``primvars:st:indices`` per
    vertex (leaves) or per face corner (wood)."""
    if part in GREEN_PARTS:
        st, interpolation = leaf_uvs(points), "vertex"
    else:
        st, interpolation = wood_uvs(points, faces), "faceVarying"
    values, indices = np.unique(stable_points(st).astype(np.float32), axis=0, return_inverse=True)
    attr(
        mesh,
        "primvars:st",
        T.TexCoord2fArray,
        Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(values)),
        interpolation=interpolation,
    )
    attr(mesh, "primvars:st:indices", T.IntArray, ints(indices.ravel()))


def _frame_doc(part: str) -> str:
    if part == "leaf":
        return "attachment at origin, blade axis +X, normal +Z, unit length"
    if part == "groundcover":
        return "footprint centred at origin, resting on z = 0, Z up, unit height"
    return "base centre at origin, growth axis +Z, unit length"


def _plain(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, list | tuple):
            out[k] = Vt.DoubleArray([float(x) for x in v])
        else:
            out[k] = v
    return out


def write_template(part: TemplatePart, path: str | Path) -> Path:
    """Write ``part`` as a template layer at ``path`` (``.usdc`` or ``.usda``), atomically."""
    path = Path(path)
    if path.suffix not in (".usdc", ".usda", ".usd"):
        raise UsdForestError(f"{path}: a template layer must end in .usdc, .usda or .usd")
    return save_layer(template_layer(part), path)


@dataclass(frozen=True)
class TemplateInfo:
    """What a tree needs to know about a template layer."""

    path: Path
    part: str
    name: str
    base_radius: float  # normalised (unit length)
    tip_radius: float
    measurements: dict
    centreline: np.ndarray  # (K, 2): x, y of the centreline at K heights z = 0..1
    hull: np.ndarray  # (h, 3) vertices of the convex hull of its meshes (exact bounds)

    def wood_shape(self) -> WoodShape:
        """Normalised base radius and centreline, for placement."""
        return WoodShape(max(self.base_radius, 1e-6), self.centreline, max(self.tip_radius, 0.0))


_READ: dict[tuple, TemplateInfo] = {}


def read_template(path: str | Path) -> TemplateInfo:
    """Read a template layer's part type, normalised radii, centreline and convex hull; once
    per process while the file is unchanged (same inode, size, and modification and change
    times)."""
    path = Path(path)
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    except OSError:
        key = None
    if key is not None and key in _READ:
        info = _READ[key]
        return info if info.path == path else replace(info, path=path)
    info = _read_template(path)
    if key is not None:
        _READ[key] = info
    return info


def _read_template(path: Path) -> TemplateInfo:
    layer = Sdf.Layer.FindOrOpen(str(path))
    if layer is None:
        raise UsdForestError(f"{path}: cannot open the template layer")
    spec = layer.GetPrimAtPath("/Template")
    if spec is None or "usdforest" not in spec.customData:
        raise UsdForestError(f"{path}: not a usdforest template (no /Template with customData)")
    data = spec.customData["usdforest"]
    stage = Usd.Stage.Open(layer)
    meshes = [UsdGeom.Mesh(p) for p in Usd.PrimRange(stage.GetPrimAtPath("/Template"))]
    pts = [np.asarray(m.GetPointsAttr().Get() or [], dtype=np.float64) for m in meshes if m]
    points = np.concatenate(pts).reshape(-1, 3) if pts else np.zeros((0, 3))
    return TemplateInfo(
        path=path,
        part=str(data["part"]),
        name=str(data["name"]),
        base_radius=float(data["normalisedBaseRadius"]),
        tip_radius=float(data["normalisedTipRadius"]),
        measurements=dict(data["measurements"]),
        centreline=centreline_of(points),
        hull=hull_vertices(points),
    )

"""The forest floor's vegetation layer: a PointInstancer of CAD-templated patches of grass,
herbs, ferns and moss, and its ground truth.

::

    forest_assets/
      groundcover.usdc  /Forest/GroundVegetation  PointInstancer (kind group), one prototype
                        per growth form: /Forest/GroundVegetation/Prototypes/<Form>
                        -> templates/groundcover_<form>.usdc (labels ground_vegetation, form)
      groundcover.csv   id,form,x,y,z,diameter,height,yaw,cover,area,light

A patch is its template scaled across (to its disc's diameter) and up (to its height): the
ground it hides from above is its template's projected area times the product of its
horizontal scales.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdforest.grow.groundcover import FORMS, Patches, PatchShape
from usdforest.usd.layers import mesh_triangles, new_layer, prim
from usdforest.usd.scatter import (
    TemplateProto,
    author_instancer,
    copy_shipped_templates,
    instance_matrices,
    labelled,
    prototype_meshes,
)

LABEL = "ground_vegetation"
CSV_HEADER = (
    "id",
    "form",
    "x",
    "y",
    "z",
    "diameter",
    "height",
    "yaw",
    "cover",
    "area",
    "light",
)


def template_name(form: str) -> str:
    """The shipped template of a growth form."""
    return f"groundcover_{form}"


def projected_area(tri: np.ndarray) -> float:
    """Area of the ground that triangles ``(m, 3, 3)`` hide from above (the union of their
    shadows on z = 0, with shapely)."""
    import shapely

    t = np.asarray(tri, dtype=float)[:, :, :2]
    polys = shapely.polygons(t)
    polys = polys[shapely.area(polys) > 0]
    return float(shapely.union_all(polys).area) if len(polys) else 0.0


def _template_triangles(form: str) -> tuple[np.ndarray, float]:
    """A shipped patch template's triangles (unit frame) and its height in metres."""
    from usdforest.cad.library import template_path

    stage = Usd.Stage.Open(str(template_path(template_name(form))), Usd.Stage.LoadNone)
    root = stage.GetDefaultPrim()
    tri = np.concatenate(
        [mesh_triangles(m, np.eye(4)) for m in stage.Traverse() if m.IsA(UsdGeom.Mesh)]
    )
    height = float(root.GetCustomDataByKey("usdforest")["measurements"]["length"])
    return tri, height


def patch_shapes() -> dict[str, PatchShape]:
    """Each shipped ground-vegetation template as a :class:`PatchShape`."""
    out = {}
    for form in FORMS:
        tri, height = _template_triangles(form)
        radius = float(np.linalg.norm(tri.reshape(-1, 3)[:, :2], axis=1).max())
        fill = projected_area(tri) / (math.pi * radius**2)
        out[form] = PatchShape(radius, fill, height)
    return out


def copy_groundcover_templates(folder: Path) -> None:
    """Copy the ground-vegetation templates into the forest's ``templates/`` folder."""
    copy_shipped_templates([template_name(f) for f in FORMS], folder)


def instance_transforms(
    patches: Patches, shapes: dict[str, PatchShape]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PointInstancer ``(positions, orientations (x, y, z, w), scales, protoIndices)``."""
    radius = np.array([shapes[f].radius for f in FORMS])[patches.form]
    across = patches.diameter / (2 * radius)
    half = patches.yaw / 2
    quat = np.column_stack(
        [np.zeros(len(patches)), np.zeros(len(patches)), np.sin(half), np.cos(half)]
    )
    scales = np.column_stack([across, across, patches.height])
    return patches.base, quat, scales, patches.form.astype(np.int32)


def groundcover_extent(patches: Patches, anchor: np.ndarray) -> np.ndarray:
    """A box round every patch (in the layers' frame, about ``anchor``)."""
    if not len(patches):
        return np.zeros((2, 3))
    pos = patches.base - np.array([anchor[0], anchor[1], 0.0])
    # orientations are stored as half floats (quath): a rim may move by 1e-3 of the radius
    r = (patches.diameter / 2 * 1.002)[:, None]
    lo = pos - np.column_stack([r, r, np.zeros(len(r))])
    hi = pos + np.column_stack([r, r, patches.height])
    return np.stack([lo.min(axis=0), hi.max(axis=0)])


def groundcover_layer(
    patches: Patches, shapes: dict[str, PatchShape], anchor: np.ndarray, ids: np.ndarray
) -> Sdf.Layer:
    """``/Forest/GroundVegetation`` for ``patches`` in recipe coordinates, written about
    ``anchor``."""
    layer = new_layer("Forest", comment="usdforest ground vegetation")
    pos, quat, scales, index = instance_transforms(patches, shapes)
    pos = pos - np.array([anchor[0], anchor[1], 0.0])
    protos = [
        TemplateProto(
            form.capitalize(),
            f"./templates/{template_name(form)}.usdc",
            (LABEL, form),
            {"form": form, "fill": round(shapes[form].fill, 6)},
        )
        for form in FORMS
    ]
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        author_instancer(
            forest,
            "GroundVegetation",
            protos,
            (pos, quat, scales, index),
            ids,
            groundcover_extent(patches, anchor),
        )
    return layer


def write_groundcover_csv(path: Path, patches: Patches, ids: np.ndarray) -> None:
    """``groundcover.csv``: one row per patch (recipe coordinates of its centre on the
    ground; metres, degrees, the fraction of its cell it covers, the m² it covers, the
    relative light at its cell)."""
    from usdforest import csvtext

    c = patches.base
    with path.open("wb") as f:
        f.write((",".join(CSV_HEADER) + "\n").encode())
        csvtext.write_rows(
            f,
            len(patches),
            lambda i: (
                csvtext.integers(np.asarray(ids)[i]),
                csvtext.labels(patches.form[i], FORMS),
                csvtext.fixed(c[i, 0], 3),
                csvtext.fixed(c[i, 1], 3),
                csvtext.fixed(c[i, 2], 3),
                csvtext.fixed(patches.diameter[i], 3),
                csvtext.fixed(patches.height[i], 3),
                csvtext.fixed(np.degrees(patches.yaw[i]), 2),
                csvtext.fixed(patches.cover[i], 4),
                csvtext.fixed(patches.area[i], 4),
                csvtext.fixed(patches.light[i], 4),
            ),
        )


def is_ground_vegetation(instancer: Usd.Prim) -> bool:
    """Whether a PointInstancer's prototypes are ground vegetation."""
    return labelled(instancer, LABEL)


def ground_vegetation_figures(instancer: Usd.Prim | None, area: float) -> dict:
    """Ground vegetation measured on the composed stage: each prototype's projected area
    (the union of its triangles' shadows) times each instance's horizontal scales, over the
    region's ``area`` m², per growth form (the prototype's ``usdforest:form``), and patches
    per hectare. ``None``: a forest without ground vegetation."""
    out = {
        "ground_vegetation_cover": 0.0,
        "ground_vegetation_cover_by_form": {f: 0.0 for f in FORMS},
        "ground_vegetation_patches_per_ha": 0.0,
    }
    if instancer is None:
        return out
    idx, mats = instance_matrices(instancer)
    if not len(idx):
        return out
    # the product of an instance's horizontal scales: the determinant of its upper-left 2x2
    # (patches turn about +Z only)
    flat = np.abs(np.linalg.det(mats[:, :2, :2]))
    pi = UsdGeom.PointInstancer(instancer)
    stage = instancer.GetStage()
    for k, target in enumerate(pi.GetPrototypesRel().GetTargets()):
        sel = idx == k
        if not sel.any():
            continue
        proto = stage.GetPrimAtPath(target)
        form = str((proto.GetCustomDataByKey("usdforest") or {}).get("form", FORMS[0]))
        tri = np.concatenate(prototype_meshes(proto))
        out["ground_vegetation_cover_by_form"][form] += (
            projected_area(tri) * float(flat[sel].sum()) / area
        )
    out["ground_vegetation_cover"] = float(sum(out["ground_vegetation_cover_by_form"].values()))
    out["ground_vegetation_patches_per_ha"] = len(idx) / (area / 1e4)
    return out

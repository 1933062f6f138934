"""The forest's ground: a plane or a height field under the plot, with a collider, a label and
a material.

``/Forest/Ground/Mesh`` is the triangulated :class:`~usdforest.sites.terrain.HeightField` (two
triangles for a plane over the region's bounding box plus a margin, at z = 0; a raster's grid
otherwise) on which every tree stands; ``PhysicsCollisionAPI`` makes it the floor robots drive
on, ``SemanticsLabelsAPI:class = ground`` labels it for sensors, and a UsdPreviewSurface gives
it the colour the thumbnail shows. Under ground vegetation (``[groundcover] litter = true``)
the material is leaf litter: brown, SimReady non-visual base ``dead_leaf_grass``, labels
``ground`` and ``litter``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pxr import Sdf, Vt

from usdforest.sites.terrain import HeightField
from usdforest.usd.layers import (
    T,
    attr,
    bind_material,
    new_layer,
    preview_material,
    prim,
    semantic_label,
    triangle_mesh,
)

GROUND_COLOR = (0.36, 0.30, 0.22)
LITTER_COLOR = (0.33, 0.22, 0.12)  # brown beech and oak leaf litter


def ground_layer(
    field: HeightField, color: Sequence[float] = GROUND_COLOR, litter: bool = False
) -> Sdf.Layer:
    """``/Forest/Ground`` in a layer of its own (a height field's arrays belong in a crate
    file, not in the text interface)."""
    layer = new_layer("Forest", comment="usdforest forest ground")
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        add_ground(forest, field, color=color, litter=litter)
    return layer


def add_ground(
    root: Sdf.PrimSpec,
    field: HeightField,
    *,
    color: Sequence[float] = GROUND_COLOR,
    litter: bool = False,
) -> None:
    """``<root>/Ground``: the mesh of ``field``, with its collider, label and material (leaf
    litter with ``litter``, in :data:`LITTER_COLOR` unless ``color`` is not the default)."""
    from usdforest.meshes import vertex_normals

    pts, tri = field.mesh()
    ground = prim(root, "Ground", "Xform")
    looks = prim(ground, "Looks", "Scope")
    if litter and tuple(color) == GROUND_COLOR:
        color = LITTER_COLOR
    material = preview_material(
        looks,
        "Litter" if litter else "Ground",
        color,
        nonvisual="dead_leaf_grass" if litter else "dirt",
        roughness=0.95,
    )
    normals = vertex_normals(pts, tri)
    mesh = triangle_mesh(ground, "Mesh", pts, tri, np.round(normals, 6) + 0.0)
    attr(
        mesh,
        "primvars:displayColor",
        T.Color3fArray,
        Vt.Vec3fArray([tuple(float(c) for c in color)]),
        interpolation="constant",
    )
    bind_material(mesh, material)
    semantic_label(mesh, ["ground", "litter"] if litter else "ground")
    items = list(mesh.GetInfo("apiSchemas").prependedItems)
    mesh.SetInfo(
        "apiSchemas",
        Sdf.TokenListOp.Create(
            prependedItems=[*items, "PhysicsCollisionAPI", "PhysicsMeshCollisionAPI"]
        ),
    )
    attr(mesh, "physics:approximation", T.Token, "none", uniform=True)

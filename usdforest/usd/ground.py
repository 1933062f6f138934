"""The forest's ground: a flat plane under the plot, with a collider, a label and a material.

``/Forest/Ground`` is a Mesh of two triangles over the region's bounding box (plus a margin)
at z = 0, where every tree stands; ``PhysicsCollisionAPI`` makes it the floor robots drive on,
``SemanticsLabelsAPI:class = ground`` labels it for sensors, and a UsdPreviewSurface gives it
the colour the thumbnail shows.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pxr import Sdf, Vt

from .layers import T, attr, bind_material, preview_material, prim, semantic_label, triangle_mesh

GROUND_COLOR = (0.36, 0.30, 0.22)


def add_ground(
    root: Sdf.PrimSpec,
    bounds: Sequence[float],
    *,
    margin: float = 0.0,
    color: Sequence[float] = GROUND_COLOR,
) -> None:
    """``<root>/Ground`` over ``bounds`` (x0, y0, x1, y1) grown by ``margin`` metres."""
    x0, y0, x1, y1 = (float(b) for b in bounds)
    x0, y0, x1, y1 = x0 - margin, y0 - margin, x1 + margin, y1 + margin
    pts = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    ground = prim(root, "Ground", "Xform")
    looks = prim(ground, "Looks", "Scope")
    material = preview_material(looks, "Ground", color, nonvisual="dirt", roughness=0.95)
    mesh = triangle_mesh(
        ground, "Mesh", pts, np.array([[0, 1, 2], [0, 2, 3]]), np.tile([0.0, 0.0, 1.0], (4, 1))
    )
    attr(
        mesh,
        "primvars:displayColor",
        T.Color3fArray,
        Vt.Vec3fArray([tuple(float(c) for c in color)]),
        interpolation="constant",
    )
    bind_material(mesh, material)
    semantic_label(mesh, "ground")
    items = list(mesh.GetInfo("apiSchemas").prependedItems)
    mesh.SetInfo(
        "apiSchemas",
        Sdf.TokenListOp.Create(
            prependedItems=[*items, "PhysicsCollisionAPI", "PhysicsMeshCollisionAPI"]
        ),
    )
    attr(mesh, "physics:approximation", T.Token, "none", uniform=True)

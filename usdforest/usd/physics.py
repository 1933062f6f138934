"""UsdPhysics authoring: collider capsules, the forest's collision layer, a physics scene.

Colliders are ``Capsule`` Gprims (axis Z, purpose ``guide`` so they never render) with
``PhysicsCollisionAPI``: static colliders, the simple shapes Isaac Sim, Omniverse PhysX and
newton read. pxr's UsdPhysics parser and newton skip colliders inside PointInstancer
prototypes, so a forest also gets ``colliders.usdc``: one capsule per trunk, placed where
each tree instance stands, under ``/Forest/Colliders`` (deactivate that prim where an engine
reads instanced colliders itself).
"""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Vt

from usdforest.grow.colliders import Capsules
from usdforest.grow.placement import frames_from_directions
from usdforest.rotations import quat_from_matrix
from usdforest.usd.layers import T, attr, new_layer, prim

COLLISION_API = "PhysicsCollisionAPI"


def _quaternions(d: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternions turning +Z to each unit direction."""
    return quat_from_matrix(frames_from_directions(d, np.zeros(len(d))))


def author_capsules(parent: Sdf.PrimSpec, caps: Capsules, names: list[str] | None = None) -> None:
    """One guide-purpose collider ``Capsule`` per capsule under ``parent`` (in a change
    block: the caller opens it).

    The first capsule is authored in full and copied (``Sdf.CopySpec``, in C++) for the
    others, which then get their own radius, height, extent and transform: 3.5x faster than
    authoring every attribute of every prim from Python.
    """
    if len(caps) == 0:
        return
    d = caps.tip - caps.base
    length = np.linalg.norm(d, axis=1)
    d = np.where(length[:, None] > 1e-9, d / np.maximum(length, 1e-12)[:, None], [0.0, 0.0, 1.0])
    centre = 0.5 * (caps.base + caps.tip)
    height = np.maximum(length - 2.0 * caps.radius, 0.0)  # the cylinder between the caps
    q = _quaternions(d)
    names = list(names or caps.names)
    layer = parent.layer
    first = prim(parent, names[0], "Capsule")
    first.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=[COLLISION_API]))
    attr(first, "purpose", T.Token, "guide", uniform=True)
    attr(first, "axis", T.Token, "Z", uniform=True)
    for name, type_ in (
        ("radius", T.Double),
        ("height", T.Double),
        ("extent", T.Float3Array),
        ("xformOp:translate", T.Double3),
        ("xformOp:orient", T.Quatf),
    ):
        Sdf.AttributeSpec(first, name, type_)
    attr(
        first,
        "xformOpOrder",
        T.TokenArray,
        Vt.TokenArray(["xformOp:translate", "xformOp:orient"]),
        uniform=True,
    )
    for k, name in enumerate(names):
        path = first.path if k == 0 else parent.path.AppendChild(name)
        if k:
            Sdf.CopySpec(layer, first.path, layer, path)
        r, h = float(caps.radius[k]), float(height[k])
        half = h / 2 + r
        x, y, z, w = (float(v) for v in q[k])
        values = (
            ("radius", r),
            ("height", h),
            ("extent", Vt.Vec3fArray([(-r, -r, -half), (r, r, half)])),
            ("xformOp:translate", Gf.Vec3d(*map(float, centre[k]))),
            ("xformOp:orient", Gf.Quatf(w, x, y, z)),
        )
        for prop, value in values:
            layer.GetAttributeAtPath(path.AppendProperty(prop)).default = value


def add_colliders(root: Sdf.PrimSpec, caps: Capsules) -> None:
    """``<root>/Colliders`` (Scope, purpose guide) holding the capsules."""
    if len(caps) == 0:
        return
    scope = prim(root, "Colliders", "Scope")
    author_capsules(scope, caps)


def collision_layer(caps: Capsules, names: list[str]) -> Sdf.Layer:
    """``/Forest/Colliders/<name>``: every tree instance's capsules, in forest space."""
    layer = new_layer("Forest", comment="usdforest forest colliders (UsdPhysics)")
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        scope = prim(forest, "Colliders", "Scope")
        author_capsules(scope, caps, names)
    return layer


def instance_capsules(
    proto_caps: list[Capsules],
    proto_index: np.ndarray,
    xyz: np.ndarray,
    yaw_deg: np.ndarray,
    scale: np.ndarray,
) -> tuple[Capsules, list[str]]:
    """Each instance's prototype capsules moved to where it stands (``xyz``: on the ground;
    yaw about Z, uniform scale), with names ``T_<instance>`` (``T_<instance>_<k>`` for a
    tree's k-th capsule)."""
    bases, tips, radii, names = [], [], [], []
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    for k, caps in enumerate(proto_caps):
        inst = np.flatnonzero(proto_index == k)
        if len(caps) == 0 or inst.size == 0:
            continue
        for j in range(len(caps)):
            for src, out in ((caps.base[j], bases), (caps.tip[j], tips)):
                p = src[None, :] * scale[inst, None]
                x = c[inst] * p[:, 0] - s[inst] * p[:, 1] + xyz[inst, 0]
                y = s[inst] * p[:, 0] + c[inst] * p[:, 1] + xyz[inst, 1]
                out.append(np.stack([x, y, p[:, 2] + xyz[inst, 2]], axis=1))
            radii.append(caps.radius[j] * scale[inst])
            names.append((inst, j))
    if not bases:
        return Capsules((), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)), []
    order = np.argsort(np.concatenate([i * 64 + j for i, j in names]), kind="stable")
    flat = [f"T_{i:07d}" + ("" if j == 0 else f"_{j}") for ids, j in names for i in ids]
    out = Capsules(
        tuple(np.asarray(flat, dtype=object)[order]),
        np.concatenate(bases)[order],
        np.concatenate(tips)[order],
        np.concatenate(radii)[order],
    )
    return out, list(out.names)


def join_capsules(a: Capsules, b: Capsules) -> Capsules:
    """The capsules of ``a`` then those of ``b``."""
    return Capsules(
        tuple(a.names) + tuple(b.names),
        np.concatenate([a.base.reshape(-1, 3), b.base.reshape(-1, 3)]),
        np.concatenate([a.tip.reshape(-1, 3), b.tip.reshape(-1, 3)]),
        np.concatenate([a.radius.reshape(-1), b.radius.reshape(-1)]),
    )


def add_physics_scene(root: Sdf.PrimSpec, gravity: float = 9.81) -> None:
    """``<root>/PhysicsScene`` (UsdPhysics.Scene, gravity down -Z in m/s²)."""
    scene = prim(root, "PhysicsScene", "PhysicsScene")
    attr(scene, "physics:gravityDirection", T.Vector3f, Gf.Vec3f(0.0, 0.0, -1.0))
    attr(scene, "physics:gravityMagnitude", T.Float, float(gravity))

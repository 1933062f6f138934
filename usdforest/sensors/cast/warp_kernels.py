"""NVIDIA Warp kernels for first hits through instances of instances (trees, then leaves).

Imported only when Warp casts rays (on CUDA; Warp compiles these on first use and caches
them), so the rest of usdforest starts without it. The layout the kernels read is built by
:class:`~usdforest.sensors.cast.warpcast.WarpCaster`:

* ``wood``: one grouped :class:`warp.Mesh`, group 0 the world's own triangles, group
  ``p + 1`` tree prototype ``p``'s; ``wood_roots[g]`` its BVH root (-2: empty group).
* ``leaf_bvh``: one grouped :class:`warp.Bvh` of leaf instance boxes, grouped the same way
  (in the owner's space); each leaf's inverse transform (``leaf_inv``, ``leaf_shift``: column
  form, ``local = inv @ (x - shift)``) and its shape's root in ``shapes``, a grouped mesh
  of the leaf shapes.
* ``top``: a :class:`warp.Bvh` of the tree instances' world boxes, with their inverse
  transforms and prototype; on CUDA the boxes themselves, looped over (a BVH query must not
  open inside another's loop there: :mod:`usdforest.sensors.cast.warpcast`).

Directions are never renormalised between spaces, so the ray parameter ``t`` is the
world-space distance at every level and one running ``best`` prunes them all.
"""

from __future__ import annotations

import warp as wp

EMPTY = -2  # a group with nothing in it: never queried (root -1 would mean the whole BVH)


@wp.func
def _part(
    wood: wp.uint64,
    wood_root: wp.int32,
    leaf_bvh: wp.uint64,
    leaf_root: wp.int32,
    leaf_inv: wp.array[wp.mat33],
    leaf_shift: wp.array[wp.vec3],
    leaf_shape: wp.array[wp.int32],
    shapes: wp.uint64,
    o: wp.vec3,
    d: wp.vec3,
    best: float,
):
    """Nearest hit nearer than ``best`` on one owner's wood and leaves (owner space):
    (found, t, leaf or -1, face, unit normal in owner space)."""
    found = False
    leaf = int(-1)
    face = int(-1)
    normal = wp.vec3(0.0, 0.0, 0.0)
    if wood_root != EMPTY:
        h = wp.mesh_query_ray(wood, o, d, best, wood_root)
        if h.result and h.t < best:
            found = True
            best = h.t
            face = h.face
            normal = h.normal
    if leaf_root != EMPTY:
        q = wp.bvh_query_ray(leaf_bvh, o, d, leaf_root)
        j = int(0)
        while wp.bvh_query_next(q, j, best):
            a = leaf_inv[j]
            h = wp.mesh_query_ray(shapes, a * (o - leaf_shift[j]), a * d, best, leaf_shape[j])
            if h.result and h.t < best:
                found = True
                best = h.t
                leaf = j
                face = h.face
                normal = wp.normalize(wp.transpose(a) * h.normal)
    return found, best, leaf, face, normal


@wp.func
def _box_entry(lo: wp.vec3, hi: wp.vec3, o: wp.vec3, d: wp.vec3) -> float:
    """Distance at which a ray enters a box (a huge value when it misses)."""
    if lo[0] > hi[0]:  # an empty box: an instance that cannot be entered
        return 1.0e30
    t0 = float(0.0)
    t1 = float(1.0e30)
    for a in range(3):
        if wp.abs(d[a]) < 1.0e-30:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0e30
        else:
            u = (lo[a] - o[a]) / d[a]
            v = (hi[a] - o[a]) / d[a]
            t0 = wp.max(t0, wp.min(u, v))
            t1 = wp.min(t1, wp.max(u, v))
    if t0 > t1:
        return 1.0e30
    return t0


@wp.func
def _tree(
    k: int,
    wood: wp.uint64,
    wood_roots: wp.array[wp.int32],
    leaf_bvh: wp.uint64,
    leaf_roots: wp.array[wp.int32],
    leaf_inv: wp.array[wp.mat33],
    leaf_shift: wp.array[wp.vec3],
    leaf_shape: wp.array[wp.int32],
    shapes: wp.uint64,
    inst_inv: wp.array[wp.mat33],
    inst_shift: wp.array[wp.vec3],
    inst_proto: wp.array[wp.int32],
    o: wp.vec3,
    d: wp.vec3,
    best: float,
):
    """Nearest hit nearer than ``best`` in tree instance ``k`` (its prototype's wood and
    leaves, the ray moved into its space): (found, t, leaf, face, unit world normal)."""
    a = inst_inv[k]
    g = inst_proto[k] + 1
    hit, t, lf, fc, nl = _part(
        wood, wood_roots[g], leaf_bvh, leaf_roots[g], leaf_inv, leaf_shift, leaf_shape,
        shapes, a * (o - inst_shift[k]), a * d, best,
    )  # fmt: skip
    return hit, t, lf, fc, wp.normalize(wp.transpose(a) * nl)


@wp.kernel
def first_hits(
    origins: wp.array[wp.vec3],
    directions: wp.array[wp.vec3],
    limits: wp.array[float],
    wood: wp.uint64,
    wood_roots: wp.array[wp.int32],
    leaf_bvh: wp.uint64,
    leaf_roots: wp.array[wp.int32],
    leaf_inv: wp.array[wp.mat33],
    leaf_shift: wp.array[wp.vec3],
    leaf_shape: wp.array[wp.int32],
    shapes: wp.uint64,
    top: wp.uint64,
    inst_lo: wp.array[wp.vec3],
    inst_hi: wp.array[wp.vec3],
    looped: int,
    n_instances: int,
    inst_inv: wp.array[wp.mat33],
    inst_shift: wp.array[wp.vec3],
    inst_proto: wp.array[wp.int32],
    out_t: wp.array[float],
    out_instance: wp.array[wp.int32],
    out_leaf: wp.array[wp.int32],
    out_face: wp.array[wp.int32],
    out_normal: wp.array[wp.vec3],
):
    """Each ray's nearest hit within its limit: distance (the limit when none), tree
    instance (-1: the world's own), leaf (-1: wood), face, unit world normal. The trees are
    found by a BVH query over their world boxes, or (``looped``, as CUDA needs: one BVH
    query open at a time) by a loop over the boxes."""
    i = wp.tid()
    o = origins[i]
    d = directions[i]
    found, best, leaf, face, normal = _part(
        wood, wood_roots[0], leaf_bvh, leaf_roots[0], leaf_inv, leaf_shift, leaf_shape,
        shapes, o, d, limits[i],
    )  # fmt: skip
    instance = int(-1)
    if n_instances > 0 and looped != 0:
        for k in range(n_instances):
            if _box_entry(inst_lo[k], inst_hi[k], o, d) < best:
                hit, t, lf, fc, nl = _tree(
                    k, wood, wood_roots, leaf_bvh, leaf_roots, leaf_inv, leaf_shift,
                    leaf_shape, shapes, inst_inv, inst_shift, inst_proto, o, d, best,
                )  # fmt: skip
                if hit:
                    found, best, instance, leaf, face, normal = True, t, k, lf, fc, nl
    if n_instances > 0 and looped == 0:
        q = wp.bvh_query_ray(top, o, d)
        k = int(0)
        while wp.bvh_query_next(q, k, best):
            hit, t, lf, fc, nl = _tree(
                k, wood, wood_roots, leaf_bvh, leaf_roots, leaf_inv, leaf_shift,
                leaf_shape, shapes, inst_inv, inst_shift, inst_proto, o, d, best,
            )  # fmt: skip
            if hit:
                found, best, instance, leaf, face, normal = True, t, k, lf, fc, nl
    out_t[i] = best
    out_instance[i] = instance
    out_leaf[i] = leaf
    if not found:
        face = -1
    out_face[i] = face
    out_normal[i] = normal


@wp.kernel
def mesh_roots(mesh: wp.uint64, groups: wp.array[wp.int32], out: wp.array[wp.int32]):
    """BVH root of each listed group of a grouped mesh."""
    i = wp.tid()
    out[i] = wp.mesh_get_group_root(mesh, groups[i])


@wp.kernel
def bvh_roots(bvh: wp.uint64, groups: wp.array[wp.int32], out: wp.array[wp.int32]):
    """Root of each listed group of a grouped BVH."""
    i = wp.tid()
    out[i] = wp.bvh_get_group_root(bvh, groups[i])

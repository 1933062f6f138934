"""numba code that drives Embree 4: the loop that casts rays on every core, and the callbacks of
the leaf geometry that moves a ray into a leaf's frame and casts it at the leaf's shape.

Compiled on first use and cached on disk (numba's cache), so later processes load it in well
under a second. Nothing here holds data: every array is reached through addresses that
:class:`~usdforest.sensors.raycast.SceneCaster` keeps alive, so the cached machine code does
not depend on a scene.

Layout of a leaf geometry's user block (int64 words), one per owner (the world, a tree
prototype): ``[inverse, shift, scene, first, rtcIntersect1, boxes, shape, shape_boxes]`` - the
addresses of the leaves' float32 3x3 inverse linear parts (row-major, ``local = inv @ (x -
shift)``), their float32 shifts, their shapes' Embree scenes (int64 handles), this owner's
first leaf, the address of ``rtcIntersect1``, the leaves' float32 boxes in the owner's space
(lower xyz, upper xyz), their shapes (int64 indices) and the shapes' float32 boxes in their
own space.
"""

from __future__ import annotations

import numba
from llvmlite import ir
from numba import carray, cfunc, njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

INVALID = 0xFFFFFFFF
BLOCK = 64  # rays per task of the parallel loop


def _pointer_to(dtype):
    @intrinsic
    def cast(typingctx, addr):
        if not isinstance(addr, types.Integer):
            return None
        ptr = types.CPointer(dtype)

        def codegen(context, builder, sig, args):
            return builder.inttoptr(args[0], context.get_value_type(ptr))

        return ptr(addr), codegen

    return cast


_f32 = _pointer_to(types.float32)
_u32 = _pointer_to(types.uint32)
_i32 = _pointer_to(types.int32)
_i64 = _pointer_to(types.int64)


@intrinsic
def _scratch(typingctx):
    """Address of 96 bytes on the stack, 16-byte aligned: one RTCRayHit."""

    def codegen(context, builder, sig, args):
        i64 = ir.IntType(64)
        raw = cgutils.alloca_once(builder, ir.ArrayType(ir.IntType(8), 128))
        at = builder.add(builder.ptrtoint(raw, i64), ir.Constant(i64, 15))
        return builder.and_(at, ir.Constant(i64, ~15))

    return types.int64(), codegen


@intrinsic
def _intersect1(typingctx, fn, scene, rayhit):
    """``rtcIntersect1(scene, rayhit, NULL)`` through the function's address ``fn``."""
    if not all(isinstance(a, types.Integer) for a in (fn, scene, rayhit)):
        return None

    def codegen(context, builder, sig, args):
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p, i8p])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        scene, rayhit = (builder.inttoptr(a, i8p) for a in args[1:])
        builder.call(f, [scene, rayhit, ir.Constant(i8p, None)])
        return context.get_dummy_value()

    return types.void(fn, scene, rayhit), codegen


@njit(inline="always")
def _ray(q, qu, ox, oy, oz, dx, dy, dz, tfar):
    q[0], q[1], q[2], q[3] = ox, oy, oz, 0.0
    q[4], q[5], q[6], q[7] = dx, dy, dz, 0.0
    q[8] = tfar
    qu[9], qu[10], qu[11] = INVALID, 0, 0
    qu[17], qu[18], qu[19], qu[20] = INVALID, INVALID, INVALID, INVALID


@njit(inline="always")
def _enters(box, q):
    """Whether ray ``q`` (an RTCRayHit's words) passes through ``box`` within its extent."""
    t0, t1 = q[3], q[8]
    for a in range(3):
        o, d = q[a], q[4 + a]
        if d == 0.0:
            if o < box[a] or o > box[3 + a]:
                return False
            continue
        u = (box[a] - o) / d
        v = (box[3 + a] - o) / d
        if u > v:
            u, v = v, u
        t0 = max(t0, u)
        t1 = min(t1, v)
    return t0 <= t1


def _leaf_bounds(args):
    w = carray(_i64(args), 3)
    prim = carray(_u32(args), 4)[2]
    user = carray(_i64(w[0]), 8)
    box = carray(_f32(user[5] + (user[3] + prim) * 24), 6)
    out = carray(_f32(w[2]), 8)
    out[0], out[1], out[2] = box[0], box[1], box[2]
    out[4], out[5], out[6] = box[3], box[4], box[5]


def _leaf_intersect(args):
    w = carray(_i64(args), 6)
    u = carray(_u32(args), 12)
    if carray(_i32(w[0]), 1)[0] == 0:
        return
    user = carray(_i64(w[1]), 8)
    prim = u[4]
    j = user[3] + prim
    a = carray(_f32(user[0] + j * 36), 9)
    s = carray(_f32(user[1] + j * 12), 3)
    shape = carray(_i64(user[2] + j * 8), 1)[0]
    rh = carray(_f32(w[4]), 24)
    rhu = carray(_u32(w[4]), 24)
    px, py, pz = rh[0] - s[0], rh[1] - s[1], rh[2] - s[2]
    dx, dy, dz = rh[4], rh[5], rh[6]
    buf = _scratch()
    q = carray(_f32(buf), 24)
    qu = carray(_u32(buf), 24)
    _ray(
        q, qu,
        a[0] * px + a[1] * py + a[2] * pz,
        a[3] * px + a[4] * py + a[5] * pz,
        a[6] * px + a[7] * py + a[8] * pz,
        a[0] * dx + a[1] * dy + a[2] * dz,
        a[3] * dx + a[4] * dy + a[5] * dz,
        a[6] * dx + a[7] * dy + a[8] * dz,
        rh[8],
    )  # fmt: skip
    q[3] = rh[3]
    # the shape's own box, tighter than the leaf's box in the owner's space: most rays that
    # enter the latter miss the former, and are spared a call into Embree
    k = carray(_i64(user[6] + j * 8), 1)[0]
    if not _enters(carray(_f32(user[7] + k * 24), 6), q):
        return
    _intersect1(user[4], shape, buf)
    if qu[18] == INVALID:
        return
    nx, ny, nz = q[12], q[13], q[14]
    ctx = carray(_u32(w[3]), 2)
    rh[8] = q[8]
    # a normal goes back to the owner's space through the inverse's transpose
    rh[12] = a[0] * nx + a[3] * ny + a[6] * nz
    rh[13] = a[1] * nx + a[4] * ny + a[7] * nz
    rh[14] = a[2] * nx + a[5] * ny + a[8] * nz
    rhu[15] = qu[17]  # the face within the leaf's shape, kept in u's slot
    rh[16] = 0.0
    rhu[17] = prim
    rhu[18] = u[11]
    rhu[19] = ctx[0]
    rhu[20] = ctx[1]


_ARGS = types.void(types.int64)
leaf_bounds = cfunc(_ARGS, cache=True)(_leaf_bounds)
leaf_intersect = cfunc(_ARGS, cache=True)(_leaf_intersect)


@njit(parallel=True, cache=True)
def cast(fn, scene, o, d, limit, t, geom, prim, inst, face, normal):
    """First hits of rays ``o``, ``d`` (float32 (n, 3)) within ``limit`` on Embree ``scene``:
    distance (``limit`` when none), geometry (-1: none), primitive, instance (-1: none), face
    within a leaf's shape, and the hit's normal in the space of what was hit."""
    n = o.shape[0]
    for b in prange((n + BLOCK - 1) // BLOCK):
        buf = _scratch()
        q = carray(_f32(buf), 24)
        qu = carray(_u32(buf), 24)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            _ray(q, qu, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], limit[i])
            _intersect1(fn, scene, buf)
            t[i] = q[8]
            if qu[18] == INVALID:
                geom[i] = -1
                continue
            geom[i] = qu[18]
            prim[i] = qu[17]
            inst[i] = -1 if qu[19] == INVALID else qu[20]
            face[i] = qu[15]
            normal[i, 0], normal[i, 1], normal[i, 2] = q[12], q[13], q[14]


def threads() -> int:
    """Threads the casting loop runs on."""
    return numba.get_num_threads()

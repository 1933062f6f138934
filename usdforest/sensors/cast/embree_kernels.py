"""numba code that drives Embree 4: the loop that casts rays on every core, and the callbacks of
the leaf geometry that moves a ray into a leaf's frame and casts it at the leaf's shape.

Compiled on first use and cached on disk (numba's cache), so later processes load it in well
under a second. Nothing here holds data: every array is reached through addresses that
:class:`~usdforest.sensors.cast.raycast.SceneCaster` keeps alive, so the cached machine code does
not depend on a scene.

Layout of a leaf geometry's user block (int64 words), one per owner (the world, a tree
prototype): ``[inverse, shift, scene, first, rtcIntersect1, boxes, shape, shape_boxes,
rtcIntersect8, turns]`` - the
addresses of the leaves' float32 3x3 inverse linear parts (row-major, ``local = inv @ (x -
shift)``), their float32 shifts, their shapes' Embree scenes (int64 handles), this owner's
first leaf, the address of ``rtcIntersect1``, the leaves' float32 boxes in the owner's space
(lower xyz, upper xyz), their shapes (int64 indices), the shapes' float32 boxes in their
own space, the address of ``rtcIntersect8``, and the address of one int64 that holds the
address of the shapes' turns (0: none): per shape twelve float32, a row-major 3x3 and a
shift, which move a ray from the leaf's frame as placed to its shape as it has turned since
(:mod:`usdforest.sensors.scene.turns`; the caster sets it before each cast).
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import carray, cfunc, njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

INVALID = 0xFFFFFFFF
BLOCK = 64  # rays per task of the parallel loop
WIDTH = 8  # rays of a packet (rtcIntersect8)
PACKET_BYTES = 64 + 21 * 4 * WIDTH  # valid[8] (padded to 64) and an RTCRayHit8


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


def _stack(size: int, align: int):
    @intrinsic
    def scratch(typingctx):
        def codegen(context, builder, sig, args):
            i64 = ir.IntType(64)
            raw = cgutils.alloca_once(builder, ir.ArrayType(ir.IntType(8), size + align))
            at = builder.add(builder.ptrtoint(raw, i64), ir.Constant(i64, align - 1))
            return builder.and_(at, ir.Constant(i64, -align))

        return types.int64(), codegen

    return scratch


_scratch = _stack(96, 16)  # one RTCRayHit
_affine = _stack(48, 16)  # a leaf's inverse with its shape's turn
_packet = _stack(PACKET_BYTES, 64)  # valid[8] then an RTCRayHit8


def _codegen_call(context, builder, sig, values):
    """Call ``values[0]`` (a function's address) with the other values as pointers and a
    trailing NULL (Embree's default arguments)."""
    i8p = ir.IntType(8).as_pointer()
    fnty = ir.FunctionType(ir.VoidType(), [i8p] * len(values))
    f = builder.inttoptr(values[0], fnty.as_pointer())
    builder.call(f, [*(builder.inttoptr(v, i8p) for v in values[1:]), ir.Constant(i8p, None)])
    return context.get_dummy_value()


@intrinsic
def _intersect1(typingctx, fn, scene, rayhit):
    """``rtcIntersect1(scene, rayhit, NULL)`` through the function's address ``fn``."""
    if all(isinstance(a, types.Integer) for a in (fn, scene, rayhit)):
        return types.void(fn, scene, rayhit), _codegen_call
    return None


@intrinsic
def _intersect8(typingctx, fn, valid, scene, rayhit):
    """``rtcIntersect8(valid, scene, rayhit, NULL)`` through the function's address ``fn``."""
    if all(isinstance(a, types.Integer) for a in (fn, valid, scene, rayhit)):
        return types.void(fn, valid, scene, rayhit), _codegen_call
    return None


@njit(inline="always")
def _ray(q, qu, ox, oy, oz, dx, dy, dz, tfar):
    q[0], q[1], q[2], q[3] = ox, oy, oz, 0.0
    q[4], q[5], q[6], q[7] = dx, dy, dz, 0.0
    q[8] = tfar
    qu[9], qu[10], qu[11] = INVALID, 0, 0
    qu[17], qu[18], qu[19], qu[20] = INVALID, INVALID, INVALID, INVALID


def _leaf_bounds(args):
    w = carray(_i64(args), 3)
    prim = carray(_u32(args), 4)[2]
    user = carray(_i64(w[0]), 10)
    box = carray(_f32(user[5] + (user[3] + prim) * 24), 6)
    out = carray(_f32(w[2]), 8)
    out[0], out[1], out[2] = box[0], box[1], box[2]
    out[4], out[5], out[6] = box[3], box[4], box[5]


@njit(inline="always")
def _to_leaf(a, s, rh, n, i, q, m, k):
    """Ray ``i`` of ``rh`` (width ``n``) moved into a leaf's frame (``a``, ``s``, then the
    shift ``a[9:12]``) as ray ``k`` of ``q`` (width ``m``), its extent kept."""
    px, py, pz = rh[i] - s[0], rh[n + i] - s[1], rh[2 * n + i] - s[2]
    dx, dy, dz = rh[4 * n + i], rh[5 * n + i], rh[6 * n + i]
    q[k] = a[0] * px + a[1] * py + a[2] * pz + a[9]
    q[m + k] = a[3] * px + a[4] * py + a[5] * pz + a[10]
    q[2 * m + k] = a[6] * px + a[7] * py + a[8] * pz + a[11]
    q[3 * m + k] = rh[3 * n + i]
    q[4 * m + k] = a[0] * dx + a[1] * dy + a[2] * dz
    q[5 * m + k] = a[3] * dx + a[4] * dy + a[5] * dz
    q[6 * m + k] = a[6] * dx + a[7] * dy + a[8] * dz
    q[7 * m + k] = 0.0
    q[8 * m + k] = rh[8 * n + i]


@njit(inline="always")
def _enters(box, q, m, k):
    """Whether ray ``k`` of ``q`` (width ``m``) passes through ``box`` within its extent."""
    t0, t1 = q[3 * m + k], q[8 * m + k]
    for a in range(3):
        o, d = q[a * m + k], q[(4 + a) * m + k]
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


@njit(inline="always")
def _back(a, rh, rhu, n, i, q, qu, m, k, prim, geom, ctx):
    """The hit of ray ``k`` of ``q`` (the leaf's frame, width ``m``) as ray ``i``'s of ``rh``
    (width ``n``): distance, normal through the inverse's transpose, leaf, face, instance."""
    nx, ny, nz = q[12 * m + k], q[13 * m + k], q[14 * m + k]
    h = 12 * n + i
    rh[8 * n + i] = q[8 * m + k]
    rh[h] = a[0] * nx + a[3] * ny + a[6] * nz
    rh[h + n] = a[1] * nx + a[4] * ny + a[7] * nz
    rh[h + 2 * n] = a[2] * nx + a[5] * ny + a[8] * nz
    rhu[h + 3 * n] = qu[17 * m + k]  # the face within the leaf's shape, kept in u's slot
    rh[h + 4 * n] = 0.0
    rhu[h + 5 * n] = prim
    rhu[h + 6 * n] = geom
    rhu[h + 7 * n] = ctx[0]
    rhu[h + 8 * n] = ctx[1]


@njit(inline="always")
def _blank(qu, m, k):
    qu[9 * m + k], qu[10 * m + k], qu[11 * m + k] = INVALID, 0, 0
    for f in range(17, 21):
        qu[f * m + k] = INVALID


def _leaf_intersect(args):
    """One leaf met by ``N`` rays (1 for ``rtcIntersect1``, up to a packet's width for
    ``rtcIntersect8``): the rays moved into the leaf's frame and cast at its shape, one by one
    or as one packet. Rays and hits are Embree's structure-of-arrays: field ``f`` of ray ``i``
    at ``f * N + i``, the hit's fields after the ray's 12."""
    w = carray(_i64(args), 6)
    u = carray(_u32(args), 12)
    n = u[10]
    valid = carray(_i32(w[0]), n)
    user = carray(_i64(w[1]), 10)
    prim = u[4]
    j = user[3] + prim
    inv = carray(_f32(user[0] + j * 36), 9)
    s = carray(_f32(user[1] + j * 12), 3)
    shape = carray(_i64(user[2] + j * 8), 1)[0]
    k_shape = carray(_i64(user[6] + j * 8), 1)[0]
    # the leaf's inverse, then its shape's turn since it was placed (none: the identity)
    a = carray(_f32(_affine()), 12)
    turns = carray(_i64(user[9]), 1)[0]
    if turns == 0:
        for c in range(9):
            a[c] = inv[c]
        a[9], a[10], a[11] = 0.0, 0.0, 0.0
    else:
        e = carray(_f32(turns + k_shape * 48), 12)
        for r in range(3):
            for c in range(3):
                a[3 * r + c] = (
                    e[3 * r] * inv[c] + e[3 * r + 1] * inv[3 + c] + e[3 * r + 2] * inv[6 + c]
                )
        a[9], a[10], a[11] = e[9], e[10], e[11]
    # the shape's own box, tighter than the leaf's box in the owner's space: most rays that
    # enter the latter miss the former, and are spared a call into Embree
    box = carray(_f32(user[7] + k_shape * 24), 6)
    rh = carray(_f32(w[4]), 21 * n)
    rhu = carray(_u32(w[4]), 21 * n)
    ctx = carray(_u32(w[3]), 2)
    if n == 1 or n > WIDTH:
        buf = _scratch()
        q = carray(_f32(buf), 24)
        qu = carray(_u32(buf), 24)
        for i in range(n):
            if valid[i] == 0:
                continue
            _to_leaf(a, s, rh, n, i, q, 1, 0)
            if not _enters(box, q, 1, 0):
                continue
            _blank(qu, 1, 0)
            _intersect1(user[4], shape, buf)
            if qu[18] != INVALID:
                _back(a, rh, rhu, n, i, q, qu, 1, 0, prim, u[11], ctx)
        return
    pbuf = _packet()
    pv = carray(_i32(pbuf), WIDTH)
    q = carray(_f32(pbuf + 64), 21 * WIDTH)
    qu = carray(_u32(pbuf + 64), 21 * WIDTH)
    live = False
    for k in range(WIDTH):
        pv[k] = 0
        if k < n and valid[k] != 0:
            _to_leaf(a, s, rh, n, k, q, WIDTH, k)
            if _enters(box, q, WIDTH, k):
                pv[k] = -1
                live = True
                _blank(qu, WIDTH, k)
    if not live:
        return
    _intersect8(user[8], pbuf, shape, pbuf + 64)
    for k in range(n):
        if pv[k] != 0 and qu[18 * WIDTH + k] != INVALID:
            _back(a, rh, rhu, n, k, q, qu, WIDTH, k, prim, u[11], ctx)


_ARGS = types.void(types.int64)
leaf_bounds = cfunc(_ARGS, cache=True)(_leaf_bounds)
leaf_intersect = cfunc(_ARGS, cache=True)(_leaf_intersect)


@njit(inline="always")
def _store(i, t, geom, prim, inst, face, normal, q, qu, k, n):
    """Ray ``k`` of the (structure-of-arrays, width ``n``) ray-hit ``q`` as hit ``i``."""
    t[i] = q[8 * n + k]
    g = qu[18 * n + k]
    if g == INVALID:
        geom[i] = -1
        return
    geom[i] = g
    prim[i] = qu[17 * n + k]
    inst[i] = -1 if qu[19 * n + k] == INVALID else qu[20 * n + k]
    face[i] = qu[15 * n + k]
    normal[i, 0], normal[i, 1], normal[i, 2] = q[12 * n + k], q[13 * n + k], q[14 * n + k]


@njit(parallel=True, cache=True)
def cast(fn, scene, o, d, limit, t, geom, prim, inst, face, normal):
    """First hits of rays ``o``, ``d`` (float32 (n, 3)) within ``limit`` on Embree ``scene``
    (``fn``: the address of ``rtcIntersect1``): distance (``limit`` when none), geometry (-1:
    none), primitive, instance (-1: none), face within a leaf's shape, and the hit's normal
    in the space of what was hit."""
    n = o.shape[0]
    for b in prange((n + BLOCK - 1) // BLOCK):
        buf = _scratch()
        q = carray(_f32(buf), 24)
        qu = carray(_u32(buf), 24)
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            _ray(q, qu, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], limit[i])
            _intersect1(fn, scene, buf)
            _store(i, t, geom, prim, inst, face, normal, q, qu, 0, 1)


@njit(parallel=True, cache=True)
def cast_packets(fn, scene, o, d, limit, width, t, geom, prim, inst, face, normal):
    """:func:`cast` for rays that come in groups of ``width`` (at most 8: the sub-rays of a
    lidar's beam, nearly parallel), each group one packet (``fn``: the address of
    ``rtcIntersect8``), so Embree walks the trees once for the group."""
    groups = o.shape[0] // width
    for b in prange((groups + BLOCK - 1) // BLOCK):
        buf = _packet()
        valid = carray(_i32(buf), WIDTH)
        q = carray(_f32(buf + 64), 21 * WIDTH)
        qu = carray(_u32(buf + 64), 21 * WIDTH)
        for g in range(b * BLOCK, min(groups, (b + 1) * BLOCK)):
            for k in range(WIDTH):
                i = g * width + min(k, width - 1)
                valid[k] = -1 if k < width else 0
                q[k], q[WIDTH + k], q[2 * WIDTH + k] = o[i, 0], o[i, 1], o[i, 2]
                q[3 * WIDTH + k] = 0.0
                q[4 * WIDTH + k], q[5 * WIDTH + k], q[6 * WIDTH + k] = d[i, 0], d[i, 1], d[i, 2]
                q[7 * WIDTH + k] = 0.0
                q[8 * WIDTH + k] = limit[i]
                qu[9 * WIDTH + k], qu[10 * WIDTH + k], qu[11 * WIDTH + k] = INVALID, 0, 0
                for f in range(17, 21):
                    qu[f * WIDTH + k] = INVALID
            _intersect8(fn, buf, scene, buf + 64)
            for k in range(width):
                _store(g * width + k, t, geom, prim, inst, face, normal, q, qu, k, WIDTH)


def threads() -> int:
    """Threads the casting loop runs on."""
    return numba.get_num_threads()


@njit(parallel=True, cache=True)
def resolve(
    geom, prim, entry, sub, normal, entry_owner, entry_inst, wood_first, leaf_first,
    shape_first, leaf_shape, inst_inv,
):  # fmt: skip
    """What :func:`cast` found, in the scene's global numbering: (leaf, face, instance, unit
    world normal) of each ray; -1 (and a zero normal) where it hit nothing. Geometry 0 of an
    owner is its wood, geometry 1 its leaves (``sub``: the face within the leaf's shape); a
    normal in a tree's space goes to the world through its inverse's transpose."""
    n = geom.shape[0]
    leaf = np.full(n, -1, np.int64)
    face = np.full(n, -1, np.int64)
    instance = np.full(n, -1, np.int64)
    out = np.zeros((n, 3), np.float32)
    for i in prange(n):
        if geom[i] < 0:
            continue
        owner = entry_owner[entry[i]]
        if geom[i] == 0:
            face[i] = wood_first[owner] + prim[i]
        else:
            lf = leaf_first[owner] + prim[i]
            leaf[i] = lf
            face[i] = shape_first[leaf_shape[lf]] + sub[i]
        k = entry_inst[entry[i]]
        instance[i] = k
        x, y, z = np.float64(normal[i, 0]), np.float64(normal[i, 1]), np.float64(normal[i, 2])
        if k >= 0:
            a = inst_inv[k]
            x, y, z = (
                np.float64(a[0, 0]) * x + np.float64(a[1, 0]) * y + np.float64(a[2, 0]) * z,
                np.float64(a[0, 1]) * x + np.float64(a[1, 1]) * y + np.float64(a[2, 1]) * z,
                np.float64(a[0, 2]) * x + np.float64(a[1, 2]) * y + np.float64(a[2, 2]) * z,
            )
        r = max(np.sqrt(x * x + y * y + z * z), 1e-30)
        out[i, 0], out[i, 1], out[i, 2] = x / r, y / r, z / r
    return leaf, face, instance, out

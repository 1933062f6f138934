"""Embree 4 through ctypes: the library the ``embreex`` wheel installs, beyond what its Python
binding exposes (instance arrays, user geometries).

``embreex`` binds Embree's triangle meshes only, but the shared library it ships
(``embreex.libs/libembree4-<hash>.so.4``) is a whole Embree 4.4. This module finds that file,
declares the handful of functions :class:`~usdforest.sensors.twolevel.TwoLevelCaster` needs,
and checks at load time that the library behaves as the caster assumes (one instance level,
instance arrays that report which instance was hit).
"""

from __future__ import annotations

import ctypes
import functools
import importlib.util
import threading
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.sensors.cast.rayscene import RawHits, RayScene, outward32

INVALID = 0xFFFFFFFF  # RTC_INVALID_GEOMETRY_ID
# enum values of Embree 4's public headers (rtcore_common.h, rtcore_geometry.h, rtcore_buffer.h)
GEOMETRY_TRIANGLE = 0
GEOMETRY_USER = 120
GEOMETRY_INSTANCE_ARRAY = 122
BUFFER_INDEX = 0
BUFFER_VERTEX = 1
BUFFER_TRANSFORM = 23
FORMAT_UINT = 0x5001
FORMAT_UINT3 = 0x5003
FORMAT_FLOAT3 = 0x9003
FORMAT_FLOAT3X4_ROW_MAJOR = 0x9134
# RTC_BUILD_QUALITY_MEDIUM: builds the default forest 0.7 s sooner than HIGH, rays 1-3 % slower
BUILD_QUALITY = 1
# An RTCRayHit for one ray, as 32-bit words: ray (org, tnear, dir, time, tfar, mask, id,
# flags), then hit (Ng, u, v, primID, geomID, instID[1], instPrimID[1]); 96 bytes, 16-aligned.
RAYHIT_WORDS = 24

_P, _U, _I, _S = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t
_SIGNATURES = {  # name: (result, arguments), as Embree 4's headers declare them
    "rtcNewDevice": (_P, [ctypes.c_char_p]),
    "rtcGetDeviceError": (_I, [_P]),
    "rtcGetDeviceLastErrorMessage": (ctypes.c_char_p, [_P]),
    "rtcNewScene": (_P, [_P]),
    "rtcSetSceneBuildQuality": (None, [_P, _I]),
    "rtcCommitScene": (None, [_P]),
    "rtcReleaseScene": (None, [_P]),
    "rtcNewGeometry": (_P, [_P, _I]),
    "rtcSetSharedGeometryBuffer": (None, [_P, _I, _U, _I, _P, _S, _S, _S]),
    "rtcSetGeometryInstancedScenes": (None, [_P, _P, _S]),
    "rtcSetGeometryUserPrimitiveCount": (None, [_P, _U]),
    "rtcSetGeometryUserData": (None, [_P, _P]),
    "rtcSetGeometryBoundsFunction": (None, [_P, _P, _P]),
    "rtcSetGeometryIntersectFunction": (None, [_P, _P]),
    "rtcCommitGeometry": (None, [_P]),
    "rtcAttachGeometryByID": (None, [_P, _P, _U]),
    "rtcReleaseGeometry": (None, [_P]),
    "rtcIntersect1": (None, [_P, _P, _P]),
    "rtcIntersect8": (None, [_P, _P, _P, _P]),
}


def _candidates() -> list[Path]:
    """Where wheels put the Embree 4 library beside ``embreex`` (Linux, macOS, Windows)."""
    spec = importlib.util.find_spec("embreex")
    if spec is None or spec.origin is None:
        return []
    pkg = Path(spec.origin).parent
    found: list[Path] = []
    for folder in (pkg.parent / "embreex.libs", pkg / ".dylibs", pkg):
        for pattern in ("libembree4*.so*", "libembree4*.dylib", "embree4*.dll"):
            found += sorted(folder.glob(pattern))
    return found


class Embree:
    """The Embree 4 library: its functions by name, one device, and error checks."""

    def __init__(self, path: Path):
        self.path = path
        self.lib = ctypes.CDLL(str(path))
        for name, (res, args) in _SIGNATURES.items():
            f = getattr(self.lib, name)
            f.restype, f.argtypes = res, args
        self.device = self.lib.rtcNewDevice(None)
        if not self.device:
            raise UsdForestError(f"Embree ({path.name}): cannot create a device")
        self.intersect1 = ctypes.cast(self.lib.rtcIntersect1, ctypes.c_void_p).value
        self.intersect8 = ctypes.cast(self.lib.rtcIntersect8, ctypes.c_void_p).value

    def __getattr__(self, name: str):
        return getattr(self.lib, name)

    def check(self, what: str) -> None:
        """Raise :class:`UsdForestError` naming ``what`` if the device reports an error."""
        code = self.lib.rtcGetDeviceError(self.device)
        if code:
            msg = self.lib.rtcGetDeviceLastErrorMessage(self.device) or b""
            raise UsdForestError(f"Embree: {what} failed (error {code}: {msg.decode()})")

    def triangles(self, scene: int, vertices: np.ndarray, n: int, geom_id: int) -> tuple:
        """Attach ``n`` triangles (``vertices``: their corners as flat float32, padded) to
        ``scene`` under ``geom_id``, shared: the arrays returned must outlive the scene."""
        g = self.lib.rtcNewGeometry(self.device, GEOMETRY_TRIANGLE)
        idx = np.arange(3 * n, dtype=np.uint32)
        self.lib.rtcSetSharedGeometryBuffer(
            g, BUFFER_VERTEX, 0, FORMAT_FLOAT3, vertices.ctypes.data, 0, 12, 3 * n
        )
        self.lib.rtcSetSharedGeometryBuffer(
            g, BUFFER_INDEX, 0, FORMAT_UINT3, idx.ctypes.data, 0, 12, n
        )
        self.lib.rtcCommitGeometry(g)
        self.lib.rtcAttachGeometryByID(scene, g, geom_id)
        self.lib.rtcReleaseGeometry(g)
        return vertices, idx

    def scene(self) -> int:
        s = self.lib.rtcNewScene(self.device)
        self.lib.rtcSetSceneBuildQuality(s, BUILD_QUALITY)
        return s


@functools.cache
def embree() -> Embree:
    """The Embree 4 library of the installed ``embreex`` wheel (found once per process)."""
    paths = _candidates()
    if not paths:
        raise UsdForestError(
            "no Embree 4 library found beside the embreex package (pip install embreex)"
        )
    errors = []
    for path in paths:
        try:
            lib = Embree(path)
        except (OSError, AttributeError) as exc:
            errors.append(f"{path.name}: {exc}")
            continue
        _self_check(lib)
        return lib
    raise UsdForestError("cannot load Embree 4: " + "; ".join(errors))


def _self_check(lib: Embree) -> None:
    """Cast one ray through a two-entry instance array of one triangle, through ctypes alone:
    the hit must be the second entry's, at its distance, reported in ``instPrimID``, as the
    caster reads hits. A library built otherwise (no instance arrays, several instance levels,
    another hit layout) is refused by name instead of casting wrong hits."""
    tri, n = _padded(np.array([[[0, -1, -1], [0, 1, -1], [0, 0, 1]]], np.float32))
    inner = lib.scene()
    kept = lib.triangles(inner, tri, n, 0)
    lib.rtcCommitScene(inner)
    top = lib.scene()
    geom = lib.rtcNewGeometry(lib.device, GEOMETRY_INSTANCE_ARRAY)
    table = np.array([inner], np.uint64)
    xf = np.zeros((2, 3, 4), np.float32)
    xf[:, :, :3] = np.eye(3)
    xf[:, 0, 3] = [5.0, 10.0]
    idx = np.zeros(2, np.uint32)
    lib.rtcSetGeometryInstancedScenes(geom, table.ctypes.data, 1)
    lib.rtcSetSharedGeometryBuffer(
        geom, BUFFER_TRANSFORM, 0, FORMAT_FLOAT3X4_ROW_MAJOR, xf.ctypes.data, 0, 48, 2
    )
    lib.rtcSetSharedGeometryBuffer(geom, BUFFER_INDEX, 0, FORMAT_UINT, idx.ctypes.data, 0, 4, 2)
    lib.rtcCommitGeometry(geom)
    lib.rtcAttachGeometryByID(top, geom, 0)
    lib.rtcReleaseGeometry(geom)
    lib.rtcCommitScene(top)
    raw = np.zeros(RAYHIT_WORDS + 4, np.float32)  # room to align to 16 bytes
    at = (-raw.ctypes.data % 16) // 4
    ray = raw[at : at + RAYHIT_WORDS]
    words = ray.view(np.uint32)
    ray[:9] = [7.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 100.0]  # from x = 7 along +x
    words[9] = INVALID
    words[17:21] = INVALID
    lib.rtcIntersect1(top, ray.ctypes.data, None)
    got = (float(ray[8]), int(words[18]), int(words[19]), int(words[20]))
    lib.rtcReleaseScene(top)
    lib.rtcReleaseScene(inner)
    del kept
    lib.check("checking the library")
    if not self_check_hit(got):
        raise UsdForestError(
            f"Embree ({lib.path.name}) does not report instance-array hits as the ray caster "
            f"reads them (distance, geometry, instance, entry: {got}, expected (3.0, 0, 0, 1)); "
            "install the embreex wheel from PyPI (its Embree 4.4)"
        )


def self_check_hit(got: tuple[float, int, int, int]) -> bool:
    """Whether the self-check's hit (distance, geometry, instance, entry) is the one expected:
    the ids exactly, the distance 3 to a few float32 roundings (Embree's kernels differ by
    CPU: an AMD EPYC with AVX2 gives 3 less one ulp with every ISA Embree offers it, where
    the machines before gave 3, and every scan there was refused)."""
    return abs(got[0] - 3.0) <= 4 * float(np.spacing(np.float32(3.0))) and got[1:] == (0, 0, 1)


def _release(lib, scenes: list[int]) -> None:
    for s in reversed(scenes):
        lib.rtcReleaseScene(s)


class EmbreeCaster:
    """Raw first hits on a :class:`~usdforest.sensors.cast.rayscene.RayScene` with Embree 4, two
    instance levels kept.

    One Embree scene per leaf shape; one per owner (the world, each tree prototype) holding
    its wood triangles (geometry 0) and one user geometry of its leaves (geometry 1), whose
    primitives are the leaves' boxes and whose intersect callback moves the ray into the hit
    leaf's frame and casts it at that leaf's shape scene; and a top scene with one instance
    array placing the world and every tree. Embree allows one instance level; the leaf level
    is a fresh ``rtcIntersect1`` inside the callback, so memory grows with the prototypes'
    leaves, not with the trees. The loop over rays and the callbacks are numba code
    (:mod:`usdforest.sensors.cast.embree_kernels`) that runs on every core.
    """

    def __init__(self, rs: RayScene, progress: Callable[[str, int, int], None] | None = None):
        from usdforest.sensors.cast import embree_kernels as kern

        tick = progress or (lambda stage, done, total: None)
        tick("ray-casting scene", 0, rs.owners + 1)
        self._kern = kern
        self._rs = rs
        lib = embree()
        self._lib = lib
        scenes: list[int] = []
        self._scenes = scenes
        weakref.finalize(self, _release, lib.lib, scenes)
        keep: list = []  # arrays Embree reads in place, alive as long as the caster
        self._keep = keep

        def new_scene() -> int:
            s = lib.scene()
            scenes.append(s)
            return s

        # one scene per distinct shape: a windy forest's flutter classes repeat each leaf
        # shape under other prims (2,885 shapes of 93 meshes in the default forest)
        shape_scene = np.zeros(len(rs.shape_tri), np.int64)
        made: dict[bytes, int] = {}
        for k, tri in enumerate(rs.shape_tri):
            key = tri.tobytes()
            if key not in made:
                s = new_scene()
                if len(tri):
                    keep.append(lib.triangles(s, *_padded(tri), 0))
                lib.rtcCommitScene(s)
                made[key] = s
            shape_scene[k] = made[key]
        leaf_scene = shape_scene[rs.leaf_shape] if len(rs.leaf_shape) else np.zeros(0, np.int64)
        inv = np.ascontiguousarray(rs.leaf_inv, np.float32).reshape(-1, 9)
        shift = np.ascontiguousarray(rs.leaf_shift, np.float32).reshape(-1, 3)
        box = np.ascontiguousarray(np.concatenate([rs.leaf_lo, rs.leaf_hi], axis=1), np.float32)
        leaf_scene = np.ascontiguousarray(leaf_scene, np.int64)
        leaf_shape = np.ascontiguousarray(rs.leaf_shape, np.int64)
        shape_box = np.ascontiguousarray(
            np.concatenate(outward32(rs.shape_box[:, 0], rs.shape_box[:, 1]), axis=1), np.float32
        )
        keep += [inv, shift, box, leaf_scene, leaf_shape, shape_box]
        # the address of the shapes' turns the leaves' callbacks read (0: none), set by each
        # cast to its caster's (casters of one forest at other times share the prototypes)
        self._turns_cell = np.zeros(1, np.int64)
        self._casting = threading.Lock()
        keep.append(self._turns_cell)
        owner_scene = np.zeros(rs.owners, np.int64)
        for g in range(rs.owners):
            w0, w1 = rs.wood_first[g], rs.wood_first[g + 1]
            l0, l1 = rs.leaf_first[g], rs.leaf_first[g + 1]
            if w0 == w1 and l0 == l1:
                continue
            s = new_scene()
            if w1 > w0:
                keep.append(lib.triangles(s, *_padded(rs.wood[w0:w1]), 0))
            if l1 > l0:
                block = np.array(
                    [inv.ctypes.data, shift.ctypes.data, leaf_scene.ctypes.data, l0,
                     lib.intersect1, box.ctypes.data, leaf_shape.ctypes.data,
                     shape_box.ctypes.data, lib.intersect8, self._turns_cell.ctypes.data],
                    dtype=np.int64,
                )  # fmt: skip
                keep.append(block)
                geom = lib.rtcNewGeometry(lib.device, GEOMETRY_USER)
                lib.rtcSetGeometryUserPrimitiveCount(geom, int(l1 - l0))
                lib.rtcSetGeometryUserData(geom, block.ctypes.data)
                lib.rtcSetGeometryBoundsFunction(geom, kern.leaf_bounds.address, block.ctypes.data)
                lib.rtcSetGeometryIntersectFunction(geom, kern.leaf_intersect.address)
                lib.rtcCommitGeometry(geom)
                lib.rtcAttachGeometryByID(s, geom, 1)
                lib.rtcReleaseGeometry(geom)
            lib.rtcCommitScene(s)
            lib.check("building a prototype's scene")
            owner_scene[g] = s
            tick("ray-casting scene", g + 1, rs.owners + 1)
        self._owner_scene = owner_scene
        self._top_level(rs)
        tick("ray-casting scene", rs.owners + 1, rs.owners + 1)

    def moved(self, rs: RayScene) -> EmbreeCaster:
        """A caster of ``rs``, this one's ray scene with its trees placed anew
        (:meth:`RayScene.moved`): the prototypes' scenes are shared, the top level is built
        again (milliseconds)."""
        other = object.__new__(EmbreeCaster)
        other.__dict__.update(self.__dict__)
        other._base = self  # the prototypes' scenes live as long as this caster
        scenes: list[int] = []
        other._scenes = scenes
        weakref.finalize(other, _release, self._lib.lib, scenes)
        other._keep = []
        other._top_level(rs)
        return other

    def _top_level(self, rs: RayScene) -> None:
        """The top scene: the world (identity) and every tree that can be entered."""
        lib, owner_scene, keep = self._lib, self._owner_scene, self._keep
        self._rs = rs
        self._turns = (
            None if rs.shape_turn is None else np.ascontiguousarray(rs.shape_turn, np.float32)
        )
        world = [-1] if owner_scene[0] else []
        inst = np.flatnonzero(rs.inst_ok & (owner_scene[rs.inst_proto + 1] != 0))
        self._entry_inst = np.concatenate([world, inst]).astype(np.int64)
        self._entry_owner = np.concatenate([[0] * len(world), rs.inst_proto[inst] + 1]).astype(
            np.int64
        )
        used, index = np.unique(self._entry_owner, return_inverse=True)
        xf = np.zeros((len(self._entry_inst), 3, 4), np.float32)
        xf[:, :, :3] = np.eye(3, dtype=np.float32)
        if len(inst):  # object to world, column form
            xf[len(world) :, :, :3] = rs.inst_fwd[inst]
            xf[len(world) :, :, 3] = rs.inst_shift[inst]
        self._top = lib.scene()
        self._scenes.append(self._top)
        if len(xf):
            table = np.ascontiguousarray(owner_scene[used], np.uint64)
            idx = np.ascontiguousarray(index, np.uint32)
            keep += [table, idx, xf]
            geom = lib.rtcNewGeometry(lib.device, GEOMETRY_INSTANCE_ARRAY)
            lib.rtcSetGeometryInstancedScenes(geom, table.ctypes.data, len(table))
            lib.rtcSetSharedGeometryBuffer(
                geom, BUFFER_TRANSFORM, 0, FORMAT_FLOAT3X4_ROW_MAJOR, xf.ctypes.data, 0, 48,
                len(xf),
            )  # fmt: skip
            lib.rtcSetSharedGeometryBuffer(
                geom, BUFFER_INDEX, 0, FORMAT_UINT, idx.ctypes.data, 0, 4, len(idx)
            )
            lib.rtcCommitGeometry(geom)
            lib.rtcAttachGeometryByID(self._top, geom, 0)
            lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(self._top)
        lib.check("building the forest's scene")

    def cast(self, o: np.ndarray, d: np.ndarray, limit: np.ndarray, group: int = 1) -> RawHits:
        """Raw hits of rays ``o``, ``d`` (float32 (n, 3)) within ``limit``; rays that come in
        nearly parallel groups of ``group`` (2 to 8: a beam's sub-rays) are cast as packets."""
        rs, n = self._rs, len(o)
        t = np.asarray(limit, np.float32).copy()
        geom = np.full(n, -1, np.int64)
        prim = np.zeros(n, np.int64)
        entry = np.zeros(n, np.int64)
        sub = np.zeros(n, np.int64)
        normal = np.zeros((n, 3), np.float32)
        if len(self._entry_inst) and n:
            out = (t, geom, prim, entry, sub, normal)
            with self._casting:  # the turns' cell is the forest's, shared by its casters
                self._turns_cell[0] = 0 if self._turns is None else self._turns.ctypes.data
                if 1 < group <= self._kern.WIDTH and n % group == 0:
                    self._kern.cast_packets(self._lib.intersect8, self._top, o, d, t, group, *out)
                else:
                    self._kern.cast(self._lib.intersect1, self._top, o, d, t, *out)
        leaf, face, instance, out = self._kern.resolve(
            geom, prim, entry, sub, normal, self._entry_owner, self._entry_inst,
            rs.wood_first, rs.leaf_first, rs.shape_first, rs.leaf_shape, rs.inst_inv,
        )  # fmt: skip
        return RawHits(t, instance, leaf, face, out)


def _padded(tri: np.ndarray) -> tuple[np.ndarray, int]:
    """Triangles as a flat float32 vertex array with one float to spare (Embree reads the
    last vertex with a 16-byte load), and their count."""
    flat = np.zeros(tri.size + 1, np.float32)
    flat[:-1] = np.asarray(tri, np.float32).ravel()
    return flat, len(tri)

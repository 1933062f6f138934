"""Pictures: a headless renderer for composed stages, site plots, skeleton drawings.

The renderer reads the stage through pxr, so what it draws is what composes. It samples
points on every Mesh's triangles (density matched to the image's pixel size, area-weighted),
expands every PointInstancer (nested ones included) by its instance transforms, and splats
the points into a z-buffer with numpy: an orthographic view, Lambert shading with the bound
material's diffuse colour. A tree of 100k triangles renders in a couple of seconds. A forest's
trees (instances that only turn about +Z and scale) are sprites: each prototype is splatted
once per yaw and scale bin (bins half a pixel apart at the prototype's reach) and copied at
every instance's pixel with its depth, batch by batch into one z-buffer, so a million trees
cost a few pixels each.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from usdforest.errors import UsdForestError
from usdforest.grow import exact
from usdforest.progress import Progress
from usdforest.runs import run_starts

VIEWS = ("side", "top", "iso")
SKY = np.array([0.93, 0.95, 0.98])
GROUND = np.array([0.55, 0.5, 0.4])
LIGHT = np.array([0.35, -0.55, 0.76])
LIGHT = LIGHT / np.linalg.norm(LIGHT)
MAX_POINTS = 12_000_000


@dataclass(frozen=True, eq=False)
class Cloud:
    """Surface samples: positions, unit normals, colours (n, 3) and splat radius (world m)."""

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    spacing: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @staticmethod
    def concat(clouds: Iterable[Cloud]) -> Cloud:
        cs = [c for c in clouds if len(c)]
        if not cs:
            z = np.zeros((0, 3))
            return Cloud(z, z, z, np.zeros(0))
        return Cloud(
            *(
                np.concatenate([getattr(c, f) for c in cs])
                for f in ("points", "normals", "colors", "spacing")
            )
        )

    def transformed(self, m: np.ndarray) -> Cloud:
        """Apply a row-vector 4x4 transform (USD convention)."""
        rot = m[:3, :3]
        n = exact.matmul(self.normals, exact.inv3(rot).T)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return Cloud(exact.matmul(self.points, rot) + m[3, :3], n, self.colors,
                     self.spacing * _scale(m))  # fmt: skip


# --------------------------------------------------------------------------- stage -> points


def mesh_color(prim) -> np.ndarray:
    """The diffuse colour of the material bound to ``prim`` (its display colour, else grey)."""
    from pxr import UsdGeom, UsdShade

    mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if mat:
        for shader in mat.GetPrim().GetChildren():
            a = shader.GetAttribute("inputs:diffuseColor")
            if a and a.HasValue():
                return np.array(a.Get(), dtype=float)
    dc = UsdGeom.Gprim(prim).GetDisplayColorAttr().Get()
    if dc is not None and len(dc):
        return np.array(dc[0], dtype=float)
    return np.array([0.6, 0.6, 0.6])


def _sample_mesh(prim, to_root: np.ndarray, spacing: float, rng: np.random.Generator) -> Cloud:
    from usdforest.usd.layers import mesh_triangles

    return _sample_triangles(
        mesh_triangles(prim, np.eye(4)), to_root[None], spacing, rng, lambda: mesh_color(prim)
    )


def _sample_triangles(
    local: np.ndarray, mats: np.ndarray, spacing: float, rng: np.random.Generator, color
) -> Cloud:
    """Samples on the triangles ``local`` (m, 3, 3) of one mesh placed by each row-vector
    transform of ``mats`` (k, 4, 4), all at once: the branch prims of a tree instance one
    template mesh each. ``color()`` gives the mesh's colour."""
    if len(local) == 0 or len(mats) == 0:
        return Cloud.concat([])
    t = (exact.matmul(local.reshape(1, -1, 3), mats[:, :3, :3]) + mats[:, None, 3, :3]).reshape(
        len(mats), -1, 3, 3
    )
    e1, e2 = t[:, :, 1] - t[:, :, 0], t[:, :, 2] - t[:, :, 0]
    fn = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(fn, axis=2)
    fn /= np.maximum(2 * area[..., None], 1e-18)
    # about one point per spacing^2 of surface (stochastic rounding per triangle); a mesh too
    # small for any gets one point at its largest triangle, splatted as large as the mesh
    expected = area / spacing**2
    n = np.minimum(np.floor(expected + rng.uniform(size=area.shape)).astype(np.int64), 4096)
    empty = np.flatnonzero(n.sum(axis=1) == 0)
    k_big = np.argmax(area[empty], axis=1)
    lone_points, lone_normals = t[empty, k_big].mean(axis=1), fn[empty, k_big]
    lone_spacing = np.maximum(np.sqrt(area[empty].sum(axis=1)), 1e-6)
    which = np.repeat(np.arange(n.size), n.ravel())
    t, e1, e2, fn = (a.reshape(-1, *a.shape[2:]) for a in (t, e1, e2, fn))
    r1, r2 = rng.uniform(size=(2, which.size))
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    points = np.concatenate(
        [t[which, 0] + e1[which] * r1[:, None] + e2[which] * r2[:, None], lone_points]
    )
    return Cloud(
        points,
        np.concatenate([fn[which], lone_normals]),
        np.broadcast_to(color(), points.shape).copy(),
        np.concatenate([np.full(which.size, max(spacing, 1e-6)), lone_spacing]),
    )


def _times3(x: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``x @ a`` for rows of 3 and a 3x3 ``a``, summed column by column (numpy's matmul of
    millions of 3-vectors is ten times slower)."""
    return x[..., 0, None] * a[0] + x[..., 1, None] * a[1] + x[..., 2, None] * a[2]


def _scale(m: np.ndarray) -> float:
    """The (median) uniform scale of row-vector 4x4 transforms ``m`` ((4, 4) or (k, 4, 4))."""
    det = np.abs(exact.det3(np.asarray(m).reshape(-1, 4, 4)[:, :3, :3]))
    return float(np.median(exact.cbrt(det))) or 1.0


def _matrix(m) -> np.ndarray:
    return np.array(m, dtype=float).reshape(4, 4)


@dataclass(frozen=True, eq=False)
class Stamps:
    """Instances left unexpanded: ``protos[k]`` (samples in prototype space) placed in the
    world as prototype ``proto[i]``, scaled uniformly by ``scale[i]``, turned by ``yaw[i]``
    (radians) about +Z and moved to ``origin[i]``."""

    protos: tuple[Cloud, ...]
    scale: np.ndarray
    yaw: np.ndarray
    origin: np.ndarray
    proto: np.ndarray


def stage_cloud(
    stage,
    root=None,
    *,
    spacing: float = 0.01,
    budget: int = MAX_POINTS,
    seed: int = 0,
    stamps: list[Stamps] | None = None,
) -> Cloud:
    """Surface samples of everything under ``root`` (default prim) that renders (no proxy or
    guide purpose), instancers expanded; given a ``stamps`` list, the instancers directly
    under ``root`` whose instances only turn about +Z and scale uniformly (a forest's trees)
    are appended to it instead, to be drawn as sprites (:func:`splat`)."""
    from pxr import Usd, UsdGeom

    from usdforest.usd.layers import mesh_triangles, rendered

    rng = np.random.default_rng(seed)
    root = root or stage.GetDefaultPrim() or stage.GetPseudoRoot()
    cache = UsdGeom.XformCache()
    memo: dict = {}
    shared: dict = {}  # prototype samples by what they compose from (see _prototype)

    def _drawn(p) -> bool:
        return (
            p.IsActive()
            and rendered(p)
            and not (
                p.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(p).ComputeVisibility() == "invisible"
            )
        )

    def _instanced(first, mats: np.ndarray, spacing: float) -> list[Cloud]:
        """Samples on the meshes of the instanceable prim ``first`` (read through its
        instance proxies) placed by each instance's transform ``mats`` (k, 4, 4)."""
        out = []
        first_inv = exact.inv_affine(_matrix(cache.GetLocalToWorldTransform(first)))
        it = iter(Usd.PrimRange(first, Usd.TraverseInstanceProxies()))
        next(it)
        for p in it:
            if not _drawn(p):
                it.PruneChildren()
                continue
            rel = exact.matmul(_matrix(cache.GetLocalToWorldTransform(p)), first_inv)
            if p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                inner = _instances(p, spacing / _scale(exact.matmul(rel, mats))).transformed(rel)
                out.extend(inner.transformed(m) for m in mats)
                continue
            if not p.IsA(UsdGeom.Mesh):
                continue
            local = mesh_triangles(p, rel)
            step = max(1, 200_000 // max(len(local), 1))  # instances per batch (~200k triangles)
            color = functools.cache(lambda p=p: mesh_color(p))  # read once per mesh
            for a in range(0, len(mats), step):
                out.append(_sample_triangles(local, mats[a : a + step], spacing, rng, color))
        return out

    def subtree(prim, spacing: float, defer: list[Stamps] | None = None) -> Cloud:
        """Samples under ``prim`` in ``prim``'s own local space."""
        key = (prim.GetPath(), round(spacing, 9))
        if key in memo:
            return memo[key]
        prim_to_world = _matrix(cache.GetLocalToWorldTransform(prim))
        inv = exact.inv_affine(prim_to_world)
        parts = []
        instances: dict = {}  # instanceable prims (a tree's branches) by their prototype
        it = iter(Usd.PrimRange(prim, Usd.TraverseInstanceProxies()))
        for p in it:
            if not _drawn(p):
                it.PruneChildren()
                continue
            if p.IsA(UsdGeom.Mesh):
                to_root = exact.matmul(_matrix(cache.GetLocalToWorldTransform(p)), inv)
                parts.append(_sample_mesh(p, to_root, spacing, rng))
            elif p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                to_root = exact.matmul(_matrix(cache.GetLocalToWorldTransform(p)), inv)
                deferred = defer is not None and _defer(
                    p, spacing, exact.matmul(to_root, prim_to_world), defer
                )
                if not deferred:  # sampled in the instancer's own units
                    parts.append(_instances(p, spacing / _scale(to_root)).transformed(to_root))
            elif p.IsInstance():
                # its prototype's meshes are sampled below, once for all its instances
                it.PruneChildren()
                to_root = exact.matmul(_matrix(cache.GetLocalToWorldTransform(p)), inv)
                instances.setdefault(p.GetPrototype().GetPath(), (p, []))[1].append(to_root)
        for first, mats in instances.values():
            parts.extend(_instanced(first, np.stack(mats), spacing))
        out = Cloud.concat(parts)
        memo[key] = out
        return out

    def _transforms(p) -> tuple[np.ndarray, np.ndarray, list]:
        pi = UsdGeom.PointInstancer(p)
        xf = pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
        idx = pi.GetProtoIndicesAttr().Get()
        if xf is None or idx is None or len(idx) == 0:
            return np.zeros((0, 4, 4)), np.zeros(0, dtype=int), []
        protos = pi.GetPrototypesRel().GetTargets()
        return np.asarray(xf, dtype=float).reshape(-1, 4, 4), np.asarray(idx), protos

    def _prototype(p, path, scales: np.ndarray, spacing: float) -> Cloud:
        """A prototype's samples in the instancer's space (before the instance transform),
        as dense as its instances' (uniform) ``scales`` need."""
        proto = p.GetStage().GetPrimAtPath(path)
        # (on a grid of half octaves, so that instancers of the same trees share samples)
        sp = float(
            2.0 ** (np.round(2 * math.log2(spacing / max(float(np.median(scales)), 1e-6))) / 2)
        )
        # the same tree asset under several instancers (a tiled forest's tiles) is sampled
        # once: keyed by the specs it composes from outside its own layer and its variants
        stack = proto.GetPrimStack()
        own = stack[0]
        # shared only when its own spec says no more than what to reference and which
        # variants (anything else authored there, e.g. visibility, makes it its own)
        plain = (
            not own.properties
            and not own.nameChildren
            and set(own.ListInfoKeys())
            <= {"references", "variantSelection", "specifier", "typeName", "kind"}
        )
        key = (
            tuple((s.layer.identifier, str(s.path)) for s in stack if s.layer != own.layer),
            tuple(sorted(proto.GetVariantSets().GetAllVariantSelections().items())),
            round(sp, 9),
        )
        if not plain:
            key = (*key, own.layer.identifier, str(own.path))
        if key[0] and key in shared:
            local = shared[key]
        else:
            local = shared[key] = subtree(proto, sp)
        own = _matrix(cache.GetLocalTransformation(proto)[0])
        return local.transformed(own)

    def _defer(p, spacing: float, to_world: np.ndarray, out: list[Stamps]) -> bool:
        xf, idx, protos = _transforms(p)
        if len(xf) == 0:
            return False
        n = len(xf)
        scale, yaw, origin = np.empty(n), np.empty(n), np.empty((n, 3))
        for a in range(0, n, 250_000):  # in chunks: a million 3x3 temporaries add up
            lin = _times3(xf[a : a + 250_000, :3, :3], to_world[:3, :3])
            s = np.hypot(lin[:, 0, 0], lin[:, 0, 1])
            # a yaw and a uniform scale, up to what half-precision quaternions make of them
            if not (
                np.all(np.abs(lin[:, 2, :2]) <= 1e-6 * s[:, None])
                and np.all(np.abs(lin[:, :2, 2]) <= 1e-6 * s[:, None])
                and np.allclose(lin[:, 2, 2], s, rtol=1e-2)
                and np.allclose(lin[:, 1, 1], lin[:, 0, 0], rtol=1e-6, atol=1e-9 * s.max())
                and np.allclose(lin[:, 1, 0], -lin[:, 0, 1], rtol=1e-6, atol=1e-9 * s.max())
            ):
                return False
            scale[a : a + len(s)] = s
            yaw[a : a + len(s)] = exact.arctan2(lin[:, 0, 1], lin[:, 0, 0])
            origin[a : a + len(s)] = (
                _times3(xf[a : a + 250_000, 3, :3], to_world[:3, :3]) + to_world[3, :3]
            )
        del xf
        clouds = []
        for k, path in enumerate(protos):
            sel = idx == k
            clouds.append(
                _prototype(p, path, scale[sel], spacing) if sel.any() else Cloud.concat([])
            )
        ok = (idx >= 0) & (idx < len(protos))
        out.append(Stamps(tuple(clouds), scale[ok], yaw[ok], origin[ok], idx[ok]))
        return True

    def _instances(p, spacing: float) -> Cloud:
        xf_all, idx, protos = _transforms(p)
        if len(xf_all) == 0:
            return Cloud.concat([])
        placed = int(np.count_nonzero((idx >= 0) & (idx < len(protos))))
        parts = []
        for k, path in enumerate(protos):
            sel = np.flatnonzero(idx == k)
            if sel.size == 0:
                continue
            scales = exact.cbrt(np.abs(exact.det3(xf_all[sel, :3, :3])))
            local = _prototype(p, path, scales, spacing)
            if len(local) == 0:
                continue
            xf = xf_all
            per = len(local)
            # cap: every instance gets the same share of its prototype's samples
            share = max(1, min(per, budget // max(1, placed)))
            pick = rng.permutation(per)[:share]
            pts, nrm = local.points[pick], local.normals[pick]
            m = xf[sel]
            wp = np.einsum("pj,njk->npk", pts, m[:, :3, :3]) + m[:, None, 3, :3]
            wn = np.einsum("pj,njk->npk", nrm, m[:, :3, :3])
            wn /= np.maximum(np.linalg.norm(wn, axis=2, keepdims=True), 1e-12)
            sp = local.spacing[pick][None, :] * scales[:, None] * np.sqrt(per / share)
            parts.append(
                Cloud(
                    wp.reshape(-1, 3),
                    wn.reshape(-1, 3),
                    np.tile(local.colors[pick], (len(sel), 1)),
                    sp.reshape(-1),
                )
            )
        return Cloud.concat(parts)

    world = _matrix(cache.GetLocalToWorldTransform(root))
    return subtree(root, spacing, stamps).transformed(world)


# --------------------------------------------------------------------------- camera and splat


def view_basis(view: str) -> np.ndarray:
    """Rows: screen right, screen up, forward (into the screen)."""
    if view == "side":
        return np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    if view == "top":
        return np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])
    if view == "iso":
        f = np.array([1.0, 1.0, -0.75])
        f /= exact.norm(f)
        r = np.cross(f, [0, 0, 1.0])
        r /= exact.norm(r)
        u = np.cross(r, f)
        return np.stack([r, u, f])
    raise UsdForestError(f"unknown view {view!r}; use side, top or iso")


def view_window(
    uv: np.ndarray, size: tuple[int, int], margin: float = 0.04
) -> tuple[float, float, float, float]:
    """The (u0, u1, v0, v1) window that frames screen points ``uv (n, 2)`` with square
    pixels and a ``margin`` on each side."""
    w, h = size
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    span = np.maximum(hi - lo, 1e-6) * (1 + 2 * margin)
    c = (lo + hi) / 2
    px = max(span[0] / w, span[1] / h)
    u0, v0 = c[0] - px * w / 2, c[1] - px * h / 2
    return (u0, u0 + px * w, v0, v0 + px * h)


def splat(
    cloud: Cloud,
    basis: np.ndarray,
    size: tuple[int, int],
    *,
    background: np.ndarray | None = None,
    margin: float = 0.04,
    window: tuple[float, float, float, float] | None = None,
    stamps: Iterable[Stamps] = (),
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Z-buffer splatting of ``cloud`` and of ``stamps`` (each prototype drawn once per yaw
    and scale bin as a sprite, then stamped at its instances); returns the RGB image and its
    (u0, u1, v0, v1) window."""
    w, h = size
    img = np.empty((h, w, 3))
    img[:] = SKY if background is None else background
    if len(cloud) == 0 and window is None:
        return img, (0.0, 1.0, 0.0, 1.0)
    if window is None:
        window = view_window(exact.matmul(cloud.points, basis[:2].T), size, margin)
    u0, u1, _, v1 = window
    px = (u1 - u0) / w
    zb = _ZBuffer(img)
    if len(cloud):
        uvd = exact.matmul(cloud.points, basis.T)
        col = np.floor((uvd[:, 0] - u0) / px).astype(np.int64)
        row = np.floor((v1 - uvd[:, 1]) / px).astype(np.int64)
        zb.add(*_expand(row, col, uvd[:, 2], _radius(cloud.spacing, px)), _shaded(cloud))
    for s in stamps:
        _stamp(zb, s, basis, window, px)
    return img, window


def _shaded(cloud: Cloud) -> np.ndarray:
    shade = 0.3 + 0.7 * np.abs(exact.dot(cloud.normals, LIGHT))
    return np.clip(cloud.colors * shade[:, None] * 1.25, 0, 1)


def _radius(spacing: np.ndarray, px: float) -> np.ndarray:
    return np.clip(np.round(spacing / px * 0.6).astype(np.int64), 0, 4)


def _expand(row, col, depth, radius) -> tuple[np.ndarray, ...]:
    """Each point as a square of ``2 radius + 1`` pixels: rows, columns, depths and the
    index of the point each comes from, the points' own pixels first."""
    rows, cols, cs = [row], [col], [np.arange(len(row))]
    for r in range(1, 5):
        sel = np.flatnonzero(radius >= r)
        if sel.size == 0:
            break
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                if max(abs(dx), abs(dy)) != r:
                    continue
                rows.append(row[sel] + dy)
                cols.append(col[sel] + dx)
                cs.append(sel)
    src = np.concatenate(cs)
    return np.concatenate(rows), np.concatenate(cols), depth[src], src


def _front(key: np.ndarray, depth: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per distinct ``key`` (in ``range(n)``), the index of its nearest entry (the first of
    them in input order on a tie): a depth buffer by minimum, then the least index among
    those that reach it. Returns the keys (sorted) and those indices."""
    zbuf = np.full(n, np.inf)
    np.minimum.at(zbuf, key, depth)
    front = np.flatnonzero(depth == zbuf[key])
    first = np.full(n, len(key))
    np.minimum.at(first, key[front], front)
    keys = np.flatnonzero(first < len(key))
    return keys, first[keys]


class _ZBuffer:
    """An image and its depths, drawn into batch by batch: a later batch wins a pixel only
    when strictly nearer, so the result is the same as one batch in the same order."""

    def __init__(self, img: np.ndarray):
        self.h, self.w = img.shape[:2]
        self.flat = img.reshape(-1, 3)
        self.depth = np.full(self.h * self.w, np.inf)

    def add(self, row, col, depth, src, palette) -> None:
        """Draw entries at ``row``, ``col``, ``depth``, coloured ``palette[src]``."""
        ok = (row >= 0) & (row < self.h) & (col >= 0) & (col < self.w)
        key = row[ok] * self.w + col[ok]
        depth, src = depth[ok], src[ok]
        pixels, pick = _front(key, depth, self.h * self.w)
        nearer = depth[pick] < self.depth[pixels]
        pixels, pick = pixels[nearer], pick[nearer]
        self.depth[pixels] = depth[pick]
        self.flat[pixels] = palette[src[pick]]


STAMP_BATCH = 2_000_000  # stamped pixels drawn at once
MAX_YAW_BINS = 256  # half a pixel of turn up to a tree 20 pixels in radius


def _bins(cloud: Cloud, scale: np.ndarray, px: float) -> tuple[int, float]:
    """Yaw bins and scale step for sprites of ``cloud`` that stay within half a pixel of
    the instance they stand for: as many yaws as its widest point's circle has half pixels
    (up to ``MAX_YAW_BINS``), a scale step of half a pixel over its reach (at least 1 %)."""
    if len(cloud) == 0 or len(scale) == 0:
        return 1, 2.0
    p = cloud.points
    reach = float(np.sqrt((p * p).sum(axis=1)).max()) * float(np.median(scale)) / px
    yaws = int(np.clip(np.ceil(4 * np.pi * reach), 1, MAX_YAW_BINS))
    return yaws, 1.0 + max(0.5 / max(reach, 1e-9), 0.01)


def _stamp(zb: _ZBuffer, s: Stamps, basis: np.ndarray, window, px: float) -> None:
    """Draw instances as sprites: each prototype at each used (yaw, scale) bin splatted once
    around its origin, then copied at every instance's pixel, its depth offset by the
    instance's."""
    u0, _, _, v1 = window
    scale, yaw = s.scale, s.yaw
    if len(scale) == 0:
        return
    ybin = np.zeros(len(scale), dtype=np.int64)
    sbin = np.zeros(len(scale), dtype=np.int64)
    steps = []
    for k, cloud in enumerate(s.protos):
        sel = s.proto == k
        yaws, step = _bins(cloud, scale[sel], px)
        ybin[sel] = np.round(yaw[sel] / (2 * np.pi) * yaws).astype(np.int64) % yaws
        sbin[sel] = np.round(exact.log(np.maximum(scale[sel], 1e-12)) / math.log(step))
        steps.append((yaws, step))
    origin = _times3(s.origin, basis.T)
    col = np.floor((origin[:, 0] - u0) / px).astype(np.int64)
    row = np.floor((v1 - origin[:, 1]) / px).astype(np.int64)
    # one integer key per (prototype, yaw bin, scale bin); instances grouped by one sort
    smin = int(sbin.min())
    key = (s.proto.astype(np.int64) * MAX_YAW_BINS + ybin) * (int(sbin.max()) - smin + 1)
    key += sbin - smin
    order = np.argsort(key, kind="stable")
    first = run_starts(key[order])
    bounds = np.r_[first, len(key)]
    sprites = []
    for b in range(len(first)):
        i = order[bounds[b]]
        yaws, step = steps[s.proto[i]]
        sprites.append(
            _sprite(
                s.protos[s.proto[i]],
                ybin[i] * 2 * np.pi / yaws,
                math.pow(step, float(sbin[i])),
                basis,
                px,
            )
        )
    palette = np.concatenate([sp[3] for sp in sprites]) if sprites else np.zeros((0, 3))
    offset = np.r_[0, np.cumsum([len(sp[0]) for sp in sprites])]
    batch: list[tuple[np.ndarray, ...]] = []
    held = 0
    for b, (dr, dc, dd, _) in enumerate(sprites):
        if len(dr) == 0:
            continue
        inst = order[bounds[b] : bounds[b + 1]]
        per = max(1, STAMP_BATCH // len(dr))
        for start in range(0, len(inst), per):
            i = inst[start : start + per]
            batch.append(
                (
                    (row[i, None] + dr).ravel(),
                    (col[i, None] + dc).ravel(),
                    (origin[i, 2, None] + dd).ravel(),
                    np.tile(np.arange(offset[b], offset[b + 1]), len(i)),
                )
            )
            held += len(i) * len(dr)
            if held >= STAMP_BATCH:
                zb.add(*(np.concatenate(a) for a in zip(*batch, strict=True)), palette)
                batch, held = [], 0
    if batch:
        zb.add(*(np.concatenate(a) for a in zip(*batch, strict=True)), palette)


def _sprite(cloud: Cloud, yaw: float, scale: float, basis: np.ndarray, px: float):
    """``cloud`` turned by ``yaw`` about +Z and scaled, splatted on the pixel grid around
    its origin: the row and column offsets, depth offsets and colours of its front pixels."""
    if len(cloud) == 0:
        return (np.zeros(0, dtype=np.int64),) * 2 + (np.zeros(0), np.zeros((0, 3)))
    c, sn = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = np.array([[c, sn, 0.0], [-sn, c, 0.0], [0.0, 0.0, 1.0]]) * scale
    turned = cloud.transformed(m)
    uvd = exact.matmul(turned.points, basis.T)
    col = np.floor(uvd[:, 0] / px + 0.5).astype(np.int64)
    row = np.floor(-uvd[:, 1] / px + 0.5).astype(np.int64)
    row, col, depth, src = _expand(row, col, uvd[:, 2], _radius(turned.spacing, px))
    r0, c0 = row.min(), col.min()
    hh, ww = row.max() - r0 + 1, col.max() - c0 + 1
    keys, pick = _front((row - r0) * ww + (col - c0), depth, int(hh * ww))
    return keys // ww + r0, keys % ww + c0, depth[pick], _shaded(turned)[src[pick]]


# --------------------------------------------------------------------------- public API


@dataclass(frozen=True)
class PreviewInfo:
    kind: str  # "tree" or "forest"
    points: int
    size: tuple[int, int]


def render_stage(
    path: str | Path,
    *,
    view: str = "iso",
    size: tuple[int, int] = (800, 800),
    budget: int | None = None,
    ground: bool = True,
    progress: Progress | None = None,
) -> tuple[np.ndarray, tuple, str]:
    """Render a stage to an RGB array; returns (image, window, kind). Drawn in metres with Z
    up whatever the stage's ``metersPerUnit`` and ``upAxis`` (a Y-up centimetre host that
    references a forest draws it upright, its scale bar in metres). ``progress(stage, done,
    total)`` as each of its three steps (open, sample, draw) ends."""
    tick = progress or (lambda stage, done, total: None)
    tick("drawing", 0, 3)
    from pxr import Usd, UsdGeom

    from usdforest.sensors.scene.stageframe import moved_boxes, stage_frame
    from usdforest.usd.layers import open_stage

    path = Path(path)
    stage = open_stage(path, sound=True, full=True)
    tick("drawing", 1, 3)
    frame = stage_frame(path)
    native = np.allclose(frame, np.eye(4))
    basis = view_basis(view)
    root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    box = (
        UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"], True)
        .ComputeWorldBound(root)
        .ComputeAlignedRange()
    )
    region = (root.GetCustomDataByKey("usdforest") or {}).get("regionBounds")
    if not box.IsEmpty():
        lo, hi = np.array(box.GetMin()), np.array(box.GetMax())
        if not native:  # the box in metres, Z up
            lo, hi = (b[0] for b in moved_boxes(lo[None], hi[None], frame[None]))
    elif region is not None:  # a forest with no trees and no ground: its plot
        x0, y0, x1, y1 = (float(v) for v in region)
        lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, 0.0])
    else:
        raise UsdForestError(f"{path}: the stage has no geometry to draw")
    # a flat or empty stage (a forest with no trees) still gets a 1 m window
    flat = (hi - lo) < 1e-6
    lo, hi = np.where(flat, lo - 0.5, lo), np.where(flat, hi + 0.5, hi)
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    uv = exact.matmul(corners, basis[:2].T)
    extent = float(max(np.ptp(uv[:, 0]) / size[0], np.ptp(uv[:, 1]) / size[1]))
    kind = (
        "forest"
        if any(
            p.IsA(UsdGeom.PointInstancer) and Usd.ModelAPI(p).GetKind() == "group"
            for p in stage.Traverse()
        )
        else "tree"
    )
    budget = budget or min(MAX_POINTS, 12 * size[0] * size[1])
    # a forest's trees are stamped as sprites, framed by the stage's bounds (in a stage of
    # other units or axes every instance is sampled, then the whole cloud turned to metres)
    stamps: list[Stamps] | None = [] if kind == "forest" and native else None
    spacing = max(extent * 0.7, 1e-4) / _scale(frame)
    cloud = stage_cloud(stage, root, spacing=spacing, budget=budget, stamps=stamps)
    tick("drawing", 2, 3)
    if not native:
        cloud = cloud.transformed(frame)
    window = None
    if kind == "forest":
        window = view_window(uv, size)
        if ground:
            cloud = Cloud.concat([_ground(lo, hi, extent, _ground_meshes(stage), frame), cloud])
    img, window = splat(cloud, basis, size, window=window, stamps=stamps or ())
    tick("drawing", 3, 3)
    return img, window, kind


def _ground_meshes(stage) -> list:
    """The stage's Meshes labelled ``ground`` that render."""
    from pxr import UsdGeom

    from usdforest.usd.layers import class_labels, rendered

    return [
        p
        for p in stage.Traverse()
        if p.IsA(UsdGeom.Mesh) and rendered(p) and "ground" in class_labels(p)
    ]


def _ground(
    lo: np.ndarray, hi: np.ndarray, px: float, meshes: list, frame: np.ndarray | None = None
) -> Cloud:
    """A dense grid of ground samples, one per pixel, in the drawing's frame (``frame``: the
    stage's units and axes to metres, Z up): on the stage's own ground meshes (their heights
    interpolated, their colour) or, without one, a plain floor under everything. Ground
    meshes that are not a height field in that frame (a tilted reference) are drawn by their
    own surface samples only."""
    step = px * 0.9
    xs = np.arange(lo[0], hi[0], step)
    ys = np.arange(lo[1], hi[1], step)
    gx, gy = np.meshgrid(xs, ys)
    z = np.full(gx.shape, lo[2] - 1e-3)
    n = np.zeros((*gx.shape, 3))
    n[..., 2] = 1.0
    color = GROUND
    if meshes:
        from matplotlib.tri import LinearTriInterpolator, Triangulation
        from pxr import Usd, UsdGeom

        from usdforest.usd.layers import mesh_triangles

        frame = np.eye(4) if frame is None else frame
        now = Usd.TimeCode.Default()
        world = [
            exact.matmul(_matrix(UsdGeom.Xformable(m).ComputeLocalToWorldTransform(now)), frame)
            for m in meshes
        ]
        corners = np.concatenate(
            [mesh_triangles(m, w) for m, w in zip(meshes, world, strict=True)]
        ).reshape(-1, 3)
        if len(corners):
            # interpolate on the ground's own triangles (a height field: one z per x, y)
            # (a tiled forest's grounds share their border cells: the same triangles, to
            # float32 rounding, are kept once)
            pts, tri = np.unique(np.round(corners, 4), axis=0, return_inverse=True)
            tri = np.unique(np.sort(tri.reshape(-1, 3), axis=1), axis=0)
            try:
                mesh = Triangulation(pts[:, 0], pts[:, 1], tri)
                z = np.ma.filled(LinearTriInterpolator(mesh, pts[:, 2])(gx, gy), np.nan)
            except (RuntimeError, ValueError):  # not a height field seen from above
                return Cloud(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
            if min(z.shape) > 1:  # shade the relief: normals from the height's gradient
                dzdy, dzdx = np.gradient(z, step)
                n = np.stack([-dzdx, -dzdy, np.ones_like(z)], axis=-1)
                n /= np.linalg.norm(n, axis=-1, keepdims=True)
            keep = np.isfinite(z) & np.all(np.isfinite(n), axis=-1)
            gx, gy, z, n = gx[keep], gy[keep], z[keep] - 1e-3, n[keep]
            color = mesh_color(meshes[0])
    p = np.column_stack([gx.ravel(), gy.ravel(), np.ravel(z)])
    n = n.reshape(-1, 3)
    return Cloud(p, n, np.tile(color, (len(p), 1)), np.full(len(p), step))


def preview(
    path: str | Path,
    out: str | Path,
    *,
    view: str = "iso",
    size: tuple[int, int] = (800, 800),
    annotate: bool = True,
    progress: Progress | None = None,
) -> PreviewInfo:
    """Render ``path`` to an image at ``out`` (atomically; PNG, JPEG, WebP or TIFF by its
    suffix); ``progress`` as :func:`render_stage` calls it."""
    from usdforest.atomic import atomic_path
    from usdforest.paths import image_format

    fmt = image_format(out)
    img, window, kind = render_stage(path, view=view, size=size, progress=progress)
    with atomic_path(out) as tmp:
        if annotate:
            dpi = 100
            fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
            ax = fig.add_axes((0, 0, 1, 1))
            ax.imshow(img, interpolation="nearest")
            ax.set_axis_off()
            u0, u1 = window[0], window[1]
            bar = _nice_length((u1 - u0) / 5)
            bar_px = bar / (u1 - u0) * size[0]
            x0, y0 = size[0] * 0.05, size[1] * 0.95
            ax.plot([x0, x0 + bar_px], [y0, y0], color="k", lw=2)
            ax.text(
                x0 + bar_px / 2,
                y0 - size[1] * 0.015,
                f"{bar:g} m",
                ha="center",
                va="bottom",
                fontsize=9,
            )
            ax.text(
                size[0] * 0.02,
                size[1] * 0.03,
                f"{Path(path).name} ({kind}, {view} view)",
                fontsize=9,
                va="top",
            )
            fig.savefig(tmp, dpi=dpi, format=fmt)
            plt.close(fig)
        else:
            plt.imsave(tmp, img, format=fmt)
    return PreviewInfo(kind, 0, size)


def _nice_length(x: float) -> float:
    e = 10 ** math.floor(math.log10(max(x, 1e-9)))
    for m in (1, 2, 5, 10):
        if m * e >= x * 0.7:
            return float(m * e)
    return float(10 * e)

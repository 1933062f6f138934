"""Pictures: a headless renderer for composed stages, site plots, skeleton drawings.

The renderer reads the stage through pxr, so what it draws is what composes. It samples
points on every Mesh's triangles (density matched to the image's pixel size, area-weighted),
expands every PointInstancer (nested ones included) by its instance transforms, and splats
the points into a z-buffer with numpy: an orthographic view, Lambert shading with the bound
material's diffuse colour. A tree of 100k triangles renders in a couple of seconds; in a forest
each tree is drawn with as many points as the pixels it covers (distant or small trees are
cheap proxies of themselves), capped by a total point budget.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from .errors import UsdForestError

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
        n = self.normals @ np.linalg.inv(rot).T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        scale = float(np.cbrt(abs(np.linalg.det(rot)))) or 1.0
        return Cloud(self.points @ rot + m[3, :3], n, self.colors, self.spacing * scale)


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
    from .usd.layers import mesh_triangles

    t = mesh_triangles(prim, to_root)
    if len(t) == 0:
        return Cloud.concat([])
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    fn = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(fn, axis=1)
    fn /= np.maximum(2 * area[:, None], 1e-18)
    # about one point per spacing^2 of surface (stochastic rounding per triangle); a mesh too
    # small for any gets one point at its largest triangle, splatted as large as the mesh
    expected = area / spacing**2
    n = np.minimum(np.floor(expected + rng.uniform(size=len(area))).astype(np.int64), 4096)
    if n.sum() == 0:
        k = int(np.argmax(area))
        p = t[k].mean(axis=0)[None]
        color = mesh_color(prim)[None]
        return Cloud(p, fn[k][None], color, np.array([max(np.sqrt(area.sum()), 1e-6)]))
    which = np.repeat(np.arange(len(area)), n)
    r1, r2 = rng.uniform(size=(2, which.size))
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    p = t[which, 0] + e1[which] * r1[:, None] + e2[which] * r2[:, None]
    local_spacing = np.full(which.size, spacing)
    color = np.broadcast_to(mesh_color(prim), p.shape)
    return Cloud(p, fn[which], np.array(color), np.maximum(local_spacing, 1e-6))


def _matrix(m) -> np.ndarray:
    return np.array(m, dtype=float).reshape(4, 4)


def stage_cloud(
    stage, root=None, *, spacing: float = 0.01, budget: int = MAX_POINTS, seed: int = 0
) -> Cloud:
    """Surface samples of everything under ``root`` (default prim) that renders (no proxy or
    guide purpose), instancers expanded."""
    from pxr import Usd, UsdGeom

    from .usd.layers import rendered

    rng = np.random.default_rng(seed)
    root = root or stage.GetDefaultPrim() or stage.GetPseudoRoot()
    cache = UsdGeom.XformCache()
    memo: dict = {}

    def subtree(prim, spacing: float) -> Cloud:
        """Samples under ``prim`` in ``prim``'s own local space."""
        key = (prim.GetPath(), round(spacing, 9))
        if key in memo:
            return memo[key]
        inv = np.linalg.inv(_matrix(cache.GetLocalToWorldTransform(prim)))
        parts = []
        it = iter(Usd.PrimRange(prim, Usd.TraverseInstanceProxies()))
        for p in it:
            if (
                not p.IsActive()
                or not rendered(p)
                or (
                    p.IsA(UsdGeom.Imageable)
                    and UsdGeom.Imageable(p).ComputeVisibility() == "invisible"
                )
            ):
                it.PruneChildren()
                continue
            if p.IsA(UsdGeom.Mesh):
                to_root = _matrix(cache.GetLocalToWorldTransform(p)) @ inv
                parts.append(_sample_mesh(p, to_root, spacing, rng))
            elif p.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()
                to_root = _matrix(cache.GetLocalToWorldTransform(p)) @ inv
                parts.append(_instances(p, spacing).transformed(to_root))
        out = Cloud.concat(parts)
        memo[key] = out
        return out

    def _instances(p, spacing: float) -> Cloud:
        pi = UsdGeom.PointInstancer(p)
        xf = pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
        idx = pi.GetProtoIndicesAttr().Get()
        if xf is None or idx is None or len(idx) == 0:
            return Cloud.concat([])
        xf = np.asarray(xf, dtype=float).reshape(-1, 4, 4)
        idx = np.asarray(idx)
        protos = pi.GetPrototypesRel().GetTargets()
        placed = int(np.count_nonzero((idx >= 0) & (idx < len(protos))))
        parts = []
        for k, path in enumerate(protos):
            sel = np.flatnonzero(idx == k)
            if sel.size == 0:
                continue
            proto = p.GetStage().GetPrimAtPath(path)
            scales = np.cbrt(np.abs(np.linalg.det(xf[sel, :3, :3])))
            local = subtree(proto, spacing / max(float(np.median(scales)), 1e-6))
            if len(local) == 0:
                continue
            own = _matrix(cache.GetLocalTransformation(proto)[0])
            local = local.transformed(own)
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
    return subtree(root, spacing).transformed(world)


# --------------------------------------------------------------------------- camera and splat


def view_basis(view: str) -> np.ndarray:
    """Rows: screen right, screen up, forward (into the screen)."""
    if view == "side":
        return np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    if view == "top":
        return np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])
    if view == "iso":
        f = np.array([1.0, 1.0, -0.75])
        f /= np.linalg.norm(f)
        r = np.cross(f, [0, 0, 1.0])
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        return np.stack([r, u, f])
    raise UsdForestError(f"unknown view {view!r}; use side, top or iso")


def splat(
    cloud: Cloud,
    basis: np.ndarray,
    size: tuple[int, int],
    *,
    background: np.ndarray | None = None,
    margin: float = 0.04,
    window: tuple[float, float, float, float] | None = None,
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Z-buffer splatting of ``cloud``; returns the RGB image and its (u0, u1, v0, v1) window."""
    w, h = size
    img = np.empty((h, w, 3))
    img[:] = SKY if background is None else background
    if len(cloud) == 0:
        return img, (0.0, 1.0, 0.0, 1.0)
    uvd = cloud.points @ basis.T
    if window is None:
        lo, hi = uvd[:, :2].min(axis=0), uvd[:, :2].max(axis=0)
        span = np.maximum(hi - lo, 1e-6) * (1 + 2 * margin)
        c = (lo + hi) / 2
        px = max(span[0] / w, span[1] / h)
        u0, v0 = c[0] - px * w / 2, c[1] - px * h / 2
        window = (u0, u0 + px * w, v0, v0 + px * h)
    u0, u1, v0, v1 = window
    px = (u1 - u0) / w
    col = np.floor((uvd[:, 0] - u0) / px).astype(np.int64)
    row = np.floor((v1 - uvd[:, 1]) / px).astype(np.int64)
    depth = uvd[:, 2]
    shade = 0.3 + 0.7 * np.abs(cloud.normals @ LIGHT)
    rgb = np.clip(cloud.colors * shade[:, None] * 1.25, 0, 1)
    radius = np.clip(np.round(cloud.spacing / px * 0.6).astype(np.int64), 0, 4)
    rows, cols, deps, cs = [row], [col], [depth], [np.arange(len(cloud))]
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
                deps.append(depth[sel])
                cs.append(sel)
    row, col, depth, src = (np.concatenate(a) for a in (rows, cols, deps, cs))
    ok = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    row, col, depth, src = row[ok], col[ok], depth[ok], src[ok]
    key = row * w + col
    # per pixel, the nearest splat (the first of them in input order on a tie): a depth buffer
    # by minimum, then one pick among the few that reach it
    zbuf = np.full(w * h, np.inf)
    np.minimum.at(zbuf, key, depth)
    front = np.flatnonzero(depth == zbuf[key])
    pixels, first = np.unique(key[front], return_index=True)
    flat = img.reshape(-1, 3)
    flat[pixels] = rgb[src[front[first]]]
    return img, window


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
) -> tuple[np.ndarray, tuple, str]:
    """Render a stage to an RGB array; returns (image, window, kind)."""
    from pxr import Usd, UsdGeom

    from .usd.layers import open_stage

    path = Path(path)
    stage = open_stage(path, sound=True)
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
    uv = corners @ basis[:2].T
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
    cloud = stage_cloud(stage, root, spacing=max(extent * 0.7, 1e-4), budget=budget)
    if ground and kind == "forest":
        cloud = Cloud.concat([_ground(lo, hi, extent, _ground_meshes(stage)), cloud])
    img, window = splat(cloud, basis, size)
    return img, window, kind


def _ground_meshes(stage) -> list:
    """The stage's Meshes labelled ``ground`` that render."""
    from pxr import UsdGeom

    from .usd.layers import class_labels, rendered

    return [
        p
        for p in stage.Traverse()
        if p.IsA(UsdGeom.Mesh) and rendered(p) and "ground" in class_labels(p)
    ]


def _ground(lo: np.ndarray, hi: np.ndarray, px: float, meshes: list) -> Cloud:
    """A dense grid of ground samples, one per pixel: on the stage's own ground meshes (their
    heights interpolated, their colour) or, without one, a plain floor under everything."""
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

        from .usd.layers import mesh_triangles

        world = [
            _matrix(UsdGeom.Xformable(m).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
            for m in meshes
        ]
        corners = np.concatenate(
            [mesh_triangles(m, w) for m, w in zip(meshes, world, strict=True)]
        ).reshape(-1, 3)
        if len(corners):
            # interpolate on the ground's own triangles (a height field: one z per x, y)
            pts, tri = np.unique(corners, axis=0, return_inverse=True)
            mesh = Triangulation(pts[:, 0], pts[:, 1], tri.reshape(-1, 3))
            z = np.ma.filled(LinearTriInterpolator(mesh, pts[:, 2])(gx, gy), np.nan)
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
) -> PreviewInfo:
    """Render ``path`` to a PNG at ``out`` (atomically)."""
    from .atomic import atomic_path

    img, window, kind = render_stage(path, view=view, size=size)
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
            fig.savefig(tmp, dpi=dpi, format="png")
            plt.close(fig)
        else:
            plt.imsave(tmp, img, format="png")
    return PreviewInfo(kind, 0, size)


def _nice_length(x: float) -> float:
    e = 10 ** np.floor(np.log10(max(x, 1e-9)))
    for m in (1, 2, 5, 10):
        if m * e >= x * 0.7:
            return float(m * e)
    return float(10 * e)

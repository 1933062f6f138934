"""The wind layer: the forest's trees swaying, as time samples over the static forest.

``wind.usdc`` (beside the forest's other layers, the strongest of the forest's sublayers when
the recipe has a ``[wind]`` table) holds overs of ``/Forest/Trees``: the instancer's
``orientations`` (half floats, what Blender reads) and ``orientationsf`` (floats, which
pxr-based clients and the sensors read before them) at every time code, each tree tilted
about its base by its own sway (:mod:`usdforest.grow.sway`); the trees' first natural
frequencies (``usdforest:swayFrequency``, Hz, one per instance); the instancer's extent grown
by the largest sway, limb and leaf; each limb's own sway (:mod:`usdforest.usd.limbsway`: a
turn per limb of each prototype and time code); and the leaves' flutter
(:mod:`usdforest.usd.flutter`: a rotation per flutter class and time code, and each leaf's
class). Time codes are frames
(``timeCodesPerSecond`` = ``fps`` on the forest's root layer); the last repeats the first, so
the animation loops. Muting the layer leaves the static forest exactly as it was built:
nothing else differs.

Each tree's sizes are measured on its composed prototype, as a user would: the height from
its bounds, the DBH with a girth tape at 1.3 m (:mod:`usdforest.usd.inventory`'s), the
crown's silhouette and centre from its leaves (or, leafless, its branches), all times the
instance's scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from usdforest.errors import UsdForestError
from usdforest.grow.sway import Stems, WindSpec, natural_frequency, sway, tilts
from usdforest.rotations import quat_multiply
from usdforest.usd.flutter import author_flutter
from usdforest.usd.layers import T, attr, extents, new_layer, prim, rendered
from usdforest.usd.limbsway import author_limb_sway

BREAST = 1.3  # m
MAX_SAMPLE_BYTES = 4 * 2**30  # the layer's samples, at most
SAMPLE_BYTES = 8 + 16  # a tree a frame: quath and quatf
# a swaying limb a frame: its half3 and its crate entry (measured: a pine's 22 limbs took
# 16.1 bytes a limb a frame of its wind layer beyond its tree's 24)
LIMB_SAMPLE_BYTES = 16


@dataclass(frozen=True)
class Crown:
    """One prototype in its own space (scale 1): height, DBH, crown silhouette area and
    the height of the crown's centre (m, m, m², m)."""

    height: float
    dbh: float
    area: float
    centre: float


def crown_of(proto: Usd.Prim) -> Crown:
    """Measure a composed tree prototype (its base at its origin)."""
    from usdforest.usd.inventory import girth_dbh, mesh_world

    cache = UsdGeom.XformCache()
    inv = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(proto), dtype=float))
    leaves, wood, trunk = [], [], None
    it = iter(Usd.PrimRange(proto, Usd.TraverseInstanceProxies()))
    for p in it:
        if not rendered(p):
            it.PruneChildren()
        elif p.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            mats = np.asarray(
                UsdGeom.PointInstancer(p).ComputeInstanceTransformsAtTime(
                    Usd.TimeCode.Default(), Usd.TimeCode.Default()
                )
            )
            if len(mats):
                m = np.asarray(cache.GetLocalToWorldTransform(p), dtype=float) @ inv
                leaves.append(mats[:, 3, :3] @ m[:3, :3] + m[3, :3])
        elif p.IsA(UsdGeom.Mesh):
            v, tri = mesh_world(p, cache, inv)
            if "/Trunk" in str(p.GetPath()) and tri is not None and trunk is None:
                trunk = (v, tri)
            else:
                wood.append(v)
    bbox = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"], True)
    height = float(bbox.ComputeUntransformedBound(proto).ComputeAlignedRange().GetMax()[2])
    crown = np.concatenate(leaves) if leaves else np.concatenate(wood) if wood else None
    if trunk is None or crown is None or height <= 0:
        raise UsdForestError(f"{proto.GetPath()}: a tree without a trunk or crown cannot sway")
    dbh = float(girth_dbh(*trunk, np.array([min(BREAST, 0.5 * height)]))[0])
    base = float(np.percentile(crown[:, 2], 5))
    width = 2 * float(np.percentile(np.hypot(crown[:, 0], crown[:, 1]), 95))
    length = max(height - base, 0.0)
    return Crown(height, dbh, math.pi / 4 * width * length, float(crown[:, 2].mean()))


def crowns_of(stage: Usd.Stage, path: str = "/Forest/Trees") -> list[Crown]:
    """The :class:`Crown` of each prototype of the tree instancer at ``path``."""
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath(path))
    if not pi:
        raise UsdForestError(f"{path}: no tree instancer to animate")
    return [crown_of(stage.GetPrimAtPath(t)) for t in pi.GetPrototypesRel().GetTargets()]


def stems_of(
    stage: Usd.Stage, crowns: list[Crown], path: str = "/Forest/Trees"
) -> tuple[Stems, np.ndarray]:
    """The swaying trees of the instancer at ``path`` whose prototypes' crowns are
    ``crowns``: their :class:`Stems` and static orientations ``(n, 4)`` (x, y, z, w)."""
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath(path))
    table = np.array([[c.height, c.dbh, c.area, c.centre] for c in crowns]).reshape(-1, 4)
    idx = np.asarray(pi.GetProtoIndicesAttr().Get() or [], dtype=np.int64)
    pos = np.asarray(pi.GetPositionsAttr().Get() or [], dtype=float).reshape(-1, 3)
    scale = np.asarray(pi.GetScalesAttr().Get() or np.ones((len(idx), 3)), float).reshape(-1, 3)
    s = scale[:, 2]
    h, d, a, c = table[idx].T if len(idx) else np.zeros((4, 0))
    quats = pi.GetOrientationsAttr().Get()
    q = (
        np.asarray(quats, dtype=float).reshape(-1, 4)
        if quats
        else np.tile([0.0, 0.0, 0.0, 1.0], (len(idx), 1))
    )
    return Stems(pos[:, :2], h * s, d * s, a * s**2, c * s), q


def _largest_scale(stage: Usd.Stage, path: str = "/Forest/Trees") -> float:
    """The largest scale of the tree instancer's instances (1 when it has none authored)."""
    scales = UsdGeom.PointInstancer(stage.GetPrimAtPath(path)).GetScalesAttr().Get()
    return float(np.abs(np.asarray(scales, dtype=float)).max()) if scales else 1.0


def sample_bytes(trees: int, spec: WindSpec, limbs: int = 0) -> int:
    """What the layer's samples of ``trees`` orientations and ``limbs`` limbs' turns take
    (bytes)."""
    return (spec.frames + 1) * (trees * SAMPLE_BYTES + limbs * LIMB_SAMPLE_BYTES)


def _size(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def check_samples(trees: int, spec: WindSpec, limbs: int = 0) -> None:
    """Refuse a wind layer whose samples would pass ``MAX_SAMPLE_BYTES``: of ``trees`` (known
    before any tree grows) and, once they have grown, of ``limbs``, every limb of every tree
    asset (those that sway are fewer, found as the layer is written)."""
    need = sample_bytes(trees, spec, limbs)
    if need > MAX_SAMPLE_BYTES:
        what = f"{trees:,} trees" + (f" and up to {limbs:,} swaying limbs" if limbs else "")
        raise UsdForestError(
            f"wind: {what} x {spec.frames + 1:,} time codes would take {_size(need)} of "
            f"samples (at most {_size(MAX_SAMPLE_BYTES)}); lower wind.duration or wind.fps"
        )


def wind_layer(stage: Usd.Stage, spec: WindSpec, seed: int, extent: np.ndarray) -> Sdf.Layer:
    """The wind layer of the forest composed on ``stage`` (its trees at ``/Forest/Trees``,
    static ``extent`` (2, 3) of the instancer)."""
    crowns = crowns_of(stage)
    stems, static = stems_of(stage, crowns)
    check_samples(len(stems.xy), spec)
    top = sway(stems, spec, seed)
    layer = new_layer("Forest", comment="usdforest wind: the trees' sway as time samples")
    # the root layer's rate too: a sublayer of another rate has its time codes rescaled
    layer.timeCodesPerSecond = layer.framesPerSecond = spec.fps
    layer.startTimeCode, layer.endTimeCode = 0, spec.frames
    # outside the change block: it composes the stage at full detail too, which a change
    # block would hold back
    _, leaf = author_flutter(layer, stage, spec, seed)
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", specifier=Sdf.SpecifierOver)
        trees = prim(forest, "Trees", specifier=Sdf.SpecifierOver)
        # orientationsf wins over orientations wherever it is authored, at the default time
        # too: its default is the still forest's
        full = attr(
            trees, "orientationsf", T.QuatfArray, Vt.QuatfArray.FromNumpy(static.astype(np.float32))
        )
        freq = natural_frequency(stems.dbh, stems.height, spec)
        attr(
            trees,
            "usdforest:swayFrequency",
            T.FloatArray,
            Vt.FloatArray.FromNumpy(freq.astype(np.float32)),
        ).SetInfo("documentation", "each tree's first natural frequency (Hz)")
        tallest = float(stems.height.max()) if len(stems.height) else 1.0
        areas = [c.area for c in crowns]
        _, limb = author_limb_sway(layer, stage, spec, seed, areas, tallest)
        # a limb turns about its base, a leaf about its petiole: the trees reach farther
        scale = _largest_scale(stage) if leaf or limb else 0.0
        reach = float(np.linalg.norm(top, axis=-1).max()) if top.size else 0.0
        reach += (leaf + limb) * scale
        up = (leaf + limb) * scale
        grown = np.asarray(extent, dtype=float) + np.array(
            [[-reach, -reach, 0], [reach, reach, up]]
        )
        attr(trees, "extent", T.Float3Array, extents(grown))
        if not np.any(top):  # still air: nothing moves, no samples (nor their interpolation)
            return layer
        half = attr(trees, "orientations", T.QuathArray)
        # unit quaternions: USD scales an instance by |q|^2 and slerps as if |q| were 1, so a
        # half float's (|q| 1 +- 1e-3) would make a swaying tree breathe between samples
        unit = static / np.linalg.norm(static, axis=1, keepdims=True)
        for k in range(spec.frames + 1):
            # Vt's quaternion arrays hold (x, y, z, w) as numpy does here
            q = quat_multiply(tilts(top[k], stems.height), unit)
            layer.SetTimeSample(full.path, float(k), Vt.QuatfArray.FromNumpy(q.astype(np.float32)))
            layer.SetTimeSample(half.path, float(k), Vt.QuathArray.FromNumpy(q.astype(np.float16)))
    return layer

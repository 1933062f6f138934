"""Branch sway in the wind layer: every limb of every tree prototype turning about its base.

A tree asset groups each first-order branch with all that grows on it under one prim,
``Branches/Limb_<i>`` (:mod:`usdforest.usd.tree`), which carries where the limb starts and
ends, its base radius and its length. For each limb of each prototype of the forest's tree
instancer the wind layer authors, as an over:

* ``xformOp:translate:pivot``: the limb's base;
* ``xformOp:orient:limb``: a frame whose z is the limb's axis (x and y across it);
* ``xformOp:rotateXYZ:sway``: the turn about x, then y of that frame, in degrees (half
  floats: a small angle keeps its relative precision), at every time code, so that the tip
  moves as :func:`usdforest.grow.sway.bough_sway` says; zero by default;
* ``xformOpOrder``: pivot, frame, sway, the frame's inverse, the pivot's inverse.

A limb whose tip would sway less than ``MIN_SWAY`` (5 mm rms) stays rigid on its tree: it gets
no samples (at 5 m/s most of the default forest's limbs). So the layer holds one angle pair
per swaying limb of each prototype and time code: the trees of one prototype sway their limbs
alike (their stems sway each on its own). At the default time, or with the layer muted, every
limb is where the asset put it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from usdforest.grow import exact
from usdforest.grow.placement import frames_from_directions
from usdforest.grow.sway import Boughs, WindSpec, bough_sway
from usdforest.rotations import quat_from_matrix
from usdforest.usd.layers import T, attr, class_labels

# a limb whose tip sways less than this (m, rms) stays rigid on its tree: no samples, and the
# sensors keep it in its tree's prototype (under a lidar's few centimetres of range noise)
MIN_SWAY = 0.005
PIVOT_OP = "xformOp:translate:pivot"
FRAME_OP = "xformOp:orient:limb"
SWAY_OP = "xformOp:rotateXYZ:sway"
ORDER = (PIVOT_OP, FRAME_OP, SWAY_OP, f"!invert!{FRAME_OP}", f"!invert!{PIVOT_OP}")


@dataclass(frozen=True, eq=False)
class TreeLimbs:
    """The limbs of one composed tree prototype, in its space: their prims, bases and tips
    ``(k, 3)``, base radii and lengths ``(k,)``, the leaves each carries ``(k,)`` and the
    leaves of the whole tree."""

    paths: tuple[Sdf.Path, ...]
    base: np.ndarray
    tip: np.ndarray
    radius: np.ndarray
    length: np.ndarray
    leaves: np.ndarray
    total_leaves: int


def _leaf_count(prim: Usd.Prim) -> int:
    """The leaf instances of the active leaf instancers under ``prim``."""
    n = 0
    it = iter(Usd.PrimRange(prim))
    for p in it:
        if p.IsA(UsdGeom.PointInstancer):
            it.PruneChildren()
            if "leaf" in class_labels(p):
                n += len(UsdGeom.PointInstancer(p).GetProtoIndicesAttr().Get() or ())
    return n


def tree_limbs(proto: Usd.Prim) -> TreeLimbs:
    """The limbs of the composed tree prototype ``proto`` (none when its level of detail
    shows no branches)."""
    rows = []
    branches = proto.GetChild("Branches")
    for p in branches.GetChildren() if branches else ():
        base = p.GetAttribute("usdforest:base").Get()
        if base is None:
            continue
        rows.append(
            (
                p.GetPath(),
                np.array(base, dtype=float),
                np.array(p.GetAttribute("usdforest:tip").Get(), dtype=float),
                float(p.GetAttribute("usdforest:radius").Get()),
                float(p.GetAttribute("usdforest:length").Get()),
                _leaf_count(p),
            )
        )
    cols = list(zip(*rows, strict=True)) if rows else [()] * 6
    return TreeLimbs(
        tuple(cols[0]),
        np.array(cols[1], dtype=float).reshape(-1, 3),
        np.array(cols[2], dtype=float).reshape(-1, 3),
        np.array(cols[3], dtype=float),
        np.array(cols[4], dtype=float),
        np.array(cols[5], dtype=np.int64),
        _leaf_count(proto),
    )


def boughs_of(limbs: TreeLimbs, crown_area: float) -> Boughs:
    """The limbs as the sway model takes them: each one's share of the crown's drag area is
    its share of the tree's leaves (of its wood, radius x length, on a leafless tree)."""
    if limbs.total_leaves > 0:
        share = limbs.leaves / limbs.total_leaves
    else:
        wood = limbs.radius * limbs.length
        share = wood / max(float(wood.sum()), 1e-300)
    mid = 0.5 * (limbs.base[:, 2] + limbs.tip[:, 2])
    return Boughs(mid, 2 * limbs.radius, limbs.length, crown_area * share)


def sway_angles(limbs: TreeLimbs, tips: np.ndarray) -> np.ndarray:
    """``(frames, k, 2)`` turns (radians) about x, then y of each limb's frame that move its
    tip by ``tips`` ``(frames, k, 2)`` along the frame's x and y (the tip lies on the frame's
    z, its chord from the base)."""
    length = np.maximum(np.linalg.norm(limbs.tip - limbs.base, axis=1), 1e-9)
    ax = -exact.arcsin(np.clip(tips[..., 1] / length, -1.0, 1.0))
    ay = exact.arcsin(np.clip(tips[..., 0] / (length * np.cos(ax)), -1.0, 1.0))
    return np.stack([ax, ay], axis=-1)


def limb_frames(limbs: TreeLimbs) -> np.ndarray:
    """``(k, 4)`` quaternions (x, y, z, w) of each limb's frame: z along its axis."""
    d = limbs.tip - limbs.base
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    return quat_from_matrix(frames_from_directions(d, np.zeros(len(d))))


def limb_sways(
    stage: Usd.Stage,
    spec: WindSpec,
    seed: int,
    areas: list[float],
    top: float,
    trees: str = "/Forest/Trees",
) -> Iterator[tuple[TreeLimbs, np.ndarray]]:
    """Per prototype of the tree instancer at ``trees`` on ``stage`` that has limbs: its
    :class:`TreeLimbs` and their tips' moves ``(frames + 1, k, 2)`` (m) across their axes
    (:func:`usdforest.grow.sway.bough_sway`); ``areas`` are the prototypes' crown silhouettes
    (m²), ``top`` the stand's tallest tree (m)."""
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath(trees))
    for k, target in enumerate(pi.GetPrototypesRel().GetTargets()):
        limbs = tree_limbs(stage.GetPrimAtPath(target))
        if limbs.paths:
            stream = int(np.random.default_rng([seed, 0xB0, k]).integers(2**62))
            yield limbs, bough_sway(boughs_of(limbs, areas[k]), top, spec, stream)


def author_limb_sway(
    layer: Sdf.Layer,
    stage: Usd.Stage,
    spec: WindSpec,
    seed: int,
    areas: list[float],
    top: float,
) -> tuple[int, float]:
    """Author the sway of the limbs of the tree prototypes composed on ``stage`` whose tips
    sway at least ``MIN_SWAY`` (rms) into ``layer`` (the wind layer; see :func:`limb_sways`
    for the arguments). Returns how many limbs sway and the farthest a limb's tip moves (m,
    in its prototype's space)."""
    if not spec.branch_sway or spec.speed == 0:
        return 0, 0.0
    swaying, farthest = 0, 0.0
    with Sdf.ChangeBlock():
        for limbs, tips in limb_sways(stage, spec, seed, areas, top):
            keep = sway_rms(tips) >= MIN_SWAY
            if not keep.any():
                continue
            farthest = max(farthest, float(np.linalg.norm(tips[:, keep], axis=-1).max()))
            degrees = np.degrees(sway_angles(limbs, tips)).astype(np.float16)
            frames = limb_frames(limbs)
            for j in np.flatnonzero(keep):
                path = limbs.paths[j]
                over = Sdf.CreatePrimInLayer(layer, path)
                attr(over, PIVOT_OP, T.Float3, Gf.Vec3f(*map(float, limbs.base[j])))
                x, y, z, w = (float(v) for v in frames[j])
                attr(over, FRAME_OP, T.Quatf, Gf.Quatf(w, x, y, z))
                op = attr(over, SWAY_OP, T.Half3, Gf.Vec3h(0.0, 0.0, 0.0))
                attr(over, "xformOpOrder", T.TokenArray, Vt.TokenArray(ORDER), uniform=True)
                for f, (a, b) in enumerate(degrees[:, j]):
                    layer.SetTimeSample(op.path, float(f), Gf.Vec3h(float(a), float(b), 0.0))
            swaying += int(keep.sum())
    return swaying, farthest


def sway_rms(tips: np.ndarray) -> np.ndarray:
    """``(k,)`` each limb's tip sway (m, rms over the loop) of :func:`limb_sways`' ``tips``."""
    return np.sqrt((tips[:-1] ** 2).sum(axis=-1).mean(axis=0))

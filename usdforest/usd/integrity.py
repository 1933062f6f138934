"""Structural soundness of geometry: what must hold before anything walks or draws a stage.

A Mesh's face counts must add up to its indices, every index must name a point, every face
needs three vertices and every point must be finite. A PointInstancer's per-instance arrays
must be as long as its ``protoIndices``, every index must name a prototype, and no prototype
may be the instancer itself or one of its ancestors (instancing would never end). ``validate``
reports these as findings; ``info``, ``preview`` and ``scan`` refuse such a stage with one
line instead of crashing.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdforest.errors import UsdForestError
from usdforest.paths import shown


def _prims(stage: Usd.Stage) -> Iterator[Usd.Prim]:
    """Every prim once: the stage's own, then each instancing prototype's (not per instance)."""
    yield from stage.Traverse()
    for proto in stage.GetPrototypes():
        yield from Usd.PrimRange(proto)


def _array(attr: Usd.Attribute) -> np.ndarray | None:
    value = attr.Get() if attr else None
    return None if value is None else np.asarray(value)


def _mesh(prim: Usd.Prim, finite: bool) -> list[str]:
    mesh = UsdGeom.Mesh(prim)
    pts = _array(mesh.GetPointsAttr())
    counts = _array(mesh.GetFaceVertexCountsAttr())
    idx = _array(mesh.GetFaceVertexIndicesAttr())
    out = []
    n_pts = 0 if pts is None else len(pts)
    if finite and pts is not None and n_pts and not np.all(np.isfinite(pts)):
        out.append("points contain NaN or infinity")
    if counts is not None and len(counts):
        if np.any(counts < 3):
            out.append("a face has fewer than 3 vertices")
        total = int(np.sum(counts, dtype=np.int64))
        n_idx = 0 if idx is None else len(idx)
        if total != n_idx:
            out.append(f"faceVertexCounts add up to {total} but there are {n_idx} indices")
    if idx is not None and len(idx) and (idx.min() < 0 or idx.max() >= n_pts):
        out.append(f"faceVertexIndices outside 0..{n_pts - 1} (points: {n_pts})")
    return out


def _instancer(prim: Usd.Prim, finite: bool) -> list[str]:
    pi = UsdGeom.PointInstancer(prim)
    out = []
    targets = pi.GetPrototypesRel().GetTargets()
    here = prim.GetPath()
    for t in targets:
        if here.HasPrefix(t):
            what = "itself" if t == here else f"its ancestor {t}"
            out.append(f"lists {what} as a prototype: instancing would never end")
        elif not prim.GetStage().GetPrimAtPath(t):
            out.append(f"prototype {t} does not exist")
    proto = _array(pi.GetProtoIndicesAttr())
    n = 0 if proto is None else len(proto)
    if n and (proto.min() < 0 or proto.max() >= len(targets)):
        out.append(f"protoIndices outside 0..{len(targets) - 1} ({len(targets)} prototypes)")
    for name, attr in (
        ("positions", pi.GetPositionsAttr()),
        ("orientations", pi.GetOrientationsAttr()),
        ("scales", pi.GetScalesAttr()),
        ("ids", pi.GetIdsAttr()),
        ("velocities", pi.GetVelocitiesAttr()),
    ):
        a = _array(attr)
        if a is None or (len(a) == 0 and name != "positions"):
            continue
        if len(a) != n:
            out.append(f"{name} has {len(a)} entries for {n} instances (protoIndices)")
        elif finite and name == "positions" and not np.all(np.isfinite(a)):
            out.append("positions contain NaN or infinity")
    return out


def structural_problems(stage: Usd.Stage, *, finite: bool = True) -> list[tuple[Sdf.Path, str]]:
    """``(prim path, message)`` for every structural problem of the stage's geometry;
    ``finite=False`` leaves NaN/infinite points and positions to another check."""
    out = []
    for prim in _prims(stage):
        if prim.IsA(UsdGeom.Mesh):
            out += [(prim.GetPath(), m) for m in _mesh(prim, finite)]
        elif prim.IsA(UsdGeom.PointInstancer):
            out += [(prim.GetPath(), m) for m in _instancer(prim, finite)]
    return out


def require_sound(stage: Usd.Stage, path: str | Path) -> None:
    """Raise a one-line :class:`UsdForestError` naming the first structural problem."""
    problems = structural_problems(stage)
    if problems:
        where, msg = problems[0]
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise UsdForestError(
            f"{shown(path)}: broken geometry at {where}: {msg}{more}; "
            "`usdforest validate` lists every problem"
        )

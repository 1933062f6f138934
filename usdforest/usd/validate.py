"""Validation: every pxr.UsdValidation validator, plus project rules pxr does not check."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom, UsdValidation

from usdforest.progress import Progress
from usdforest.usd.host import placement_problems
from usdforest.usd.integrity import structural_problems
from usdforest.usd.layers import open_stage


@dataclass(frozen=True)
class Finding:
    """One problem: who found it, where, and what."""

    source: str  # validator name or "usdforest:<rule>"
    severity: str  # "error" or "warning"
    path: str
    message: str

    def as_dict(self) -> dict[str, str]:
        return {
            "source": self.source,
            "severity": self.severity,
            "path": self.path,
            "message": self.message,
        }


def _all_validators() -> list:
    return list(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())


def pxr_findings(stage: Usd.Stage) -> list[Finding]:
    """Run every registered ``UsdValidation`` validator over ``stage``."""
    ctx = UsdValidation.ValidationContext(_all_validators())
    out = []
    for e in ctx.Validate(stage):
        sev = {
            UsdValidation.ValidationErrorType.Error: "error",
            UsdValidation.ValidationErrorType.Warn: "warning",
        }.get(e.GetType(), "info")
        sites = e.GetSites()
        where = str(sites[0].GetPrim().GetPath()) if sites and sites[0].GetPrim() else ""
        out.append(Finding(e.GetName() or "usdValidation", sev, where, e.GetMessage()))
    return out


def project_findings(stage: Usd.Stage) -> list[Finding]:
    """Project rules: stage metadata, extents, finite points, unique ids, unit quaternions."""
    out: list[Finding] = []

    def err(rule: str, path: str, msg: str) -> None:
        out.append(Finding(f"usdforest:{rule}", "error", path, msg))

    root = stage.GetDefaultPrim()
    if not root:
        err("stageMetadata", "/", "no defaultPrim")
    if root and "usdforest" in root.GetCustomData():
        # a usdforest asset itself: Z-up metres, the product's contract
        if UsdGeom.GetStageUpAxis(stage) != UsdGeom.Tokens.z:
            err("stageMetadata", "/", "upAxis is not Z")
        if UsdGeom.GetStageMetersPerUnit(stage) != 1.0:
            err("stageMetadata", "/", "metersPerUnit is not 1")
    else:  # a host of its own units and up axis: the assets beneath it upright and to scale
        for path, msg in placement_problems(stage):
            err("placement", path, msg)
    for p in stage.Traverse(Usd.TraverseInstanceProxies()):
        path = str(p.GetPath())
        if p.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(p)
            pts = mesh.GetPointsAttr().Get()
            if not mesh.GetExtentAttr().HasAuthoredValue():
                err("extent", path, "Mesh has no extent")
            if pts is not None and len(pts) and not np.all(np.isfinite(np.asarray(pts))):
                err("finite", path, "points contain NaN or infinity")
            if pts is not None and len(pts) and mesh.GetExtentAttr().HasAuthoredValue():
                ext = np.asarray(mesh.GetExtentAttr().Get())
                a = np.asarray(pts)
                tol = 1e-4 * max(1.0, float(np.abs(ext).max()))
                if np.any(a.min(axis=0) < ext[0] - tol) or np.any(a.max(axis=0) > ext[1] + tol):
                    err("extent", path, "extent does not contain the points")
        elif p.IsA(UsdGeom.PointInstancer):
            pi = UsdGeom.PointInstancer(p)
            if not pi.GetExtentAttr().HasAuthoredValue():
                err("extent", path, "PointInstancer has no extent")
            ids = pi.GetIdsAttr().Get()
            if ids is not None and len(np.unique(np.asarray(ids))) != len(ids):
                err("ids", path, "PointInstancer ids are not unique")
            pos = pi.GetPositionsAttr().Get()
            if pos is not None and len(pos) and not np.all(np.isfinite(np.asarray(pos))):
                err("finite", path, "positions contain NaN or infinity")
            q = pi.GetOrientationsAttr().Get()
            if q is not None and len(q):
                qa = np.array([[x.GetReal(), *x.GetImaginary()] for x in q], dtype=np.float64)
                if np.any(np.abs(np.linalg.norm(qa, axis=1) - 1.0) > 1e-2):
                    err("quaternions", path, "orientations are not unit quaternions")
            protos = pi.GetPrototypesRel().GetTargets()
            for t in protos:
                if not stage.GetPrimAtPath(t):
                    err("prototypes", path, f"prototype {t} does not exist")
    return out


def structure_findings(stage: Usd.Stage) -> list[Finding]:
    """Broken geometry (:mod:`usdforest.usd.integrity`), one finding per problem (NaN points
    are left to the project's ``finite`` rule)."""
    return [
        Finding("usdforest:structure", "error", str(where), msg)
        for where, msg in structural_problems(stage, finite=False)
    ]


def validate(path: str | Path, progress: Progress | None = None) -> list[Finding]:
    """All findings for the stage at ``path`` (pxr validators and project rules);
    ``progress(stage, done, total)`` as each of the four steps ends.

    Broken indexing (faces or instances pointing outside their arrays, an instancer that
    instances itself) is reported on its own: pxr's validators and the project rules would
    index out of range or recurse, so they run only on a stage without it.
    """
    tick = progress or (lambda stage, done, total: None)
    tick("validating", 0, 4)
    path = Path(path)
    stage = open_stage(path)
    tick("validating", 1, 4)
    broken = structure_findings(stage)
    tick("validating", 2, 4)
    if broken:
        tick("validating", 4, 4)
        return broken
    found = pxr_findings(stage)
    tick("validating", 3, 4)
    found += project_findings(stage)
    tick("validating", 4, 4)
    return found


def errors(findings: list[Finding]) -> list[Finding]:
    return [f for f in findings if f.severity == "error"]

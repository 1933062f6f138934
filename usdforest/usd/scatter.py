"""PointInstancers scattered over a forest's ground (dead wood, ground vegetation: shipped
CAD templates; shrubs and young trees: tree assets): the layer's instancer, its prototypes,
their labels, and the templates copied beside the forest.

::

    /Forest/<Name>                  PointInstancer (kind group): positions, orientations
                                    (quath), scales, protoIndices, ids (int64), extent
    /Forest/<Name>/Prototypes       Scope (kind group)
    /Forest/<Name>/Prototypes/<P>   Xform -> ./templates/<template>.usdc (or a tree asset),
                                    labelled
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from usdforest.usd.layers import T, attr, class_labels, extents, prim, semantic_label, vec3f


@dataclass(frozen=True)
class TemplateProto:
    """One prototype of a scattered instancer: its prim name, the layer it references (a
    path relative to the layer: ``./templates/<name>.usdc``, ``./trees/<name>.usdc``), its
    semantic labels, its ``usdforest`` customData and the ``lod`` variant it selects (a tree
    asset's; ``None`` for a template)."""

    name: str
    reference: str
    labels: tuple[str, ...]
    data: dict = field(default_factory=dict)
    lod: str | None = None


def copy_shipped_templates(names: list[str], folder: Path) -> None:
    """Copy the shipped templates ``names`` into the forest's ``templates/`` folder (once)."""
    from usdforest.cad.library import template_path

    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        src = template_path(name)
        if not (folder / src.name).exists():
            shutil.copyfile(src, folder / src.name)


def author_instancer(
    forest: Sdf.PrimSpec,
    name: str,
    prototypes: list[TemplateProto],
    transforms: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    ids: np.ndarray,
    extent: np.ndarray,
) -> Sdf.PrimSpec:
    """``<forest>/<name>``: a PointInstancer of ``prototypes`` with ``transforms``
    (positions, orientations as x, y, z, w, scales, protoIndices), ``ids`` and ``extent``
    ((2, 3), in the layer's frame). Call inside an ``Sdf.ChangeBlock``."""
    pos, quat, scales, index = transforms
    inst = prim(forest, name, "PointInstancer")
    inst.kind = "group"
    protos = prim(inst, "Prototypes", "Scope")
    protos.kind = "group"
    targets = []
    for p in prototypes:
        spec = prim(protos, p.name, "Xform")
        spec.referenceList.prependedItems = [Sdf.Reference(p.reference)]
        if p.lod is not None:
            spec.variantSelections["lod"] = p.lod
        semantic_label(spec, list(p.labels))
        spec.customData = {"usdforest": dict(p.data)}
        targets.append(spec.path)
    r = Sdf.RelationshipSpec(inst, "prototypes", custom=False)
    r.targetPathList.explicitItems = targets
    attr(inst, "positions", T.Point3fArray, vec3f(pos))
    attr(
        inst,
        "orientations",
        T.QuathArray,
        Vt.QuathArray.FromNumpy(np.asarray(quat, dtype=np.float16).reshape(-1, 4)),
    )
    attr(inst, "scales", T.Float3Array, vec3f(scales))
    attr(inst, "protoIndices", T.IntArray, Vt.IntArray.FromNumpy(np.asarray(index, np.int32)))
    attr(inst, "ids", T.Int64Array, Vt.Int64Array.FromNumpy(np.array(ids, dtype=np.int64)))
    attr(inst, "extent", T.Float3Array, extents(extent))
    return inst


def labelled(instancer: Usd.Prim, label: str) -> bool:
    """Whether every prototype of a PointInstancer carries the semantic ``label``."""
    pi = UsdGeom.PointInstancer(instancer)
    targets = pi.GetPrototypesRel().GetTargets()
    stage = instancer.GetStage()
    return bool(targets) and all(label in class_labels(stage.GetPrimAtPath(t)) for t in targets)


def instance_matrices(instancer: Usd.Prim) -> tuple[np.ndarray, np.ndarray]:
    """A PointInstancer's protoIndices and its instances' transforms ``(n, 4, 4)`` (row
    vectors, prototype -> instancer space)."""
    pi = UsdGeom.PointInstancer(instancer)
    idx = np.asarray(pi.GetProtoIndicesAttr().Get() or [], dtype=np.int64)
    if not len(idx):
        return idx, np.zeros((0, 4, 4))
    mats = np.asarray(
        pi.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(), Usd.TimeCode.Default())
    )
    return idx, mats


def prototype_meshes(proto: Usd.Prim) -> list[np.ndarray]:
    """Each Mesh under a prototype as triangles ``(m, 3, 3)`` in the prototype's own space."""
    from usdforest.usd.layers import mesh_triangles

    cache = UsdGeom.XformCache()
    inv = np.asarray(cache.GetLocalToWorldTransform(proto).GetInverse(), dtype=float)
    return [
        mesh_triangles(m, np.asarray(cache.GetLocalToWorldTransform(m), float) @ inv)
        for m in Usd.PrimRange(proto)
        if m.IsA(UsdGeom.Mesh)
    ]

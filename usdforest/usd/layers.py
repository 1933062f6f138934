"""Stage metadata, Sdf authoring helpers and atomic saves."""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, Vt

from usdforest.atomic import atomic_path
from usdforest.errors import UsdForestError
from usdforest.grow import exact
from usdforest.paths import require_file, shown

T = Sdf.ValueTypeNames


def new_layer(default_prim: str, *, comment: str = "") -> Sdf.Layer:
    """An anonymous layer with the project's stage metadata.

    ``defaultPrim`` set, ``upAxis = "Z"``, ``metersPerUnit = 1``, ``kilogramsPerUnit = 1``.
    """
    layer = Sdf.Layer.CreateAnonymous(".usda")
    root = layer.pseudoRoot
    root.SetInfo("upAxis", "Z")
    root.SetInfo("metersPerUnit", 1.0)
    root.SetInfo("kilogramsPerUnit", 1.0)
    layer.defaultPrim = default_prim
    if comment:
        layer.comment = comment
    return layer


@contextmanager
def quiet_stderr() -> Iterator[None]:
    """Silence the process's stderr (file descriptor 2) for a while: USD prints its own
    warnings there, and usdforest reports what matters itself, on one line."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def _reason(exc: Exception) -> str:
    """The first message in a Tf error, without USD's file and line prefix."""
    text = " ".join(str(exc).split())
    quoted = re.findall(r" : '(.*?)'(?= Error in |$)", text)
    return shown(quoted[0] if quoted else text)[:300]


def open_stage(
    path: str | Path, *, sound: bool = False, full: bool = False, playable: bool = True
) -> Usd.Stage:
    """Open the stage at ``path``, with a one-line error if it is missing, not a file, not
    USD, corrupt, or composes with errors (a reference to a missing or corrupt layer), or
    (``playable``) if its time metadata cannot be played (:func:`time_problems`).

    ``sound``: also refuse structurally broken geometry (see :mod:`usdforest.usd.integrity`),
    for commands that walk or draw it. ``full``: every tree at its full level of detail
    whatever its layers select (:func:`select_full_detail`), for what measures the forest.
    """
    path = require_file(path, "stage")
    with quiet_stderr():
        try:
            stage = Usd.Stage.Open(str(path))
        except Tf.ErrorException as exc:
            raise UsdForestError(
                f"{shown(path)}: not a readable USD stage: {_reason(exc)}"
            ) from None
    if stage is None:
        raise UsdForestError(f"{shown(path)}: cannot open as a USD stage")
    errors = stage.GetCompositionErrors()
    if errors:
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        raise UsdForestError(
            f"{shown(path)}: does not compose: {_reason(Exception(str(errors[0])))}{more}"
        )
    if playable:
        require_playable(stage.GetRootLayer(), path)
    if full:
        select_full_detail(stage)
    if sound:
        from usdforest.usd.integrity import require_sound

        require_sound(stage, path)
    return stage


LOD_SET = "lod"
FULL = "full"


def select_full_detail(stage: Usd.Stage) -> list[str]:
    """Select ``lod = full`` on every prim whose ``lod`` variant set selects another level,
    in the stage's session layer (its files are untouched): sensors, stand figures and
    pictures measure the trees as grown, while clients open the forest at the level its
    layers select. Returns the prims switched. A tree inside an instance of someone else's
    stage (an instance proxy) cannot be switched and keeps its level."""
    switched = []
    it = iter(Usd.PrimRange.Stage(stage))
    for prim in it:
        sets = prim.GetVariantSets()
        if not sets.HasVariantSet(LOD_SET):
            continue
        it.PruneChildren()  # a tree: nothing below it selects a level of its own
        if sets.GetVariantSet(LOD_SET).GetVariantSelection() != FULL:
            switched.append(prim.GetPath())
    if switched:
        session = stage.GetSessionLayer()
        with Sdf.ChangeBlock():
            for path in switched:
                Sdf.CreatePrimInLayer(session, path).variantSelections[LOD_SET] = FULL
    return [str(p) for p in switched]


@contextmanager
def full_detail(stage: Usd.Stage) -> Iterator[list[str]]:
    """Every tree of ``stage`` at full detail inside the block (:func:`select_full_detail`,
    which it yields), the stage's own selections back after it."""
    switched = select_full_detail(stage)
    try:
        yield switched
    finally:
        session = stage.GetSessionLayer()
        with Sdf.ChangeBlock():
            for path in switched:
                spec = session.GetPrimAtPath(path)
                if spec is not None and LOD_SET in spec.variantSelections:
                    del spec.variantSelections[LOD_SET]


def mesh_triangles(prim: Usd.Prim, to_root: np.ndarray) -> np.ndarray:
    """A Mesh prim's faces, fan-triangulated, as ``float64[m, 3, 3]`` transformed by the
    row-vector 4x4 ``to_root`` (empty when the mesh has no faces)."""
    mesh = UsdGeom.Mesh(prim)
    pts = mesh.GetPointsAttr().Get()
    counts = mesh.GetFaceVertexCountsAttr().Get()
    idx = mesh.GetFaceVertexIndicesAttr().Get()
    if pts is None or counts is None or idx is None or len(pts) == 0 or len(counts) == 0:
        return np.zeros((0, 3, 3))
    v = exact.matmul(np.asarray(pts, dtype=float), to_root[:3, :3]) + to_root[3, :3]
    counts, idx = np.asarray(counts), np.asarray(idx)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tri = []
    for k in range(1, int(counts.max()) - 1):
        s = starts[counts > k + 1]
        tri.append(np.stack([idx[s], idx[s + k], idx[s + k + 1]], axis=1))
    return v[np.concatenate(tri)] if tri else np.zeros((0, 3, 3))


def save_layer(layer: Sdf.Layer, path: str | Path) -> Path:
    """Write ``layer`` to ``path`` atomically (a temporary file in the same folder, renamed).

    The file format follows the extension (``.usda`` text, ``.usdc`` crate).
    """
    from pxr import Tf

    path = Path(path)
    with atomic_path(path) as tmp:
        try:
            ok = layer.Export(str(tmp))
        except Tf.ErrorException as exc:  # e.g. a full disk: USD reports the OS's error
            reasons = re.findall(r"Error occurred writing file: ([^'\n]*)", str(exc))
            why = reasons[0].strip() if reasons else str(exc).strip().splitlines()[0][:120]
            raise UsdForestError(f"{path.name}: could not write the layer ({why})") from None
        if not ok:
            raise UsdForestError(f"{path}: could not write the layer")
    return path


def prim(
    parent: Sdf.PrimSpec | Sdf.Layer,
    name: str,
    type_name: str = "",
    specifier: Sdf.Specifier = Sdf.SpecifierDef,
) -> Sdf.PrimSpec:
    """Create (or fetch) a prim spec under a layer's root or another prim spec."""
    owner = parent.pseudoRoot if isinstance(parent, Sdf.Layer) else parent
    existing = owner.nameChildren.get(name)
    if existing is not None:
        return existing
    return Sdf.PrimSpec(owner, name, specifier, type_name)


def attr(
    spec: Sdf.PrimSpec,
    name: str,
    type_name,
    value=None,
    *,
    uniform: bool = False,
    interpolation: str | None = None,
) -> Sdf.AttributeSpec:
    """Author an attribute with a default value."""
    a = Sdf.AttributeSpec(
        spec, name, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying
    )
    if value is not None:
        a.default = value
    if interpolation:
        a.SetInfo("interpolation", interpolation)
    return a


def rel(spec: Sdf.PrimSpec, name: str, targets: Sequence[Sdf.Path]) -> Sdf.RelationshipSpec:
    r = Sdf.RelationshipSpec(spec, name, custom=False)
    r.targetPathList.explicitItems = list(targets)
    return r


def apply_schemas(spec: Sdf.PrimSpec, schemas: Iterable[str]) -> None:
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=list(schemas)))


def vec3f(a: np.ndarray) -> Vt.Vec3fArray:
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))


def extents(a: np.ndarray) -> Vt.Vec3fArray:
    """Min, max pairs ``(2 k, 3)`` as a float3[] rounded outward (see
    :func:`usdforest.grow.bounds.outward_f32`): an extent or an extentsHint."""
    from usdforest.grow.bounds import outward_f32

    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(outward_f32(a)))


def ints(a: np.ndarray) -> Vt.IntArray:
    return Vt.IntArray.FromNumpy(np.ascontiguousarray(a, dtype=np.int32))


def extent_of(points: np.ndarray) -> Vt.Vec3fArray:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return vec3f(np.zeros((2, 3)))
    return vec3f(np.stack([pts.min(axis=0), pts.max(axis=0)]))


def triangle_mesh(
    parent: Sdf.PrimSpec, name: str, points: np.ndarray, triangles: np.ndarray, normals: np.ndarray
) -> Sdf.PrimSpec:
    """``<parent>/<name>``: a Mesh of triangles with vertex normals, its extent and no
    subdivision (the caller binds a material and adds labels)."""
    mesh = prim(parent, name, "Mesh")
    attr(mesh, "points", T.Point3fArray, vec3f(points))
    attr(mesh, "faceVertexCounts", T.IntArray, ints(np.full(len(triangles), 3)))
    attr(mesh, "faceVertexIndices", T.IntArray, ints(np.asarray(triangles).ravel()))
    attr(mesh, "normals", T.Normal3fArray, vec3f(normals), interpolation="vertex")
    attr(mesh, "extent", T.Float3Array, extent_of(points))
    attr(mesh, "subdivisionScheme", T.Token, "none", uniform=True)
    return mesh


def semantic_label(spec: Sdf.PrimSpec, label: str | Sequence[str]) -> None:
    """Apply ``SemanticsLabelsAPI:class`` with ``semantics:labels:class = [label, ...]``,
    and the same labels in the older ``SemanticsAPI:Semantics`` schema (``semantic:Semantics:
    params:semanticType = "class"``, ``semanticData`` the labels joined by commas) that
    Isaac Sim 4.x and Replicator read: UsdSemantics came with USD 25.2."""
    labels = [label] if isinstance(label, str) else list(label)
    existing = spec.GetInfo("apiSchemas") if spec.HasInfo("apiSchemas") else None
    items = list(existing.prependedItems) if existing else []
    for schema in ("SemanticsLabelsAPI:class", "SemanticsAPI:Semantics"):
        if schema not in items:
            items.append(schema)
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=items))
    attr(spec, "semantics:labels:class", T.TokenArray, Vt.TokenArray(labels), uniform=True)
    attr(spec, "semantic:Semantics:params:semanticType", T.String, "class")
    attr(spec, "semantic:Semantics:params:semanticData", T.String, ",".join(labels))


RENDERED_PURPOSES = ("default", "render")


def rendered(prim: Usd.Prim) -> bool:
    """Whether a renderer draws ``prim`` as far as its own purpose goes: False where it is
    ``proxy`` or ``guide`` (purpose inherits, so a traversal prunes there)."""
    a = prim.GetAttribute("purpose")
    return not a or a.Get() in RENDERED_PURPOSES


def class_labels(prim: Usd.Prim) -> list[str]:
    """The prim's ``semantics:labels:class`` labels (empty when it has none; the pseudo-root,
    which has no properties, has none)."""
    if prim.IsPseudoRoot():
        return []
    a = prim.GetAttribute("semantics:labels:class")
    v = a.Get() if a and a.HasValue() else None
    return list(v) if v else []


# the SimReady non-visual material vocabulary that RTX lidar and radar read (base tokens)
NONVISUAL_BASES = ("bark", "leaf_grass", "dead_leaf_grass", "wood", "dirt", "stone", "none")


def preview_material(
    parent: Sdf.PrimSpec,
    name: str,
    color: Sequence[float],
    *,
    nonvisual: str,
    roughness: float = 0.8,
) -> Sdf.Path:
    """A Material with a UsdPreviewSurface shader; returns the material's path.

    ``nonvisual`` is the SimReady non-visual base (``bark``, ``leaf_grass``, ``dirt``, ...),
    authored as ``omni:simready:nonvisual:base`` with coating and attributes ``none``: the
    material attributes NVIDIA's RTX lidar and radar models take their response from.
    """
    if nonvisual not in NONVISUAL_BASES:
        raise ValueError(f"non-visual base {nonvisual!r}: expected one of {NONVISUAL_BASES}")
    mat = prim(parent, name, "Material")
    attr(mat, "omni:simready:nonvisual:base", T.Token, nonvisual)
    attr(mat, "omni:simready:nonvisual:coating", T.Token, "none")
    attr(mat, "omni:simready:nonvisual:attributes", T.TokenArray, Vt.TokenArray(["none"]))
    shader = prim(mat, "PreviewSurface", "Shader")
    attr(shader, "info:id", T.Token, "UsdPreviewSurface", uniform=True)
    attr(shader, "inputs:diffuseColor", T.Color3f, tuple(float(c) for c in color))
    attr(shader, "inputs:roughness", T.Float, float(roughness))
    attr(shader, "inputs:metallic", T.Float, 0.0)
    out = attr(shader, "outputs:surface", T.Token)
    surf = attr(mat, "outputs:surface", T.Token)
    surf.connectionPathList.explicitItems = [out.path]
    return mat.path


def bind_material(spec: Sdf.PrimSpec, material: Sdf.Path) -> None:
    """Apply MaterialBindingAPI and bind ``material``."""
    existing = spec.GetInfo("apiSchemas") if spec.HasInfo("apiSchemas") else None
    items = list(existing.prependedItems) if existing else []
    if "MaterialBindingAPI" not in items:
        items.insert(0, "MaterialBindingAPI")
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=items))
    rel(spec, "material:binding", [material])


def time_problems(layer: Sdf.Layer) -> list[str]:
    """What is wrong with the time metadata of ``layer`` (a stage's root layer), each as
    ``key = value: why``: a rate (``timeCodesPerSecond``, ``framesPerSecond``) that is not a
    positive finite number, a start or end that is not finite, an end before the start. USD
    divides by the rate and walks the range: a stage with one of these cannot be played."""
    import math

    found = []
    for key, has, value in (
        ("timeCodesPerSecond", layer.HasTimeCodesPerSecond(), layer.timeCodesPerSecond),
        ("framesPerSecond", layer.HasFramesPerSecond(), layer.framesPerSecond),
    ):
        if has and not (math.isfinite(value) and value > 0):
            found.append(f"{key} = {value:g}: not a positive rate")
    start, end = layer.startTimeCode, layer.endTimeCode
    for key, has, value in (
        ("startTimeCode", layer.HasStartTimeCode(), start),
        ("endTimeCode", layer.HasEndTimeCode(), end),
    ):
        if has and not math.isfinite(value):
            found.append(f"{key} = {value:g}: not a finite time")
    if (layer.HasStartTimeCode() and layer.HasEndTimeCode() and math.isfinite(start)
            and math.isfinite(end) and end < start):  # fmt: skip
        found.append(f"endTimeCode = {end:g}: before startTimeCode = {start:g}")
    return found


def require_playable(layer: Sdf.Layer, path: str | Path) -> None:
    """A one-line :class:`UsdForestError` naming ``path`` where ``layer``'s time metadata
    cannot be played (:func:`time_problems`)."""
    problems = time_problems(layer)
    if problems:
        raise UsdForestError(f"{shown(path)}: {problems[0]}; fix the layer's time metadata")


def time_range(layer: Sdf.Layer) -> tuple[float, float, float, bool]:
    """The animation ``layer`` (a stage's root layer) gives: its first and last time codes in
    seconds, its time codes a second (``timeCodesPerSecond``, else ``framesPerSecond``, else
    24, as USD reads them) and whether it loops (a usdforest wind's last time code is its
    first: ``customLayerData`` ``loops``)."""
    tcps = (
        layer.timeCodesPerSecond
        if layer.HasTimeCodesPerSecond() or not layer.HasFramesPerSecond()
        else layer.framesPerSecond
    )
    loops = bool(layer.customLayerData.get("loops", False))
    return layer.startTimeCode / tcps, layer.endTimeCode / tcps, tcps, loops

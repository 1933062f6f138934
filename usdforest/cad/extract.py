"""Whole-tree CAD decomposition: wood vs foliage, trunk, branch hierarchy, foliage clumps.

Input: one CAD model of a whole tree (e.g. a low-poly game asset) whose wood and foliage are
separate parts. Steps:

1. **wood vs foliage** by material/group names (``bark``, ``wood``, ``trunk``... vs ``leaf``,
   ``leaves``, ``foliage``, ``needle``...); groups that match neither are split into connected
   components and classified by shape (elongated tubes are wood, compact clumps foliage). A
   model without foliage (a dead tree, a broadleaf in winter) is a tree without leaves;
2. **up axis**: the largest wood component's principal axis, pointing from its lower end
   towards the foliage (or, leafless, from its thicker end to its thinner one);
3. **units**: the unit that makes the tree's height plausible (1-120 m);
4. **wood**: the trunk is the largest wood component on the ground. Every wood component is
   split at its forks (:mod:`usdforest.cad.tubes`: geodesic bands from its base ring), so limbs
   fused into the trunk become branches of their own. A separate component's base is the end
   that touches other wood; the component it touches is its parent. Each branch is measured
   from its base (where it leaves its parent) to its tip: length, direction (angle to the
   vertical, azimuth), base radius, order, parent;
5. **foliage clumps**: each foliage component's centre, principal frame (signs fixed by the
   third moment, so the same shape always gets the same frame), extents and area. Clumps of
   the same shape (triangle count and proportions) share a template: the median clump of the
   group, centred in its own frame. Each clump is then that template rotated into the clump's
   frame and scaled per axis to the clump's extents.

The result is a template per part (trunk, branch, clump_<k>) and a measured profile that
:func:`usdforest.grow.species.species_from_profile` grows back into a tree.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usdforest.cad.parts import (
    DEFAULT_COLORS,
    UNITS,
    CADMesh,
    Measurements,
    TemplatePart,
    components,
    face_areas,
    normalise_part,
    principal_axes,
    read_cad,
)
from usdforest.errors import CADError
from usdforest.grow import exact
from usdforest.meshes import vertex_normals

WOOD_NAMES = re.compile(r"bark|wood|trunk|branch|stem|twig|log|limb", re.IGNORECASE)
FOLIAGE_NAMES = re.compile(r"lea(f|ves)|foliage|needle|crown|canopy|frond|conifer", re.IGNORECASE)
TREE_HEIGHT_RANGE = (1.0, 120.0)
SAME_SHAPE = 0.2  # clumps whose sorted extent ratios differ by less than this share a template


@dataclass(frozen=True)
class BranchMeasure:
    """One branch, metres and degrees, in the tree's frame (trunk base at the origin, Z up)."""

    length: float  # base to tip
    base_radius: float
    insertion_height: float  # z of the base
    angle_to_trunk: float  # degrees between the branch (base to tip) and the vertical
    base: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tip: tuple[float, float, float] = (0.0, 0.0, 0.0)
    azimuth: float = 0.0  # degrees, of the base-to-tip direction (0 = +X, 90 = +Y)
    parent: int = -1  # index of the branch it grows from, -1 for the trunk
    order: int = 1


@dataclass(frozen=True)
class ClumpMeasure:
    """One foliage clump; ``orient`` (x, y, z, w) and ``scale`` place its template."""

    centre: tuple[float, float, float]
    radius: float  # largest distance from the centre
    area: float
    bottom: float
    top: float
    orient: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    template: int = 0


@dataclass(frozen=True, eq=False)
class Extraction:
    """Parts and measurements of a decomposed whole-tree model (metres, Z up, base at origin)."""

    source: str
    sha256: str
    units: str
    up_axis: str
    height: float
    trunk: TemplatePart
    branches: tuple[BranchMeasure, ...]
    clumps: tuple[ClumpMeasure, ...]
    templates: tuple[TemplatePart, ...]
    wood_by: str  # "names", "shape" or "names+shape"
    trunk_roll: float = 0.0  # azimuth (degrees) of the trunk template's +X in the model
    trunk_centreline: tuple[tuple[float, float, float], ...] = ()

    @property
    def clump_templates(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.templates if t.name.startswith("clump"))

    def profile(self) -> dict:
        """The measured profile as plain data (written as TOML)."""
        t = self.trunk.measurements
        b = self.branches
        c = self.clumps
        r6 = lambda x: round(float(x), 6)  # noqa: E731

        def vecs(rows) -> list[list[float]]:
            return [[r6(x) for x in row] for row in rows]

        return {
            "source": {
                "file": self.source,
                "sha256": self.sha256,
                "units": self.units,
                "up_axis": self.up_axis,
                "wood_foliage_split": self.wood_by,
            },
            "tree": {
                "height": r6(self.height),
                "crown_base_height": r6(min((x.bottom for x in c), default=0.0)),
                "crown_diameter": r6(_crown_diameter(c)),
            },
            "trunk": {
                "length": r6(t.length),
                "base_radius": r6(t.base_radius),
                "tip_radius": r6(t.tip_radius),
                "triangles": t.triangles,
                "roll_deg": r6(self.trunk_roll),
                "centreline": vecs(self.trunk_centreline),
            },
            "branches": {
                "count": len(b),
                "lengths": [r6(x.length) for x in b],
                "base_radii": [r6(x.base_radius) for x in b],
                "insertion_heights": [r6(x.insertion_height) for x in b],
                "angles_to_trunk_deg": [r6(x.angle_to_trunk) for x in b],
                "azimuths_deg": [r6(x.azimuth) for x in b],
                "bases": vecs(x.base for x in b),
                "tips": vecs(x.tip for x in b),
                "parents": [x.parent for x in b],
                "orders": [x.order for x in b],
            },
            "foliage": {
                "clumps": len(c),
                "templates": list(self.clump_templates),
                "clump_templates": [x.template for x in c],
                "clump_centres": vecs(x.centre for x in c),
                "clump_orientations": vecs(x.orient for x in c),
                "clump_scales": vecs(x.scale for x in c),
                "clump_radii": [r6(x.radius) for x in c],
                "clump_heights": [r6(x.centre[2]) for x in c],
                "clump_areas": [r6(x.area) for x in c],
                "total_area": r6(sum(x.area for x in c)),
            },
        }


def _crown_diameter(clumps: tuple[ClumpMeasure, ...]) -> float:
    if not clumps:
        return 0.0
    pts = np.array([x.centre for x in clumps])[:, :2]
    r = np.array([x.radius for x in clumps])
    lo = (pts - r[:, None]).min(axis=0)
    hi = (pts + r[:, None]).max(axis=0)
    return float((hi - lo).max())


def _split_wood_foliage(mesh: CADMesh) -> tuple[np.ndarray, str]:
    """``bool[m]`` per face: True for wood; and how it was decided."""
    wood_groups = [bool(WOOD_NAMES.search(g)) for g in mesh.groups]
    foliage_groups = [bool(FOLIAGE_NAMES.search(g)) for g in mesh.groups]
    named = [w != f for w, f in zip(wood_groups, foliage_groups, strict=True)]
    is_wood = np.array(wood_groups, dtype=bool)[mesh.face_group]
    if all(named) and any(wood_groups):
        return is_wood, "names"
    # by shape, component by component, for the faces whose group names did not decide
    undecided = ~np.array(named, dtype=bool)[mesh.face_group]
    label = components(mesh)
    for c in np.unique(label[undecided]):
        sel = label == c
        part = mesh.subset(sel)
        _, axes = principal_axes(part.vertices, part.faces)
        local = (part.vertices - part.vertices.mean(axis=0)) @ axes.T
        ext = np.ptp(local, axis=0) + 1e-12
        is_wood[sel] = ext[0] / ext[1] > 3.0
    return is_wood, "shape" if not any(named) else "names+shape"


def _rotation_to_z(axis: np.ndarray) -> np.ndarray:
    """Rotation matrix taking the unit coordinate ``axis`` (e.g. +Y) to +Z."""
    z = np.asarray(axis, dtype=float)
    x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = x - z * (x @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _end_radius(v: np.ndarray, axis: np.ndarray, at_max: bool) -> float:
    t = (v - v.mean(axis=0)) @ axis
    span = float(np.ptp(t)) or 1.0
    sel = t >= t.max() - 0.1 * span if at_max else t <= t.min() + 0.1 * span
    p = v[sel] - v[sel].mean(axis=0)
    p -= np.outer(p @ axis, axis)
    return float(np.median(np.linalg.norm(p, axis=1)))


def _up_axis(wood: CADMesh, foliage: CADMesh, biggest: CADMesh, up: str) -> np.ndarray:
    if up != "auto":
        names = {"Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}
        if up.upper() not in names:
            raise CADError(f"unknown up axis {up!r}; use Y, Z or auto")
        return np.array(names[up.upper()])
    _, axes = principal_axes(biggest.vertices, biggest.faces)
    k = int(np.argmax(np.abs(axes[0])))
    axis = np.zeros(3)
    axis[k] = 1.0
    if len(foliage.faces):
        towards = foliage.vertices.mean(axis=0) - biggest.vertices.mean(axis=0)
        if towards[k] < 0:
            axis = -axis
    elif _end_radius(biggest.vertices, axis, True) > _end_radius(biggest.vertices, axis, False):
        axis = -axis  # leafless: the thick end is the base
    return axis


@dataclass(frozen=True, eq=False)
class _Part:
    """A tube of the wood (trunk or branch) in the tree's frame."""

    mesh: CADMesh
    centreline: np.ndarray
    parent: int  # part index, -1 for the trunk


def _face_part(mesh: CADMesh, vertex_part: np.ndarray) -> np.ndarray:
    """Each face goes to the part most of its vertices belong to (the first vertex's on a tie)."""
    fp = vertex_part[mesh.faces]
    return np.where(fp[:, 1] == fp[:, 2], fp[:, 1], fp[:, 0])


def _wood_parts(wood: CADMesh, trunk_label: int, label: np.ndarray, height: float) -> list[_Part]:
    """Trunk first, then every branch after its parent."""
    from scipy.spatial import cKDTree

    from usdforest.cad.tubes import mesh_edges, split_tubes

    n_comp = int(label.max()) + 1
    comps = [wood.subset(label == c) for c in range(n_comp)]
    trees = [cKDTree(m.vertices) for m in comps]

    # grow the hierarchy from the trunk (Prim's algorithm): repeatedly attach the component
    # whose end comes nearest to the wood attached so far; that end is its base
    base_ring: dict[int, np.ndarray] = {}
    attach: dict[int, int] = {}
    tm = comps[trunk_label]
    base_ring[trunk_label] = tm.vertices[:, 2] <= tm.vertices[:, 2].min() + 0.02 * height
    ends: dict[int, list[np.ndarray]] = {}
    radius = np.zeros(n_comp)  # each component's thicker end, from one principal-axis fit
    for c in range(n_comp):
        m = comps[c]
        _, axes = principal_axes(m.vertices, m.faces)
        radius[c] = max(_end_radius(m.vertices, axes[0], end) for end in (False, True))
        t = (m.vertices - m.vertices.mean(axis=0)) @ axes[0]
        ends[c] = [t <= t.min() + 0.05 * np.ptp(t), t >= t.max() - 0.05 * np.ptp(t)]
    # dist[c][o] = (distance, end) from component c's nearer end to component o
    near: dict[tuple[int, int], tuple[float, int]] = {}
    for c in range(n_comp):
        for o in range(n_comp):
            if o != c and c != trunk_label:
                near[c, o] = min(
                    (float(trees[o].query(comps[c].vertices[sel])[0].min()), e)
                    for e, sel in enumerate(ends[c])
                )
    order_of = [trunk_label]
    depth = {trunk_label: 0}
    while len(order_of) < n_comp:
        d, c, _, _ = min(
            (near[c, o][0], c, o, near[c, o][1])
            for c in range(n_comp)
            if c not in order_of
            for o in order_of
        )
        # of the wood it nearly touches, the lowest order wins (limbs meeting at the top of
        # the trunk all grow from the trunk, not from each other)
        tol = d + 0.5 * radius[c]
        _, _, o = min((depth[o], near[c, o][0], o) for o in order_of if near[c, o][0] <= tol)
        base_ring[c] = ends[c][near[c, o][1]]
        attach[c] = o
        depth[c] = depth[o] + 1
        order_of.append(c)

    parts: list[_Part] = []
    part_vertices: list[np.ndarray] = []
    for c in order_of:
        m = comps[c]
        # bands at least as wide as the mesh's rings are apart, so a ring is one piece
        e = mesh_edges(m.faces)
        edge = np.linalg.norm(m.vertices[e[:, 0]] - m.vertices[e[:, 1]], axis=1)
        band = max(radius[c], float(np.quantile(edge, 0.75)), 0.01 * height)
        tubes = split_tubes(
            m.vertices,
            m.faces,
            base_ring[c],
            band=band,
            min_length=max(2.5 * band, 0.05 * height),
            root_axis=np.array([0.0, 0.0, 1.0]) if c == trunk_label else None,
        )
        vertex_part = np.zeros(len(m.vertices), dtype=np.int64)
        for i, tb in enumerate(tubes):
            vertex_part[tb.vertices] = i
        face_part = _face_part(m, vertex_part)
        first = len(parts)
        for i, tb in enumerate(tubes):
            if tb.parent >= 0:
                parent = first + tb.parent
            elif c == trunk_label:
                parent = -1
            else:
                # the part of the parent component nearest to this base
                cands = [j for j, pv in enumerate(part_vertices) if pv[0] == attach[c]]
                dists = [
                    float(np.min(np.linalg.norm(pv[1] - tb.base, axis=1)))
                    for pv in (part_vertices[j] for j in cands)
                ]
                parent = cands[int(np.argmin(dists))]
            sub = m.subset(face_part == i)
            if len(sub.faces) == 0:
                continue
            parts.append(_Part(sub, tb.centreline, parent))
            part_vertices.append((c, sub.vertices))
    return parts


def _clump_frame(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre, axes (rows; signs fixed by the third moment, right-handed) and extents."""
    centre = v.mean(axis=0)
    _, axes = principal_axes(v, f)
    local = (v - centre) @ axes.T
    skew = np.sum(local * local * local, axis=0) / len(local)
    axes = axes * np.where(skew < 0, -1.0, 1.0)[:, None]
    if np.linalg.det(axes) < 0:  # right-handed: flip the axis whose sign is least certain
        k = int(np.argmin(np.abs(skew) / (exact.power(np.std(local, axis=0), 3) + 1e-30)))
        axes[k] = -axes[k]
    local = (v - centre) @ axes.T
    mid = 0.5 * (local.min(axis=0) + local.max(axis=0))
    centre = centre + mid @ axes
    return centre, axes, np.ptp(local, axis=0)


def _quat_xyzw(rows: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of the rotation taking the template frame to ``rows`` (axes)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(rows.T).as_quat()
    if q[3] < 0:
        q = -q
    return tuple(float(x) for x in q)


def _clumps(foliage: CADMesh, provenance: dict) -> tuple[list[ClumpMeasure], list[TemplatePart]]:
    if len(foliage.faces) == 0:
        return [], []
    label = components(foliage)
    meshes = [foliage.subset(label == c) for c in np.unique(label)]
    frames = [_clump_frame(m.vertices, m.faces) for m in meshes]
    # group by shape: triangle count and proportions
    keys = []
    groups: list[list[int]] = []
    for i, (m, (_, _, ext)) in enumerate(zip(meshes, frames, strict=True)):
        shape = np.sort(ext)[::-1] / max(float(ext.max()), 1e-12)
        for g, (n, s) in enumerate(keys):
            if n == len(m.faces) and np.all(np.abs(shape - s) < SAME_SHAPE):
                groups[g].append(i)
                break
        else:
            keys.append((len(m.faces), shape))
            groups.append([i])
    templates: list[TemplatePart] = []
    template_of = np.zeros(len(meshes), dtype=np.int64)
    rep_extent = []
    for g, members in enumerate(groups):
        sizes = np.array([frames[i][2].max() for i in members])
        rep = members[int(np.argsort(sizes)[len(sizes) // 2])]
        centre, axes, ext = frames[rep]
        m = meshes[rep]
        size = float(ext.max())
        local = (m.vertices - centre) @ axes.T / size
        templates.append(_clump_template(f"clump_{g}", local, m, size, provenance))
        rep_extent.append(np.maximum(ext / size, 1e-6))
        template_of[members] = g
    clumps = []
    for i, m in enumerate(meshes):
        centre, axes, ext = frames[i]
        g = int(template_of[i])
        scale = np.full(
            3, float(exact.exp(np.mean(exact.log(np.maximum(ext / rep_extent[g], 1e-9)))))
        )
        clumps.append(
            ClumpMeasure(
                centre=tuple(float(x) for x in centre),
                radius=float(np.linalg.norm(m.vertices - centre, axis=1).max()),
                area=float(face_areas(m.vertices, m.faces).sum()),
                bottom=float(m.vertices[:, 2].min()),
                top=float(m.vertices[:, 2].max()),
                orient=_quat_xyzw(axes),
                scale=tuple(float(x) for x in scale),
                template=g,
            )
        )
    order = np.argsort([-x.centre[2] for x in clumps], kind="stable")
    return [clumps[i] for i in order], templates


def _clump_template(
    name: str, local: np.ndarray, mesh: CADMesh, size: float, provenance: dict
) -> TemplatePart:
    """A clump as a ``leaf`` template in its own frame: centred, principal axes along X, Y, Z,
    largest extent 1."""
    area = float(face_areas(mesh.vertices, mesh.faces).sum())
    m = Measurements(
        length=size,
        base_radius=0.0,
        tip_radius=0.0,
        width=float(np.ptp(local[:, 1]) * size),
        surface_area=area,
        leaf_area=area,
        equivalent_disk_radius=math.sqrt(area / math.pi),
        triangles=len(mesh.faces),
    )
    return TemplatePart(
        name,
        "leaf",
        local,
        mesh.faces.copy(),
        vertex_normals(local, mesh.faces),
        m,
        {**provenance, "clump": "foliage clump, centred, principal axes, largest extent 1"},
        DEFAULT_COLORS["leaf"],
    )


def extract_tree(path: str | Path, *, units: str = "auto", up: str = "auto") -> Extraction:
    """Decompose a whole-tree CAD model into trunk, branches and foliage clumps.

    Parameters
    ----------
    path
        The model (OBJ with materials works best; STL, PLY and glTF are read too).
    units
        ``m``, ``cm``, ``mm``, ``in`` or ``auto`` (a tree between 1 and 120 m tall).
    up
        ``Y``, ``Z`` or ``auto`` (the trunk's axis).

    Raises
    ------
    CADError
        If the model has no wood or no plausible trunk.
    """
    if up.upper() not in ("AUTO", "Y", "Z"):
        raise CADError(f"--up: unknown up axis {up!r}; use Y, Z or auto")
    if units != "auto" and units not in UNITS:
        raise CADError(f"--units: unknown units {units!r}; use one of {', '.join(UNITS)} or auto")
    raw = read_cad(path)
    is_wood, wood_by = _split_wood_foliage(raw)
    if not is_wood.any():
        raise CADError(f"{raw.source}: found no wood (bark) parts; name the material 'Bark'")
    wood = raw.subset(is_wood)
    foliage = raw.subset(~is_wood) if (~is_wood).any() else None
    wood_label = components(wood)
    areas = np.bincount(wood_label, weights=face_areas(wood.vertices, wood.faces))
    biggest = wood.subset(wood_label == int(np.argmax(areas)))
    empty = CADMesh(
        np.zeros((0, 3)),
        np.zeros((0, 3), np.int64),
        np.zeros(0, np.int32),
        (),
        raw.source,
        raw.sha256,
        raw.fmt,
    )
    foliage = foliage if foliage is not None else empty

    axis = _up_axis(wood, foliage, biggest, up)
    up_name = ("+" if axis.sum() > 0 else "-") + "XYZ"[int(np.argmax(np.abs(axis)))]
    rot = _rotation_to_z(axis)
    allv = raw.vertices @ rot.T
    height_units = float(np.ptp(allv[:, 2]))

    if units == "auto":
        lo, hi = TREE_HEIGHT_RANGE
        fits = [u for u in ("m", "cm", "mm", "in") if lo <= height_units * UNITS[u] <= hi]
        unit = fits[0] if fits else "m"
    elif units in UNITS:
        unit = units
    else:
        raise CADError(f"unknown units {units!r}; use one of {', '.join(UNITS)} or auto")
    scale = UNITS[unit]

    def place(m: CADMesh) -> CADMesh:
        return m.with_vertices(m.vertices @ rot.T * scale)

    wood, foliage = place(wood), place(foliage)
    ground = float(wood.vertices[:, 2].min())
    everything = np.concatenate([wood.vertices, foliage.vertices])
    height = float(np.ptp(everything[:, 2]))

    # trunk: the largest wood component touching the ground
    comp_min_z = np.array(
        [
            wood.vertices[np.unique(wood.faces[wood_label == c])][:, 2].min()
            for c in range(len(areas))
        ]
    )
    grounded = np.flatnonzero(comp_min_z <= ground + 0.05 * height)
    trunk_label = int(grounded[np.argmax(areas[grounded])])
    tb = wood.vertices[np.unique(wood.faces[wood_label == trunk_label])]
    base_xy = tb[tb[:, 2] <= ground + 0.02 * height, :2].mean(axis=0)
    offset = np.array([base_xy[0], base_xy[1], ground])
    wood = wood.with_vertices(wood.vertices - offset)
    foliage = foliage.with_vertices(foliage.vertices - offset)

    provenance = {
        "source": raw.source,
        "sha256": raw.sha256,
        "format": raw.fmt,
        "units": unit,
        "upAxis": up_name,
        "extractedFrom": "whole-tree model",
    }
    parts = _wood_parts(wood, trunk_label, wood_label, height)
    trunk = normalise_part(parts[0].mesh, "trunk", name="trunk", provenance=provenance)
    # the trunk template's +X, as an azimuth in the model (to place it back unrotated)
    _, flat = principal_axes(parts[0].mesh.vertices * [1.0, 1.0, 0.0], parts[0].mesh.faces)
    trunk_roll = math.degrees(math.atan2(flat[0, 1], flat[0, 0]))

    branches: list[BranchMeasure] = []
    branch_parts: list[TemplatePart] = []
    index_of = {0: -1}
    for i, p in enumerate(parts[1:], start=1):
        base, tip = p.centreline[0], p.centreline[-1]
        direction = tip - base
        length = float(np.linalg.norm(direction))
        if length <= 1e-6 or p.parent not in index_of:
            continue
        try:
            part = normalise_part(
                p.mesh, "branch", name=f"branch_{len(branch_parts)}", provenance=provenance
            )
        except CADError:
            continue
        parent = index_of[p.parent]
        index_of[i] = len(branches)
        branch_parts.append(part)
        branches.append(
            BranchMeasure(
                length=length,
                base_radius=part.measurements.base_radius,
                insertion_height=float(base[2]),
                angle_to_trunk=math.degrees(
                    math.acos(float(np.clip(direction[2] / length, -1, 1)))
                ),
                base=tuple(float(x) for x in base),
                tip=tuple(float(x) for x in tip),
                azimuth=math.degrees(math.atan2(direction[1], direction[0])),
                parent=parent,
                order=1 if parent < 0 else branches[parent].order + 1,
            )
        )

    clumps, clump_templates = _clumps(foliage, provenance)

    templates = [trunk]
    if branch_parts:
        first = [bp for bp, b in zip(branch_parts, branches, strict=True) if b.order == 1]
        pool = first or branch_parts
        lengths = np.array([b.measurements.length for b in pool])
        rep = pool[int(np.argsort(lengths)[len(lengths) // 2])]
        templates.append(
            TemplatePart(
                "branch",
                "branch",
                rep.vertices,
                rep.faces,
                rep.normals,
                rep.measurements,
                rep.provenance,
                rep.color,
            )
        )
    templates.extend(clump_templates)

    return Extraction(
        source=raw.source,
        sha256=raw.sha256,
        units=unit,
        up_axis=up_name,
        height=height,
        trunk=trunk,
        branches=tuple(branches),
        clumps=tuple(clumps),
        templates=tuple(templates),
        wood_by=wood_by,
        trunk_roll=trunk_roll,
        trunk_centreline=tuple(tuple(float(x) for x in c) for c in parts[0].centreline),
    )

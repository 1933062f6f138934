"""Whole-tree CAD decomposition: wood vs foliage, trunk, branches, foliage clumps, a profile.

Input: one CAD model of a whole tree (e.g. a low-poly game asset) whose wood and foliage are
separate connected parts. Steps:

1. **wood vs foliage** by material/group names (``bark``, ``wood``, ``trunk``... vs ``leaf``,
   ``leaves``, ``foliage``, ``needle``...); groups that match neither are split into connected
   components and classified by shape (elongated tubes are wood, compact clumps foliage);
2. **up axis**: the largest wood component's principal axis, pointing from its lower end
   towards the foliage;
3. **units**: the unit that makes the tree's height plausible (1-120 m);
4. **trunk**: the largest wood component touching the ground; **branches**: the other wood
   components, each measured from its base (the end nearest the trunk axis); **foliage
   clumps**: the foliage components.

The result is a template per part type (trunk, branch, clump) and a measured profile.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cad import (
    UNITS,
    CADMesh,
    TemplatePart,
    components,
    face_areas,
    normalise_part,
    principal_axes,
    read_cad,
)
from .errors import CADError

WOOD_NAMES = re.compile(r"bark|wood|trunk|branch|stem|twig|log|limb", re.IGNORECASE)
FOLIAGE_NAMES = re.compile(r"lea(f|ves)|foliage|needle|crown|canopy|frond|conifer", re.IGNORECASE)
TREE_HEIGHT_RANGE = (1.0, 120.0)


@dataclass(frozen=True)
class BranchMeasure:
    length: float
    base_radius: float
    insertion_height: float
    angle_to_trunk: float  # degrees between the branch axis (base to tip) and the trunk axis


@dataclass(frozen=True)
class ClumpMeasure:
    centre: tuple[float, float, float]
    radius: float  # largest distance from the centre
    area: float
    bottom: float
    top: float


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
    wood_by: str  # "names" or "shape"

    def profile(self) -> dict:
        """The measured profile as plain data (written as TOML)."""
        t = self.trunk.measurements
        b = self.branches
        c = self.clumps
        r6 = lambda x: round(float(x), 6)  # noqa: E731
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
            },
            "branches": {
                "count": len(b),
                "lengths": [r6(x.length) for x in b],
                "base_radii": [r6(x.base_radius) for x in b],
                "insertion_heights": [r6(x.insertion_height) for x in b],
                "angles_to_trunk_deg": [r6(x.angle_to_trunk) for x in b],
            },
            "foliage": {
                "clumps": len(c),
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
    if all(named) and any(wood_groups) and any(foliage_groups):
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
        If the model has no wood or no foliage, or no plausible trunk.
    """
    raw = read_cad(path)
    is_wood, wood_by = _split_wood_foliage(raw)
    if not is_wood.any():
        raise CADError(f"{raw.source}: found no wood (bark) parts; name the material 'Bark'")
    if is_wood.all():
        raise CADError(f"{raw.source}: found no foliage parts; name the material 'Leaves'")
    wood = raw.subset(is_wood)
    foliage = raw.subset(~is_wood)
    wood_label = components(wood)
    areas = np.bincount(wood_label, weights=face_areas(wood.vertices, wood.faces))
    biggest = wood.subset(wood_label == int(np.argmax(areas)))

    # up axis
    if up == "auto":
        _, axes = principal_axes(biggest.vertices, biggest.faces)
        k = int(np.argmax(np.abs(axes[0])))
        axis = np.zeros(3)
        axis[k] = 1.0
        if (foliage.vertices.mean(axis=0) - biggest.vertices.mean(axis=0))[k] < 0:
            axis = -axis
    else:
        names = {"Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}
        if up.upper() not in names:
            raise CADError(f"unknown up axis {up!r}; use Y, Z or auto")
        axis = np.array(names[up.upper()])
    up_name = ("+" if axis.sum() > 0 else "-") + "XYZ"[int(np.argmax(np.abs(axis)))]
    rot = _rotation_to_z(axis)
    allv = raw.vertices @ rot.T
    height_units = float(np.ptp(allv[:, 2]))

    # units
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
    height = float(np.ptp(np.concatenate([wood.vertices, foliage.vertices])[:, 2]))

    # trunk: the largest wood component touching the ground
    comp_min_z = np.array(
        [
            wood.vertices[np.unique(wood.faces[wood_label == c])][:, 2].min()
            for c in range(len(areas))
        ]
    )
    grounded = np.flatnonzero(comp_min_z <= ground + 0.05 * height)
    trunk_label = int(grounded[np.argmax(areas[grounded])])
    trunk_mesh = wood.subset(wood_label == trunk_label)
    tb = trunk_mesh.vertices
    base_sel = tb[:, 2] <= ground + 0.02 * height
    base_xy = tb[base_sel, :2].mean(axis=0)
    offset = np.array([base_xy[0], base_xy[1], ground])
    wood = wood.with_vertices(wood.vertices - offset)
    foliage = foliage.with_vertices(foliage.vertices - offset)
    trunk_mesh = trunk_mesh.with_vertices(trunk_mesh.vertices - offset)

    provenance = {
        "source": raw.source,
        "sha256": raw.sha256,
        "format": raw.fmt,
        "units": unit,
        "upAxis": up_name,
        "extractedFrom": "whole-tree model",
    }
    trunk = normalise_part(trunk_mesh, "trunk", name="trunk", provenance=provenance)

    branches: list[BranchMeasure] = []
    branch_parts: list[TemplatePart] = []
    order = sorted(
        (c for c in range(len(areas)) if c != trunk_label),
        key=lambda c: -areas[c],
    )
    for c in order:
        m = wood.subset(wood_label == c)
        _, axes = principal_axes(m.vertices, m.faces)
        t = (m.vertices - m.vertices.mean(axis=0)) @ axes[0]
        ends = [
            m.vertices[t <= t.min() + 0.05 * np.ptp(t)].mean(axis=0),
            m.vertices[t >= t.max() - 0.05 * np.ptp(t)].mean(axis=0),
        ]
        dist = [float(np.hypot(*e[:2])) for e in ends]
        base, tip = (ends[0], ends[1]) if dist[0] <= dist[1] else (ends[1], ends[0])
        direction = tip - base
        length = float(np.linalg.norm(direction))
        if length <= 0:
            continue
        part = normalise_part(
            m, "branch", name=f"branch_{len(branch_parts)}", provenance=provenance
        )
        branch_parts.append(part)
        angle = math.degrees(math.acos(float(np.clip(direction[2] / length, -1.0, 1.0))))
        branches.append(
            BranchMeasure(
                length=part.measurements.length,
                base_radius=part.measurements.base_radius,
                insertion_height=float(base[2]),
                angle_to_trunk=angle,
            )
        )

    fol_label = components(foliage)
    clumps: list[ClumpMeasure] = []
    clump_parts: list[CADMesh] = []
    for c in np.unique(fol_label):
        m = foliage.subset(fol_label == c)
        centre = m.vertices.mean(axis=0)
        clumps.append(
            ClumpMeasure(
                centre=tuple(float(x) for x in centre),
                radius=float(np.linalg.norm(m.vertices - centre, axis=1).max()),
                area=float(face_areas(m.vertices, m.faces).sum()),
                bottom=float(m.vertices[:, 2].min()),
                top=float(m.vertices[:, 2].max()),
            )
        )
        clump_parts.append(m)
    clump_order = np.argsort([-x.centre[2] for x in clumps], kind="stable")
    clumps = [clumps[i] for i in clump_order]
    clump_parts = [clump_parts[i] for i in clump_order]

    templates = [trunk]
    if branch_parts:
        lengths = np.array([b.measurements.length for b in branch_parts])
        median = int(np.argsort(lengths)[len(lengths) // 2])
        rep = branch_parts[median]
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
    if clump_parts:
        sizes = np.array([x.radius for x in clumps])
        median = int(np.argsort(sizes)[len(sizes) // 2])
        templates.append(normalise_clump(clump_parts[median], provenance))

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
    )


def normalise_clump(mesh: CADMesh, provenance: dict) -> TemplatePart:
    """A foliage clump as a ``leaf`` template: attachment (its lowest point) at the origin,
    Z up kept, scaled to unit size (largest extent 1)."""
    from .cad import DEFAULT_COLORS, Measurements, vertex_normals

    v = mesh.vertices
    low = v[np.argmin(v[:, 2])]
    centre = v.mean(axis=0)
    origin = np.array([centre[0], centre[1], low[2]])
    size = float(np.ptp(v, axis=0).max())
    out = (v - origin) / size
    area = float(face_areas(v, mesh.faces).sum())
    m = Measurements(
        length=size,
        base_radius=0.0,
        tip_radius=0.0,
        width=float(np.ptp(v[:, 0])),
        surface_area=area,
        leaf_area=area,
        equivalent_disk_radius=math.sqrt(area / math.pi),
        triangles=len(mesh.faces),
    )
    return TemplatePart(
        "clump",
        "leaf",
        out,
        mesh.faces.copy(),
        vertex_normals(out, mesh.faces),
        m,
        {**provenance, "clump": "foliage clump, attachment at its lowest point"},
        DEFAULT_COLORS["leaf"],
    )

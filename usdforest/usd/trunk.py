"""A tree asset's own trunk: the stem form of :mod:`usdforest.grow.stems` as a template layer
(``templates/stem_<hash>.usdc`` beside the CAD-derived ones, referenced by ``/Tree/Trunk`` as
any trunk template is), and the girth tape on a tree of any scale.

The stem is drawn in the frame the trunk template's placement gives it (base at the origin,
axis +Z, unit length times the trunk's length), leaned with the rest of the tree
(:func:`usdforest.grow.stems.lean_matrix` turns the skeleton), and its foot sheared flush with
level ground: the lowest 30 cm of the stem (less on a small one) follow the tilt back, so the
tree stands on its base point with no gap under the high side of the foot and nothing below
z = 0.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from usdforest.grow import exact
from usdforest.grow.architecture import BREAST_HEIGHT, TreeSize, scaled_dbh
from usdforest.grow.bounds import hull_vertices
from usdforest.grow.placement import CENTRELINE_SAMPLES, Placement, WoodShape
from usdforest.grow.skeleton import Skeleton
from usdforest.grow.stems import StemForm, StemMesh, lean_matrix, ovality_draw, stem_mesh
from usdforest.usd.template import TemplateInfo

FOOT_BLEND = 0.3  # m of the stem over which the foot's shear fades


PLACEHOLDER = "stem"  # the stem template's name until it is drawn (then its content's)


def content_name(template: StemTemplate) -> str:
    """A stem template's name from what it holds (its vertices, faces and measurements as
    stored): the same stem, the same name; another, another."""
    from usdforest.usd.template import stable_points

    h = hashlib.sha1(stable_points(template.vertices).astype("<f8").tobytes())
    h.update(np.ascontiguousarray(template.faces, dtype="<i8").tobytes())
    h.update(repr(sorted(template.measurements.items())).encode())
    return "stem_" + h.hexdigest()[:16]


def placeholder_shape() -> WoodShape:
    """The shape placement sizes a stem template by: its normalised base radius is the
    trunk's own (so the template is placed at the trunk's length, uniformly), straight."""
    return WoodShape(1.0, np.zeros((CENTRELINE_SAMPLES, 2)), 0.0)


def leaned(sk: Skeleton, rotation: np.ndarray) -> Skeleton:
    """The skeleton turned about its base by ``rotation`` (column vectors)."""
    rt = np.ascontiguousarray(np.asarray(rotation, dtype=float).T)
    # (exact.matmul: the same bits whatever BLAS kernel numpy picks; rows are vectors)
    return replace(
        sk,
        start=exact.matmul(sk.start, rt),
        end=exact.matmul(sk.end, rt),
        leaf_position=exact.matmul(sk.leaf_position, rt),
        leaf_frame=exact.matmul(sk.leaf_frame, rt),  # rows: heading, left, up
    )


def flush_foot(points: np.ndarray, rows: np.ndarray, breast: float) -> np.ndarray:
    """``points`` (the stem's frame) with the foot sheared so that, placed by the row-vector
    transform ``rows`` (4 x 4), the lowest ring lies on z = 0; the shear fades linearly over
    :data:`FOOT_BLEND` (at most half the breast height: the tape's section is untouched)."""
    p = points.copy()
    m = np.asarray(rows, dtype=float)
    lift = -(p[:, 0] * m[0, 2] + p[:, 1] * m[1, 2] + m[3, 2]) / m[2, 2]
    blend = min(FOOT_BLEND, 0.5 * breast)
    w = np.clip(1.0 - p[:, 2] / blend, 0.0, 1.0)
    p[:, 2] += lift * w
    return p


@dataclass(frozen=True, eq=False)
class StemTemplate:
    """A stem drawn for one tree asset, ready to be written as a template layer (unit
    length, the foot flush): :meth:`part` is what :func:`usdforest.usd.template.write_template`
    takes (the CAD stack loads only then)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    measurements: dict
    provenance: dict
    color: tuple[float, float, float]

    def part(self):
        from usdforest.cad.parts import Measurements, TemplatePart
        from usdforest.meshes import vertex_normals

        return TemplatePart(
            name=self.name,
            part="trunk",
            vertices=self.vertices,
            faces=self.faces,
            normals=vertex_normals(self.vertices, self.faces),
            measurements=Measurements(**self.measurements),
            provenance=self.provenance,
            color=self.color,
        )


def stem_template(
    name: str,
    mesh: StemMesh,
    rows: np.ndarray,
    breast: float,
    color: tuple[float, float, float],
    provenance: dict,
) -> tuple[StemTemplate, TemplateInfo]:
    """The stem as a template (unit length) and the info a tree build reads of it.

    ``rows`` is the trunk prim's transform with a uniform scale of the stem's length (the
    template's normalised base radius is the trunk's: :func:`placeholder_shape`)."""
    length = mesh.length
    v = flush_foot(mesh.vertices(), rows / np.array([[length], [length], [length], [1.0]]), breast)
    f = mesh.faces()
    scaled = v / length
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    measurements = {
        "length": length,
        "base_radius": float(np.mean(np.linalg.norm(mesh.xy[0], axis=1))),
        "tip_radius": 0.0,
        "width": 2.0 * float(np.linalg.norm(mesh.xy, axis=2).max()),
        "surface_area": float(area.sum()),
        "leaf_area": 0.0,
        "equivalent_disk_radius": 0.0,
        "triangles": len(f),
    }
    info = TemplateInfo(
        path=Path(f"{name}.usdc"),
        part="trunk",
        name=name,
        base_radius=1.0,
        tip_radius=0.0,
        measurements=measurements,
        centreline=np.zeros((CENTRELINE_SAMPLES, 2)),
        hull=hull_vertices(scaled),
    )
    return StemTemplate(name, scaled, f, measurements, provenance, color), info


@dataclass(frozen=True, eq=False)
class StemGirth:
    """The girth tape on a tree asset's own stem: the DBH of the asset scaled by ``scale``
    (the section 1.3 m up its stem, perpendicular to it, 1.3 / scale on the asset)."""

    mesh: StemMesh

    def dbh(self, scale: np.ndarray) -> np.ndarray:
        s = np.asarray(scale, dtype=float)
        z = np.round(BREAST_HEIGHT / s, 5)  # a tenth of a millimetre: one section each
        return s * self.mesh.girth_dbh(z).reshape(s.shape)


@dataclass(frozen=True)
class ConeGirth:
    """The girth tape on the shared conical trunk template (:func:`scaled_dbh`); NaN for a
    tree without an allometric size."""

    dbh0: float
    height: float

    def dbh(self, scale: np.ndarray) -> np.ndarray:
        s = np.asarray(scale, dtype=float)
        if not math.isfinite(self.dbh0):
            return np.full(s.shape, np.nan)
        return scaled_dbh(np.full(s.shape, self.dbh0), np.full(s.shape, self.height), s)


def form_provenance(species: str, form: StemForm, ovality: float, lean: tuple) -> dict:
    """What a stem template records of where it came from."""
    return {
        "generator": "usdforest.grow.stems",
        "species": species,
        "taper": form.taper,
        "ovality": round(ovality, 4),
        "leanDegrees": round(float(lean[0]), 3),
        "leanAzimuth": round(float(lean[1]), 2),
    }


def lean_within(sk: Skeleton, angle: float, azimuth: float) -> float:
    """The lean, no more than keeps every segment and leaf site of the tree as high above
    the ground as it was or above it (a small tree's lowest branches would dip into the
    ground on its leaning side)."""

    def low(a: float) -> float:
        t = leaned(sk, lean_matrix(a, azimuth))
        return min(float(t.start[:, 2].min(initial=0.0)), float(t.end[:, 2].min(initial=0.0)),
                   float(t.leaf_position[:, 2].min(initial=0.0)))  # fmt: skip

    floor = min(low(0.0), 0.0) - 1e-9
    if low(angle) >= floor:
        return angle
    lo, hi = 0.0, angle
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if low(mid) >= floor else (lo, mid)
    return lo


def uniform_trunk(placement: Placement) -> Placement:
    """``placement`` with its trunk prim scaled uniformly by its length (a stem template's
    normalised base radius is the trunk's own: :func:`placeholder_shape`)."""
    i = placement.trunk
    scale = np.array(placement.scale, dtype=float)
    scale[i] = float(scale[i, 2])
    return replace(placement, scale=scale)


def draw_stem(
    placement: Placement,
    top: float,
    species: str,
    color: tuple[float, float, float],
    form: StemForm,
    size: TreeSize,
    lean: tuple[float, float],
    rng: np.random.Generator,
) -> tuple[Placement, tuple[StemTemplate, TemplateInfo, StemMesh]]:
    """A tree's own stem, drawn after its crown is placed (``placement``, its trunk scaled
    uniformly: :func:`uniform_trunk`): the trunk's length and the tree's ``top`` as grown
    (leaves and shoots over the stem) set where 1.3 m falls on the asset when its instances
    stand as tall as its target ``size``, and the girth tape there reads the target's DBH.
    Returns the placement with the template's name (its content's: two trees of one name
    and size, a preset's second entry or an understorey's, may grow different stems and
    share a templates folder), the template, its info and the mesh."""
    i = placement.trunk
    length = float(placement.scale[i, 2])
    name = placement.templates[placement.template[i]]
    grown = max(top, length)
    breast = BREAST_HEIGHT * grown / size.height
    dbh = size.dbh * grown / size.height
    mesh = stem_mesh(form, length, grown, breast, dbh, ovality_draw(form, rng), rng)
    made = form_provenance(species, form, mesh.ovality, lean)
    template, info = stem_template(name, mesh, placement.wood_matrices()[i], breast, color, made)
    own = content_name(template)
    template, info = replace(template, name=own), replace(info, name=own, path=Path(f"{own}.usdc"))
    names = tuple(own if t == name else t for t in placement.templates)
    return replace(placement, templates=names), (template, info, mesh)

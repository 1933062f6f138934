"""The dead wood layer (coarse woody debris, as foresters call it): a PointInstancer of
CAD-templated pieces, their colliders and their ground truth.

::

    forest_assets/
      deadwood.usdc     /Forest/DeadWood  PointInstancer (kind group), one prototype per
                        kind and decay class: /Forest/DeadWood/Prototypes/<Kind>_<decay>
                        -> templates/deadwood_<kind>_<decay>.usdc (labels dead_wood, kind)
      deadwood.csv      id,kind,decay,x,y,z,azimuth,pitch,length,diameter,volume

Pieces are scaled anisotropically (across by their diameter, along by their length): a
piece's volume is its prototype mesh's volume times the product of its scales.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdforest.grow import exact
from usdforest.grow.colliders import Capsules
from usdforest.grow.deadwood import DECAY_CLASSES, KINDS, Pieces, PieceShape
from usdforest.rotations import quat_from_matrix
from usdforest.usd.layers import mesh_triangles, new_layer, prim
from usdforest.usd.physics import author_capsules
from usdforest.usd.scatter import (
    TemplateProto,
    author_instancer,
    copy_shipped_templates,
    instance_matrices,
    labelled,
    prototype_meshes,
)

CSV_HEADER = (
    "id",
    "kind",
    "decay",
    "x",
    "y",
    "z",
    "azimuth",
    "pitch",
    "length",
    "diameter",
    "volume",
)


def template_name(kind: str, decay: int) -> str:
    """The shipped template of a kind and decay class."""
    return f"deadwood_{kind}_{decay}"


def prototype_name(kind: str, decay: int) -> str:
    return f"{kind.capitalize()}_{decay}"


def prototypes() -> list[tuple[str, int]]:
    """Every (kind, decay class), in prototype order."""
    return [(k, d) for k in KINDS for d in range(1, DECAY_CLASSES + 1)]


def mesh_volume(tri: np.ndarray) -> float:
    """Volume enclosed by closed, outward-wound triangles ``(m, 3, 3)`` (divergence theorem)."""
    t = np.asarray(tri, dtype=float)
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def piece_shapes() -> dict[tuple[str, int], PieceShape]:
    """Each shipped dead-wood template as a :class:`PieceShape` (its hull as
    :func:`~usdforest.usd.template.read_template` reads it)."""
    from usdforest.cad.library import template_path
    from usdforest.usd.template import read_template

    out = {}
    for kind, decay in prototypes():
        path = template_path(template_name(kind, decay))
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
        meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
        volume = sum(mesh_volume(mesh_triangles(m, np.eye(4))) for m in meshes)
        out[(kind, decay)] = PieceShape(volume, read_template(path).hull)
    return out


def copy_deadwood_templates(folder: Path) -> None:
    """Copy the dead-wood templates into the forest's ``templates/`` folder."""
    copy_shipped_templates([template_name(k, d) for k, d in prototypes()], folder)


def instance_transforms(
    pieces: Pieces, shapes: dict[tuple[str, int], PieceShape]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PointInstancer ``(positions, orientations (x, y, z, w), scales, protoIndices)``."""
    order = prototypes()
    pairs = zip(pieces.kind, pieces.decay, strict=True)
    index = np.array([order.index((KINDS[k], int(d))) for k, d in pairs], dtype=np.int32)
    radius = np.array([shapes[order[i]].radius for i in index], dtype=float)
    across = pieces.diameter / (2 * radius)
    third = np.cross(pieces.axis, pieces.side)
    rot = np.stack([pieces.side, third, pieces.axis], axis=2)  # columns: the template's X, Y, Z
    scales = np.stack([across, across, pieces.length], axis=1)
    return pieces.base, quat_from_matrix(rot), scales, index


def deadwood_layer(
    pieces: Pieces,
    shapes: dict[tuple[str, int], PieceShape],
    anchor: np.ndarray,
    ids: np.ndarray,
    colliders: Capsules | None = None,
) -> Sdf.Layer:
    """``/Forest/DeadWood`` for ``pieces`` in recipe coordinates, written about ``anchor``;
    with ``colliders`` (:func:`deadwood_capsules`) also ``/Forest/Colliders/D_<id>`` (a
    tiled forest's; an untiled one puts them in its collision layer)."""
    layer = new_layer("Forest", comment="usdforest dead wood")
    pos, quat, scales, index = instance_transforms(pieces, shapes)
    pos = pos - np.array([anchor[0], anchor[1], 0.0])
    protos = [
        TemplateProto(
            prototype_name(kind, decay),
            f"./templates/{template_name(kind, decay)}.usdc",
            ("dead_wood", kind),
            {"kind": kind, "decayClass": decay},
        )
        for kind, decay in prototypes()
    ]
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        author_instancer(
            forest,
            "DeadWood",
            protos,
            (pos, quat, scales, index),
            ids,
            deadwood_extent(pieces, shapes, anchor),
        )
        if colliders is not None and len(colliders):
            author_capsules(prim(forest, "Colliders", "Scope"), colliders)
    return layer


def deadwood_extent(pieces: Pieces, shapes: dict, anchor: np.ndarray) -> np.ndarray:
    """A box around every piece (in the layers' frame, about ``anchor``): its axis widened
    by its largest reach from the axis."""
    if not len(pieces):
        return np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    pos = pieces.base - np.array([anchor[0], anchor[1], 0.0])
    reach = np.array(
        [shapes[(KINDS[k], int(d))].reach for k, d in zip(pieces.kind, pieces.decay, strict=True)]
    )
    # orientations are stored as half floats (quath): a 10 m log's ends may move by 1 cm
    r = (pieces.diameter / 2 * reach + 0.005 * pieces.length)[:, None]
    tip = pos + pieces.axis * pieces.length[:, None]
    lo = np.minimum(pos, tip) - r
    hi = np.maximum(pos, tip) + r
    return np.stack([lo.min(axis=0), hi.max(axis=0)])


def deadwood_capsules(pieces: Pieces, anchor: np.ndarray, ids: np.ndarray) -> Capsules:
    """A collider capsule along each piece's axis with the piece's radius, ending at its
    ends (a stump shorter than it is wide gets a sphere of its height's half, on the
    ground)."""
    base = pieces.base - np.array([anchor[0], anchor[1], 0.0])
    tip = base + pieces.axis * pieces.length[:, None]
    r = np.minimum(pieces.diameter / 2, pieces.length / 2)
    names = tuple(f"D_{int(i):07d}" for i in ids)
    return Capsules(names, base, tip, r)


def write_deadwood_csv(path: Path, pieces: Pieces, ids: np.ndarray) -> None:
    """``deadwood.csv``: one row per piece (recipe coordinates of the middle of its axis;
    azimuth and pitch of the axis in degrees; metres and m³)."""
    from usdforest import csvtext

    c = pieces.centre
    az = np.degrees(exact.arctan2(pieces.axis[:, 1], pieces.axis[:, 0]))
    pitch = np.degrees(exact.arcsin(np.clip(pieces.axis[:, 2], -1, 1)))
    with path.open("wb") as f:
        f.write((",".join(CSV_HEADER) + "\n").encode())
        csvtext.write_rows(
            f,
            len(pieces),
            lambda i: (
                csvtext.integers(np.asarray(ids)[i]),
                csvtext.labels(pieces.kind[i], KINDS),
                csvtext.integers(pieces.decay[i]),
                csvtext.fixed(c[i, 0], 3),
                csvtext.fixed(c[i, 1], 3),
                csvtext.fixed(c[i, 2], 3),
                csvtext.fixed(az[i], 2),
                csvtext.fixed(pitch[i], 2),
                csvtext.fixed(pieces.length[i], 3),
                csvtext.fixed(pieces.diameter[i], 4),
                csvtext.fixed(pieces.volume[i], 5),
            ),
        )


def is_dead_wood(instancer: Usd.Prim) -> bool:
    """Whether a PointInstancer's prototypes are dead wood (labelled ``dead_wood``)."""
    return labelled(instancer, "dead_wood")


def dead_wood_figures(instancer: Usd.Prim | None, area: float) -> dict:
    """Dead wood measured on the composed stage: each prototype's mesh volume times the
    determinant of each instance's transform, per kind (the prototype's ``usdforest:kind``),
    in m³ and pieces per hectare of ``area`` m². ``None``: a forest without dead wood."""
    out = {
        "dead_wood_m3_per_ha": 0.0,
        "dead_wood_by_kind_m3_per_ha": {k: 0.0 for k in KINDS},
        "dead_wood_pieces_per_ha": {k: 0.0 for k in KINDS},
    }
    if instancer is None:
        return out
    ha = area / 1e4
    pi = UsdGeom.PointInstancer(instancer)
    stage = instancer.GetStage()
    idx, mats = instance_matrices(instancer)
    if not len(idx):
        return out
    det = np.abs(np.linalg.det(mats[:, :3, :3]))
    for k, target in enumerate(pi.GetPrototypesRel().GetTargets()):
        sel = idx == k
        if not sel.any():
            continue
        proto = stage.GetPrimAtPath(target)
        kind = str((proto.GetCustomDataByKey("usdforest") or {}).get("kind", "log"))
        unit = sum(mesh_volume(tri) for tri in prototype_meshes(proto))
        volume = unit * float(det[sel].sum())
        out["dead_wood_by_kind_m3_per_ha"][kind] += volume / ha
        out["dead_wood_pieces_per_ha"][kind] += int(sel.sum()) / ha
    out["dead_wood_m3_per_ha"] = float(sum(out["dead_wood_by_kind_m3_per_ha"].values()))
    return out

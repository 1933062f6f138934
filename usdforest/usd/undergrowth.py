"""The understorey layer: shrubs and young trees as instances of tree assets, and their
ground truth.

::

    forest_assets/
      understorey.usdc  /Forest/Understorey  PointInstancer (kind group), one prototype per
                        shrub variant and per young-tree height class:
                        /Forest/Understorey/Prototypes/Hazel_<k>, Bramble_<k> (labels shrub,
                        form), Sapling_<species>_<k> (labels regeneration, species)
                        -> trees/<name>.usdc (each selecting the forest's lod)
      understorey.csv   id,layer,name,x,y,z,height,scale,footprint,light

Shrubs and young trees are grown like the trees (L-system skeletons dressed with the CAD
templates, :func:`usdforest.usd.tree.build_tree`) and are instanced like them; they are not
trees of the stand (no tree id, not in ``trees.csv`` or the stand's figures).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdforest.grow.understorey import Plants
from usdforest.usd.instances import yaw_quaternions
from usdforest.usd.layers import class_labels, new_layer, prim
from usdforest.usd.scatter import TemplateProto, author_instancer, instance_matrices

LAYERS = ("shrub", "regeneration")
CSV_HEADER = (
    "id",
    "layer",
    "name",
    "x",
    "y",
    "z",
    "height",
    "scale",
    "footprint",
    "light",
)


@dataclass(frozen=True)
class Kind:
    """One understorey prototype: its layer (``shrub`` or ``regeneration``), its form or
    species, its asset's file stem, its height (m) and crown footprint (m²) at scale 1, and
    its extent ``(2, 3)`` about its base."""

    layer: str
    name: str
    stem: str
    height: float
    footprint: float
    extent: np.ndarray

    @property
    def prim_name(self) -> str:
        return re.sub(r"[^A-Za-z0-9_]", "_", self.stem[:1].upper() + self.stem[1:])


def understorey_extent(plants: Plants, kinds: list[Kind], z: np.ndarray, anchor) -> np.ndarray:
    """A box round every plant (turned about +Z: its extent's horizontal reach all round)."""
    if not len(plants):
        return np.zeros((2, 3))
    ext = np.stack([k.extent for k in kinds])[plants.proto]  # (n, 2, 3)
    reach = np.max(np.abs(ext[:, :, :2]), axis=(1, 2)) * np.sqrt(2) * plants.scale
    pos = np.column_stack([plants.xy - np.asarray(anchor)[:2], z])
    lo = pos - np.column_stack([reach, reach, -ext[:, 0, 2] * plants.scale])
    hi = pos + np.column_stack([reach, reach, ext[:, 1, 2] * plants.scale])
    return np.stack([lo.min(axis=0), hi.max(axis=0)])


def understorey_layer(
    plants: Plants,
    kinds: list[Kind],
    z: np.ndarray,
    anchor: np.ndarray,
    ids: np.ndarray,
    lod: str,
) -> Sdf.Layer:
    """``/Forest/Understorey`` for ``plants`` (recipe coordinates, on the ground at ``z``),
    written about ``anchor``; its prototypes reference ``./trees/<stem>.usdc`` at ``lod``."""
    layer = new_layer("Forest", comment="usdforest understorey: shrubs and young trees")
    pos = np.column_stack([plants.xy - np.asarray(anchor)[:2], z])
    quat = yaw_quaternions(plants.yaw)
    scales = np.repeat(plants.scale[:, None], 3, axis=1)
    protos = [
        TemplateProto(
            k.prim_name,
            f"./trees/{k.stem}.usdc",
            (k.layer, k.name),
            {
                "layer": k.layer,
                ("form" if k.layer == "shrub" else "species"): k.name,
                "height": round(k.height, 4),
            },
            lod,
        )
        for k in kinds
    ]
    with Sdf.ChangeBlock():
        forest = prim(layer, "Forest", "Xform")
        forest.kind = "assembly"
        author_instancer(
            forest,
            "Understorey",
            protos,
            (pos, quat, scales, plants.proto),
            ids,
            understorey_extent(plants, kinds, z, anchor),
        )
    return layer


def write_understorey_csv(
    path: Path, plants: Plants, kinds: list[Kind], z: np.ndarray, ids: np.ndarray
) -> None:
    """``understorey.csv``: one row per plant (recipe coordinates of its base; metres, its
    scale of its prototype, the m² its crown covers, the relative light at its cell)."""
    from usdforest import csvtext

    layer = np.array([LAYERS.index(k.layer) for k in kinds], np.int64)[plants.proto]
    names = sorted({k.name for k in kinds})
    name = np.array([names.index(k.name) for k in kinds], np.int64)[plants.proto]
    foot = np.array([k.footprint for k in kinds])[plants.proto] * plants.scale**2
    height = np.array([k.height for k in kinds])[plants.proto] * plants.scale
    with path.open("wb") as f:
        f.write((",".join(CSV_HEADER) + "\n").encode())
        csvtext.write_rows(
            f,
            len(plants),
            lambda i: (
                csvtext.integers(np.asarray(ids)[i]),
                csvtext.labels(layer[i], LAYERS),
                csvtext.labels(name[i], tuple(names)),
                csvtext.fixed(plants.xy[i, 0], 3),
                csvtext.fixed(plants.xy[i, 1], 3),
                csvtext.fixed(z[i], 3),
                csvtext.fixed(height[i], 3),
                csvtext.fixed(plants.scale[i], 4),
                csvtext.fixed(foot[i], 3),
                csvtext.fixed(plants.light[i], 4),
            ),
        )


def is_understorey(instancer: Usd.Prim) -> bool:
    """Whether every prototype of a PointInstancer is a shrub or a young tree."""
    pi = UsdGeom.PointInstancer(instancer)
    targets = pi.GetPrototypesRel().GetTargets()
    stage = instancer.GetStage()
    return bool(targets) and all(
        set(class_labels(stage.GetPrimAtPath(t))) & set(LAYERS) for t in targets
    )


def understorey_figures(
    instancer: Usd.Prim | None, area: float, footprint: dict[str, float]
) -> dict:
    """Shrub cover (each shrub prototype's crown footprint, ``footprint`` by prototype path,
    times each instance's horizontal scales, over the region's ``area`` m²), shrubs per
    hectare by form, and young trees per hectare by species, on the composed stage."""
    out: dict = {
        "shrub_cover": 0.0,
        "shrubs_per_ha": {},
        "regeneration_stems_per_ha": 0.0,
        "regeneration_by_species_per_ha": {},
    }
    if instancer is None:
        return out
    idx, mats = instance_matrices(instancer)
    if not len(idx):
        return out
    ha = area / 1e4
    flat = np.abs(np.linalg.det(mats[:, :2, :2]))
    pi = UsdGeom.PointInstancer(instancer)
    stage = instancer.GetStage()
    for k, target in enumerate(pi.GetPrototypesRel().GetTargets()):
        sel = idx == k
        data = stage.GetPrimAtPath(target).GetCustomDataByKey("usdforest") or {}
        n = int(sel.sum())
        if data.get("layer") == "shrub":
            form = str(data.get("form"))
            out["shrubs_per_ha"][form] = out["shrubs_per_ha"].get(form, 0.0) + n / ha
            out["shrub_cover"] += footprint[str(target)] * float(flat[sel].sum()) / area
        elif data.get("layer") == "regeneration":
            sp = str(data.get("species"))
            by = out["regeneration_by_species_per_ha"]
            by[sp] = by.get(sp, 0.0) + n / ha
            out["regeneration_stems_per_ha"] += n / ha
    return out

"""Lidar points as FOR-instanceV2 ships them: a binary PLY of one plot, each point with its
semantic class ``semantic_seg`` (1 ground, 2 wood, 3 leaf; 0 unlabelled) and its tree
``treeID`` (0 on no tree), the format ForestFormer3D and the loaders built on it read
(their ``load_forainetv2_data.py`` subtracts 1 from ``semantic_seg`` and takes 0, the
ground, as the background).

The mapping from the project's classes follows the FOR-instance one of
:func:`usdforest.sensors.lidar.las.for_instance_classes`, whose stem, live and woody
branches FOR-instanceV2 folds into wood and leaf: a tree's trunk and branches are wood, its
leaves or needles leaf; the ground is ground, and so is FOR-instance's low vegetation
(ground vegetation, shrubs and regeneration that are no tree, dead wood on the floor), which
FOR-instanceV2's three classes leave out of the trees.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from usdforest.atomic import atomic_path
from usdforest.sensors.lidar.las import (
    FlightReturns,
    benchmark_tree_ids,
    for_instance_classes,
    map_shift,
)

# FOR-instance's codes (las.FOR_INSTANCE, las.FOR_INSTANCE_TREE) to FOR-instanceV2's
FOR_INSTANCE_V2 = {0: 0, 1: 1, 2: 1, 3: 0, 4: 2, 5: 3, 6: 2}


def for_instance_v2_classes(cls: np.ndarray, tree: np.ndarray) -> np.ndarray:
    """FOR-instanceV2's ``semantic_seg`` (int32) of returns of our classes ``cls`` on trees
    ``tree`` (-1: on none): 2 wood and 3 leaf on a tree, 1 ground (with what is no tree),
    0 unlabelled."""
    lut = np.zeros(256, dtype=np.int32)
    for v1, v2 in FOR_INSTANCE_V2.items():
        lut[v1] = v2
    return lut[for_instance_classes(cls, tree)]


def write_ply(
    r: FlightReturns,
    out: Path,
    *,
    origin: np.ndarray | None = None,
    point_source: np.ndarray | None = None,
) -> Path:
    """A binary little-endian PLY of ``r`` with one ``vertex`` element: x, y, z (float64,
    the stage origin's map position ``origin`` added to x and y, as the LAS has them),
    ``intensity`` (uint16), ``return_number`` and ``number_of_returns`` (uint8),
    ``gps_time`` (float64, the path's seconds), ``point_source`` (uint16: the station or
    line, 1-based), ``semantic_seg`` (int32, :func:`for_instance_v2_classes`) and
    ``treeID`` (int32: ``tree_id + 1``, 0 on no tree, as the LAS's ``treeID``). Written
    with plyfile, atomically."""
    from plyfile import PlyData, PlyElement

    xyz = np.asarray(r.points, dtype=float) + map_shift(origin)
    rows = np.empty(
        len(r),
        dtype=[
            ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("intensity", "<u2"),
            ("return_number", "u1"), ("number_of_returns", "u1"), ("gps_time", "<f8"),
            ("point_source", "<u2"), ("semantic_seg", "<i4"), ("treeID", "<i4"),
        ],
    )  # fmt: skip
    rows["x"], rows["y"], rows["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rows["intensity"] = r.intensity
    rows["return_number"] = r.return_number
    rows["number_of_returns"] = r.number_of_returns
    rows["gps_time"] = r.gps_time
    rows["point_source"] = 1 if point_source is None else np.asarray(point_source, np.uint16)
    rows["semantic_seg"] = for_instance_v2_classes(r.cls, r.tree)
    rows["treeID"] = benchmark_tree_ids(r.tree)
    from usdforest import __version__

    ply = PlyData(
        [PlyElement.describe(rows, "vertex")],
        text=False,
        byte_order="<",
        comments=[
            f"usdforest {__version__}: {r.system}",
            "semantic_seg: 0 unlabelled, 1 ground, 2 wood, 3 leaf (FOR-instanceV2)",
            "treeID: 0 no tree, else trees.csv id + 1",
        ],
    )
    with atomic_path(out) as tmp, tmp.open("wb") as f:
        ply.write(f)
    return out

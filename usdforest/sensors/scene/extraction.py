"""World-space geometry of any stage for sensors: triangles with semantic class, tree id and
prim path, and leaves as disk reflectors.

Every PointInstancer level is expanded with ``ComputeInstanceTransformsAtTime``. Instances of
a tree prototype (a prim labelled ``tree``) carry the instancer's ``ids`` as tree ids. Culling
comes before expansion: only tree instances whose bounds come within ``radius`` of ``centre``
are kept, so a scan near one corner of a 1 km² forest does not expand the whole forest.

Instances stay instances, on two levels: each tree prototype's wood triangles are gathered
once in the prototype's own space and every tree is a transform to it (:class:`Instances`);
each leaf (or shoot) is a transform of one of a few leaf shapes (:class:`LeafInstances`,
:class:`Shape`). Ray casting follows both levels
(:class:`~usdforest.sensors.cast.raycast.SceneCaster`) instead of copying a million triangles per
tree and fifty per shoot. ``instancing=False`` copies every triangle instead.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from usdforest.sensors.scene.scenetypes import (
    Instances,
    LeafInstances,
    Leaves,
    Scene,
    Sources,
)
from usdforest.sensors.scene.stageframe import stage_frame, stage_time
from usdforest.sensors.scene.walk import Part, StageWalk, realise
from usdforest.usd.layers import class_labels, open_stage

if TYPE_CHECKING:
    from pxr import Usd


def extract_scene(
    stage_path: str | Path,
    *,
    centre: np.ndarray | None = None,
    radius: float | None = None,
    instancing: bool = True,
    leaf_triangles: bool = True,
    reflectors: bool = True,
    cache: bool = True,
    progress: Callable[[str, int, int], None] | None = None,
    time: float | None = None,
    opened: Usd.Stage | None = None,
) -> Scene:
    """Triangles and leaf reflectors of a stage, culled to a sphere around ``centre``, in
    metres with Z up whatever the stage's own units and up axis (:func:`stage_frame`).

    Parameters
    ----------
    stage_path
        Any USD stage: a tree, a forest, a simulation stage that references them.
    centre, radius
        Keep only tree instances and leaves within ``radius`` of ``centre`` (all when
        omitted), both in metres in the sensors' frame.
    instancing
        Keep tree instances as transforms of their prototypes (default) or copy triangles.
    leaf_triangles
        Give rays leaves to meet (default): as instances of their shapes, or copied into
        triangles without ``instancing``. A sonar that casts no ray needs the leaves as
        reflectors only: ``False`` skips their geometry.
    reflectors
        Gather every leaf in reach as a reflector (default; the sonar's input). A lidar or
        camera needs none: ``False`` saves a tuple of arrays per leaf.
    cache
        Reuse tree prototypes gathered by an earlier call on the same stage content, and keep
        the ones gathered now (:mod:`usdforest.sensors.scene.scenecache`; default).
    progress
        ``progress(stage, done, total)`` as tree prototypes are gathered and each tree's
        leaves placed as reflectors.
    time
        Seconds into the stage's animation (its time codes over ``timeCodesPerSecond``):
        instances and prims stand where the stage's time samples put them then, e.g. a
        forest's trees swaying and its leaves fluttering in its wind layer. Omitted: the
        stage's default values, the still forest.
    opened
        The stage at ``stage_path`` as :func:`open_stage` (``sound``, ``full``) opened it,
        to read instead of opening it again (seconds for a forest): a flight shares one.
    """
    path = Path(stage_path)
    stage = opened if opened is not None else open_stage(path, sound=True, full=True)
    walk = StageWalk(
        stage,
        stage_frame(path),
        stage_time(stage, time),
        centre=centre,
        radius=radius,
        instancing=instancing,
        leaf_triangles=leaf_triangles,
        reflectors=reflectors,
        use_store=cache and instancing,
        progress=progress,
    )
    bounds = walk.bounds()
    part = walk.subtree(stage.GetPseudoRoot(), top=True)
    # the leaves met outside any tree prototype (a lone tree's, a stage's own), in reach
    realised = [realise(b, centre, radius, walk.geometry, reflectors) for b in part.batches]
    whole = Part.concat([part, *(r[1] for r in realised)])
    world_leaves = LeafInstances.concat([r[2] for r in realised])
    leaves = Leaves.concat([r[0] for r in realised] + walk.placed_reflectors())
    turns, sweep = walk.turns()
    turning = bool(leaves.turning.any()) or turns is not None
    tree, leaf_tree = whole.tree, leaves.tree
    if _lone_tree(stage, walk.placed, tree):  # a stage of one tree, not instanced: tree id 0
        tree = np.zeros_like(tree)
        leaf_tree = np.zeros_like(leaf_tree)
        world_leaves = replace(world_leaves, tree=np.zeros_like(world_leaves.tree))
    protos = tuple(walk.protos)
    placed = walk.placed
    has_shapes = world_leaves.shape.size or any(len(p.leaf_instances) for p in protos)
    return Scene(
        whole.tri,
        whole.cls,
        tree,
        whole.path,
        tuple(walk.paths),
        replace(leaves, tree=leaf_tree),
        bounds,
        protos,
        Instances(
            np.array([k for k, _, _ in placed], dtype=np.int64),
            np.array([m for _, m, _ in placed]).reshape(-1, 4, 4),
            np.array([t for _, _, t in placed], dtype=np.int64),
        ),
        tuple(dict.fromkeys(walk.unseen)),
        tuple(walk.shapes) if has_shapes or turning else (),
        world_leaves,
        Sources.of(walk.sources, walk.part_rows),
        tuple(walk.shape_keys) if turning else (),
        turns,
        sweep,
    )


def _lone_tree(stage: Usd.Stage, placed: list, tree: np.ndarray) -> bool:
    """Whether ``stage`` holds one tree that is not instanced (no tree placed, no triangle
    of a tree, a prim labelled ``tree``)."""
    return (
        not placed
        and not (tree >= 0).any()
        and any("tree" in class_labels(p) for p in stage.Traverse())
    )

"""Where a stage's own units, axes and time put things for the sensors: its frame (metres,
Z up), boxes carried through transforms, and seconds as the stage's time codes."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from usdforest.sensors.scene.scenetypes import LeafInstances, Shape


def moved_boxes(
    lo: np.ndarray, hi: np.ndarray, matrix: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes of boxes ``lo``/``hi`` (n, 3) moved by row-vector 4x4 transforms
    ``matrix`` (n, 4, 4): the centre moved, the half extents through the absolute linear
    part (the exact box of each moved box)."""
    rot = matrix[:, :3, :3]
    c = np.einsum("nj,njk->nk", (lo + hi) / 2, rot) + matrix[:, 3, :3]
    h = np.einsum("nj,njk->nk", (hi - lo) / 2, np.abs(rot))
    return c - h, c + h


def leaf_boxes(
    li: LeafInstances, shapes: tuple[Shape, ...], boxes: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes ``(lowers, uppers)``, each ``(n, 3)``, of leaf instances in their
    owner's space: each shape's box (or its box in ``boxes``, ``(shapes, 2, 3)``: over its
    turns) moved by its instance's transform."""
    if not len(li):
        return np.zeros((0, 3)), np.zeros((0, 3))
    if boxes is None:
        boxes = np.array([s.box for s in shapes], dtype=float).reshape(-1, 2, 3)
    box = np.asarray(boxes, dtype=float)[li.shape]  # (n, 2, 3)
    return moved_boxes(box[:, 0], box[:, 1], li.matrix)


def root_layer(stage_path: str | Path):
    """The ``Sdf.Layer`` at ``stage_path``, or None when it is no USD layer (opening the stage
    then names the problem)."""
    from pxr import Sdf

    try:
        return Sdf.Layer.FindOrOpen(str(stage_path))
    except Exception:
        return None


def stage_frame(stage_path: str | Path) -> np.ndarray:
    """The row-vector 4x4 from a stage's own units and axes to the sensors' frame (metres, Z
    up): ``metersPerUnit`` and ``upAxis`` as its root layer authors them (a Y-up stage is
    turned +90 degrees about X, so its +Y becomes +Z and its +Z becomes -Y); unauthored
    metadata is taken as usdforest writes it, metres and Z up, not USD's fallbacks."""
    m = np.eye(4)
    layer = root_layer(stage_path)
    if layer is None:
        return m
    root = layer.pseudoRoot
    if root.HasInfo("metersPerUnit"):
        m[:3, :3] *= float(root.GetInfo("metersPerUnit"))
    if root.HasInfo("upAxis") and str(root.GetInfo("upAxis")).upper() == "Y":
        m = m @ np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
    return m


def to_frame(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """``points (..., 3)`` in a stage's own units and axes, in the sensors' frame."""
    return np.asarray(points, dtype=float) @ frame[:3, :3] + frame[3, :3]


def stage_loop(stage) -> tuple[float, float | None]:
    """Where ``stage``'s animation starts (s) and, when its root layer says it loops
    (:func:`usdforest.usd.layers.time_range`), how long one loop is (s; else None)."""
    from usdforest.usd.layers import time_range

    start, end, _, loops = time_range(stage.GetRootLayer())
    return start, (end - start if loops and end > start else None)


def looped(seconds: float, loop: tuple[float, float | None]) -> float:
    """``seconds`` into an animation of ``loop`` (:func:`stage_loop`), wrapped into its first
    loop when it loops (USD itself holds the ends' values outside the time codes)."""
    start, period = loop
    t = float(seconds)
    return start + (t - start) % period if period else t


def animated(stage) -> bool:
    """Whether ``stage`` moves in time: it gives a time code range, or a layer it uses holds
    time samples (a hand-made host of a windy forest that gives no range moves too)."""
    return bool(stage.HasAuthoredTimeCodeRange()) or any(
        layer.ListAllTimeSamples() for layer in stage.GetUsedLayers()
    )


def stage_time(stage, seconds: float | None):
    """The ``Usd.TimeCode`` of ``seconds`` into ``stage``'s animation (``None``: default),
    wrapped into its loop when it loops (:func:`looped`)."""
    from pxr import Usd

    if seconds is None:
        return Usd.TimeCode.Default()
    return Usd.TimeCode(looped(seconds, stage_loop(stage)) * stage.GetTimeCodesPerSecond())

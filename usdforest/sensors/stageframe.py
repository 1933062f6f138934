"""Where a stage's own units, axes and time put things for the sensors: its frame (metres,
Z up), boxes carried through transforms, and seconds as the stage's time codes."""

from __future__ import annotations

from pathlib import Path

import numpy as np


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


def stage_frame(stage_path: str | Path) -> np.ndarray:
    """The row-vector 4x4 from a stage's own units and axes to the sensors' frame (metres, Z
    up): ``metersPerUnit`` and ``upAxis`` as its root layer authors them (a Y-up stage is
    turned +90 degrees about X, so its +Y becomes +Z and its +Z becomes -Y); unauthored
    metadata is taken as usdforest writes it, metres and Z up, not USD's fallbacks."""
    from pxr import Sdf

    m = np.eye(4)
    try:
        layer = Sdf.Layer.FindOrOpen(str(stage_path))
    except Exception:  # not USD: opening the stage names the problem
        return m
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


def stage_time(stage, seconds: float | None):
    """The ``Usd.TimeCode`` of ``seconds`` into ``stage``'s animation (``None``: default)."""
    from pxr import Usd

    if seconds is None:
        return Usd.TimeCode.Default()
    return Usd.TimeCode(float(seconds) * stage.GetTimeCodesPerSecond())

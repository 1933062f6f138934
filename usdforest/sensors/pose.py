"""Sensor poses: position and yaw, pitch, roll in degrees (sensor forward is +X)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import UsdForestError


@dataclass(frozen=True)
class Pose:
    """Position (m) and orientation: yaw about +Z (0 looks along +X, 90 along +Y), then pitch
    (positive tilts the sensor's forward axis up), then roll about the forward axis."""

    x: float
    y: float
    z: float
    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    def rotation(self) -> np.ndarray:
        """Column-vector rotation from the sensor frame to the world frame."""
        return rotations(np.array([self.yaw]), np.array([self.pitch]), np.array([self.roll]))[0]

    @property
    def forward(self) -> np.ndarray:
        return self.rotation()[:, 0]


def rotations(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``(n, 3, 3)`` column-vector rotations sensor -> world for angles in degrees: yaw about
    +Z, then pitch (positive turns the forward axis towards +Z), then roll about forward."""
    y, p, r = (np.radians(np.asarray(a, dtype=np.float64)) for a in (yaw, pitch, roll))
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    one, zero = np.ones_like(y), np.zeros_like(y)
    rz = np.stack([cy, -sy, zero, sy, cy, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    ry = np.stack([cp, zero, -sp, zero, one, zero, sp, zero, cp], -1).reshape(-1, 3, 3)
    rx = np.stack([one, zero, zero, zero, cr, -sr, zero, sr, cr], -1).reshape(-1, 3, 3)
    return rz @ ry @ rx


def parse_pose(text: str) -> Pose:
    """``x,y,z[,yaw,pitch,roll]`` -> :class:`Pose`."""
    try:
        v = [float(p) for p in text.split(",")]
    except ValueError:
        raise UsdForestError(
            f"--pose: expected numbers x,y,z[,yaw,pitch,roll], got {text!r}"
        ) from None
    if len(v) not in (3, 4, 5, 6):
        raise UsdForestError(
            f"--pose: expected 3 to 6 numbers x,y,z[,yaw,pitch,roll], got {len(v)}"
        )
    if not all(math.isfinite(x) for x in v) or max(abs(x) for x in v[:3]) > 1e8:
        raise UsdForestError(f"--pose: values must be finite (x, y, z within 1e8), got {text!r}")
    return Pose(*v)
